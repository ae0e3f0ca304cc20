"""The compiled (Numba) loop of a joint fit: every pose's state along a twist, the pose the joint
predicts at that state, and its residual, one pass over the poses where numpy makes several dozen
small temporary arrays. A least-squares fit evaluates it a few hundred times; it is the same
arithmetic as :func:`.models.twist_log`, :func:`.models.twist_exp` and the quaternion helpers there
(the tests check one against the other). Quaternions are (x, y, z, w)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _cross(a0, a1, a2, b0, b1, b2):
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@njit(cache=True, nogil=True)
def _mul(a, b):
    """The product a b of quaternions given as 4-tuples."""
    c = _cross(a[0], a[1], a[2], b[0], b[1], b[2])
    return (
        a[3] * b[0] + b[3] * a[0] + c[0],
        a[3] * b[1] + b[3] * a[1] + c[1],
        a[3] * b[2] + b[3] * a[2] + c[2],
        a[3] * b[3] - (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]),
    )


@njit(cache=True, nogil=True)
def _rotvec(q):
    """The rotation vector, angle in [0, pi], of a quaternion."""
    s = -1.0 if q[3] < 0 else 1.0
    x, y, z, w = s * q[0], s * q[1], s * q[2], s * q[3]
    sin_half = math.sqrt(x * x + y * y + z * z)
    f = 2.0 if sin_half < 1e-9 else 2 * math.atan2(sin_half, w) / sin_half
    return x * f, y * f, z * f


@njit(cache=True, nogil=True)
def _from_rotvec(x, y, z):
    angle = math.sqrt(x * x + y * y + z * z)
    half_sinc = 0.5 - angle**2 / 48 if angle < 1e-6 else math.sin(angle / 2) / angle
    return x * half_sinc, y * half_sinc, z * half_sinc, math.cos(angle / 2)


@njit(cache=True, nogil=True)
def _predict_into(xi, p, o, R, t, sigma_m, sigma_rad, q_out, R_out, t_out):
    """The states (N,) of the poses (R (N, 4), t (N, 3)) along one twist ξ (6,) from the pose at
    state 0 (quaternion p, origin o), and the poses predicted at those states, written into q_out,
    R_out (N, 4) and t_out (N, 3). See :func:`.models._predict` for the projection."""
    ratio = (sigma_m / sigma_rad) ** 2
    w0, w1, w2, v0, v1, v2 = xi[0], xi[1], xi[2], xi[3], xi[4], xi[5]
    p_inv = (-p[0], -p[1], -p[2], p[3])
    o0, o1, o2 = o[0], o[1], o[2]
    # the twist about the part's origin, positions and angles weighed by their noise
    c = _cross(w0, w1, w2, o0, o1, o2)
    x3, x4, x5 = v0 + c[0], v1 + c[1], v2 + c[2]
    norm = ratio * (w0 * w0 + w1 * w1 + w2 * w2) + x3 * x3 + x4 * x4 + x5 * x5
    wv = _cross(w0, w1, w2, v0, v1, v2)
    wwv = _cross(w0, w1, w2, wv[0], wv[1], wv[2])
    w_len = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    for n in range(R.shape[0]):
        # the relative motion's twist (twist_log), projected on the joint's
        r = _rotvec(_mul((R[n, 0], R[n, 1], R[n, 2], R[n, 3]), p_inv))
        d0, d1, d2 = t[n, 0] - o0, t[n, 1] - o1, t[n, 2] - o2
        theta = math.sqrt(r[0] ** 2 + r[1] ** 2 + r[2] ** 2)
        if theta < 1e-4:
            k = 1 / 12
        else:
            k = (1 - theta * math.sin(theta) / (2 * (1 - math.cos(theta)))) / theta**2
        rd = _cross(r[0], r[1], r[2], d0, d1, d2)
        rrd = _cross(r[0], r[1], r[2], rd[0], rd[1], rd[2])
        l3, l4, l5 = (
            d0 - 0.5 * rd[0] + k * rrd[0],
            d1 - 0.5 * rd[1] + k * rrd[1],
            d2 - 0.5 * rd[2] + k * rrd[2],
        )
        num = ratio * (r[0] * w0 + r[1] * w1 + r[2] * w2) + l3 * x3 + l4 * x4 + l5 * x5
        s = num / norm if norm > 0 else num * 0.0
        q_out[n] = s
        # the joint's motion at that state (twist_exp), applied to the pose at state 0
        m = _from_rotvec(s * w0, s * w1, s * w2)
        angle = abs(s) * w_len
        if angle < 1e-4:
            a, e = 0.5 - angle**2 / 24, 1 / 6 - angle**2 / 120
        else:
            a, e = (1 - math.cos(angle)) / angle**2, (angle - math.sin(angle)) / angle**3
        rot = _mul(m, p)
        for i in range(4):
            R_out[n, i] = rot[i]
        u = _cross(m[0], m[1], m[2], o0, o1, o2)
        uu = _cross(m[0], m[1], m[2], u[0], u[1], u[2])
        s2, s3 = a * s * s, e * s * s * s
        t_out[n, 0] = o0 + 2 * (m[3] * u[0] + uu[0]) + s * v0 + s2 * wv[0] + s3 * wwv[0]
        t_out[n, 1] = o1 + 2 * (m[3] * u[1] + uu[1]) + s * v1 + s2 * wv[1] + s3 * wwv[1]
        t_out[n, 2] = o2 + 2 * (m[3] * u[2] + uu[2]) + s * v2 + s2 * wv[2] + s3 * wwv[2]


@njit(cache=True, nogil=True)
def _residuals_into(R, t, R_hat, t_hat, sigma_m, sigma_rad, out):
    """The normalised residuals (N, 6) of predicted poses against observed ones, written into out."""
    for n in range(R.shape[0]):
        r = _rotvec(
            _mul(
                (-R[n, 0], -R[n, 1], -R[n, 2], R[n, 3]),
                (R_hat[n, 0], R_hat[n, 1], R_hat[n, 2], R_hat[n, 3]),
            )
        )
        for i in range(3):
            out[n, i] = (t_hat[n, i] - t[n, i]) / sigma_m
            out[n, 3 + i] = r[i] / sigma_rad


@njit(cache=True, nogil=True)
def predict(xi, R0, t0, R, t, sigma_m, sigma_rad):
    """States (B, N) of the poses (R (N, 4), t (N, 3)) along twists ξ (B, 6) from the poses at state 0
    (R0 (B, 4), t0 (B, 3)), and the poses predicted at those states: rotations (B, N, 4), origins
    (B, N, 3)."""
    B, N = xi.shape[0], R.shape[0]
    q_out = np.empty((B, N))
    R_out = np.empty((B, N, 4))
    t_out = np.empty((B, N, 3))
    for b in range(B):
        _predict_into(xi[b], R0[b], t0[b], R, t, sigma_m, sigma_rad, q_out[b], R_out[b], t_out[b])
    return q_out, R_out, t_out


@njit(cache=True, nogil=True)
def residuals(R, t, R_hat, t_hat, sigma_m, sigma_rad):
    """Normalised residuals (B, N, 6) of predicted poses (R_hat (B, N, 4), t_hat (B, N, 3)) against
    the observed ones (R (N, 4), t (N, 3)): origin displacement, then rotation vector."""
    out = np.empty((R_hat.shape[0], R.shape[0], 6))
    for b in range(R_hat.shape[0]):
        _residuals_into(R, t, R_hat[b], t_hat[b], sigma_m, sigma_rad, out[b])
    return out


# the joint models, as :class:`.models._Shape` names them
FIXED, PRISMATIC, REVOLUTE, SCREW = 0, 1, 2, 3


@njit(cache=True, nogil=True)
def fit_residuals(x, model, start, basis, axis_point, R0, t0, R, t, sigma_m, sigma_rad):
    """What a fit's least squares minimises, (B, 6 N + gauge), at parameter vectors x (B, n_joint + 6),
    in one pass: see :meth:`.models._Fit.residuals`. ``model`` is one of FIXED, PRISMATIC, REVOLUTE
    and SCREW; ``start`` (6,), ``basis`` (2, 3) and ``axis_point`` (3,) are the model's starting
    twist, step directions and axis point (:class:`.models._Shape`), and R0 (4,) and t0 (3,) the pose
    at state 0 that x corrects."""
    n_joint = (0, 2, 4, 6)[model]
    n_gauge = (0, 1, 1, 2)[model]
    B, N = x.shape[0], R.shape[0]
    out = np.empty((B, 6 * N + n_gauge))
    xi, p, o = np.zeros(6), np.empty(4), np.empty(3)
    q, R_hat, t_hat = np.empty(N), np.empty((N, 4)), np.empty((N, 3))
    # the gauge: the slide of the pose at state 0 along the joint, in noise sigmas
    c = _cross(start[0], start[1], start[2], t0[0], t0[1], t0[2])
    along = np.array(
        [
            start[0] / sigma_rad,
            start[1] / sigma_rad,
            start[2] / sigma_rad,
            (c[0] + start[3]) / sigma_m,
            (c[1] + start[4]) / sigma_m,
            (c[2] + start[5]) / sigma_m,
        ]
    )
    along_len = math.sqrt(np.sum(along * along))
    for b in range(B):
        g = x[b]
        if model == SCREW:
            size = 0.0
            for i in range(6):
                xi[i] = start[i] + g[i]
                size += xi[i] * xi[i]
            xi /= math.sqrt(size)
        elif model != FIXED:
            first = 3 if model == PRISMATIC else 0
            d = (
                start[first] + g[0] * basis[0, 0] + g[1] * basis[1, 0],
                start[first + 1] + g[0] * basis[0, 1] + g[1] * basis[1, 1],
                start[first + 2] + g[0] * basis[0, 2] + g[1] * basis[1, 2],
            )
            size = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
            d = (d[0] / size, d[1] / size, d[2] / size)
            if model == PRISMATIC:
                xi[3], xi[4], xi[5] = d
            else:
                point = (
                    axis_point[0] + g[2] * basis[0, 0] + g[3] * basis[1, 0],
                    axis_point[1] + g[2] * basis[0, 1] + g[3] * basis[1, 1],
                    axis_point[2] + g[2] * basis[0, 2] + g[3] * basis[1, 2],
                )
                xi[0], xi[1], xi[2] = d
                xi[3], xi[4], xi[5] = _cross(point[0], point[1], point[2], d[0], d[1], d[2])
        p[:] = _mul(_from_rotvec(g[n_joint], g[n_joint + 1], g[n_joint + 2]), (R0[0], R0[1], R0[2], R0[3]))
        for i in range(3):
            o[i] = t0[i] + g[n_joint + 3 + i]
        _predict_into(xi, p, o, R, t, sigma_m, sigma_rad, q, R_hat, t_hat)
        _residuals_into(R, t, R_hat, t_hat, sigma_m, sigma_rad, out[b, : 6 * N].reshape((N, 6)))
        if n_gauge:
            out[b, 6 * N] = np.sum(g[n_joint : n_joint + 6] * along)
        if model == SCREW:
            out[b, 6 * N + 1] = np.sum(g[:6] * start) * along_len
    return out


def warm_up() -> None:
    """Load the compiled loops (Numba's cached machine code, or compile it) with the argument types of
    a fit's calls, so that the first fit does not pay for it."""
    R, t = np.array([[0.0, 0.0, 0.0, 1.0]]), np.zeros((1, 3))
    _, R_hat, t_hat = predict(np.zeros((1, 6)), R, t, R, t, 1.0, 1.0)
    residuals(R, t, R_hat, t_hat, 1.0, 1.0)
    fit_residuals(np.zeros((1, 6)), FIXED, np.zeros(6), np.eye(2, 3), np.zeros(3), R[0], t[0], R, t, 1.0, 1.0)
