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
def predict(xi, R0, t0, R, t, sigma_m, sigma_rad):
    """States (B, N) of the poses (R (N, 4), t (N, 3)) along twists ξ (B, 6) from the poses at state 0
    (R0 (B, 4), t0 (B, 3)), and the poses predicted at those states: rotations (B, N, 4), origins
    (B, N, 3). See :meth:`.models._Poses.project` for the projection."""
    B, N = xi.shape[0], R.shape[0]
    q_out = np.empty((B, N))
    R_out = np.empty((B, N, 4))
    t_out = np.empty((B, N, 3))
    ratio = (sigma_m / sigma_rad) ** 2
    for b in range(B):
        w0, w1, w2, v0, v1, v2 = xi[b, 0], xi[b, 1], xi[b, 2], xi[b, 3], xi[b, 4], xi[b, 5]
        p = (R0[b, 0], R0[b, 1], R0[b, 2], R0[b, 3])
        p_inv = (-p[0], -p[1], -p[2], p[3])
        o0, o1, o2 = t0[b, 0], t0[b, 1], t0[b, 2]
        # the twist about the part's origin, positions and angles weighed by their noise
        c = _cross(w0, w1, w2, o0, o1, o2)
        x3, x4, x5 = v0 + c[0], v1 + c[1], v2 + c[2]
        norm = ratio * (w0 * w0 + w1 * w1 + w2 * w2) + x3 * x3 + x4 * x4 + x5 * x5
        wv = _cross(w0, w1, w2, v0, v1, v2)
        wwv = _cross(w0, w1, w2, wv[0], wv[1], wv[2])
        w_len = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
        for n in range(N):
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
            q_out[b, n] = s
            # the joint's motion at that state (twist_exp), applied to the pose at state 0
            m = _from_rotvec(s * w0, s * w1, s * w2)
            angle = abs(s) * w_len
            if angle < 1e-4:
                a, e = 0.5 - angle**2 / 24, 1 / 6 - angle**2 / 120
            else:
                a, e = (1 - math.cos(angle)) / angle**2, (angle - math.sin(angle)) / angle**3
            rot = _mul(m, p)
            for i in range(4):
                R_out[b, n, i] = rot[i]
            u = _cross(m[0], m[1], m[2], o0, o1, o2)
            uu = _cross(m[0], m[1], m[2], u[0], u[1], u[2])
            s2, s3 = a * s * s, e * s * s * s
            t_out[b, n, 0] = o0 + 2 * (m[3] * u[0] + uu[0]) + s * v0 + s2 * wv[0] + s3 * wwv[0]
            t_out[b, n, 1] = o1 + 2 * (m[3] * u[1] + uu[1]) + s * v1 + s2 * wv[1] + s3 * wwv[1]
            t_out[b, n, 2] = o2 + 2 * (m[3] * u[2] + uu[2]) + s * v2 + s2 * wv[2] + s3 * wwv[2]
    return q_out, R_out, t_out


@njit(cache=True, nogil=True)
def residuals(R, t, R_hat, t_hat, sigma_m, sigma_rad):
    """Normalised residuals (B, N, 6) of predicted poses (R_hat (B, N, 4), t_hat (B, N, 3)) against
    the observed ones (R (N, 4), t (N, 3)): origin displacement, then rotation vector."""
    B, N = R_hat.shape[0], R.shape[0]
    out = np.empty((B, N, 6))
    for b in range(B):
        for n in range(N):
            r = _rotvec(
                _mul(
                    (-R[n, 0], -R[n, 1], -R[n, 2], R[n, 3]),
                    (R_hat[b, n, 0], R_hat[b, n, 1], R_hat[b, n, 2], R_hat[b, n, 3]),
                )
            )
            for i in range(3):
                out[b, n, i] = (t_hat[b, n, i] - t[n, i]) / sigma_m
                out[b, n, 3 + i] = r[i] / sigma_rad
    return out


def warm_up() -> None:
    """Load the compiled loops (Numba's cached machine code, or compile it) with the argument types of
    a fit's calls, so that the first fit does not pay for it."""
    R, t = np.array([[0.0, 0.0, 0.0, 1.0]]), np.zeros((1, 3))
    _, R_hat, t_hat = predict(np.zeros((1, 6)), R, t, R, t, 1.0, 1.0)
    residuals(R, t, R_hat, t_hat, 1.0, 1.0)
