"""Joint models fitted to a part's poses in its parent's frame, one chosen by BIC.

A one-degree-of-freedom joint moves the part by ``exp(q ξ)``, a screw motion with a fixed twist ξ
(6-vector: angular part ω, linear part v) and a state q per frame:

- ``fixed``: no motion;
- ``prismatic``: ξ = (0, d), d a unit direction, q in metres;
- ``revolute``: ξ = (u, c × u), u the unit axis direction and c a point on the axis, q in radians;
- ``screw``: any ξ (the general one-degree-of-freedom motion, with revolute and prismatic as
  special cases), the fallback.

The part's pose in frame i is predicted as ``exp(q_i ξ) P0``, with ``P0`` its pose at state 0; the
residual of a pose is the displacement of the part's origin (metres) and the rotation between the
predicted and the observed pose (radians), each divided by its noise level.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from artclass_core import InputError, Params, param
from artclass_core.interfaces import JointEstimate

from . import _compiled

MODELS = ("fixed", "prismatic", "revolute", "screw")

#: Residual evaluations a least-squares fit may take (a revolute model of a straight path drifts its
#: axis away without end; the path's prismatic model wins anyway).
MAX_EVALUATIONS = 50

#: Steps of the fixed-point iteration of the mean orientation, and the step (radians) at which it stops.
KARCHER_STEPS, KARCHER_TOLERANCE_RAD = 20, 1e-10


@dataclass(frozen=True)
class BICJointParams(Params):
    sigma_position_m: float | None = param(
        None,
        unit="m",
        bounds=(1e-5, 1.0),
        auto="from the residuals of the screw model, within min/max_sigma_position_m",
        help="Noise of the part's position in one pose (standard deviation per axis).",
    )
    sigma_orientation_rad: float | None = param(
        None,
        unit="rad",
        bounds=(1e-5, 1.0),
        auto="from the residuals of the screw model, within min/max_sigma_orientation_rad",
        help="Noise of the part's orientation in one pose (standard deviation per axis of the rotation vector).",
    )
    min_sigma_position_m: float = param(
        0.0005,
        unit="m",
        bounds=(1e-6, 0.1),
        help="Lowest position noise the estimate may assume: the depth resolution.",
    )
    min_sigma_orientation_rad: float = param(
        0.002, unit="rad", bounds=(1e-6, 0.5), help="Lowest orientation noise the estimate may assume."
    )
    max_sigma_position_m: float = param(
        0.01,
        unit="m",
        bounds=(1e-5, 1.0),
        help="Highest position noise the estimate may assume: a part whose "
        "poses scatter more about every joint moves freely.",
    )
    max_sigma_orientation_rad: float = param(
        0.09,
        unit="rad",
        bounds=(1e-5, 1.0),
        help="Highest orientation noise the estimate may assume (0.09 rad is about 5 degrees): a "
        "part whose orientations scatter more about the general joint (the screw) moves freely.",
    )
    outlier_level: float = param(
        0.999,
        unit="fraction",
        bounds=(0.5, 0.999999),
        help="A pose beyond this quantile of the chi-square distribution (6 dof) of the "
        "screw model's residuals is an outlier, left out of every model's score.",
    )
    min_inlier_fraction: float = param(
        0.5,
        unit="fraction",
        bounds=(0.0, 1.0),
        help="When the chosen model explains fewer of the poses than this, the "
        "part's motion is reported as free.",
    )
    n_hypotheses: int = param(
        48,
        unit="pairs",
        bounds=(1, 10_000),
        help="Pose pairs drawn to start each model (least median of squares).",
    )
    distinct_sigmas: float = param(
        3.0,
        unit="sigma",
        bounds=(0.0, 100.0),
        help="A model is chosen only where what sets it apart shows by more than this many "
        "noise sigmas over the video: a revolute joint's turn, a prismatic joint's "
        "travel, a screw's turn and its slide along the axis.",
    )
    axis_reach: float = param(
        2.0,
        unit="1",
        bounds=(0.5, 1000.0),
        help="A revolute or screw axis must pass within this many times the object's reach "
        "(how far its points reach from the part's origin) of the part: a joint lies on the "
        "object, and the points seen may be only part of it.",
    )
    seed: int = param(0, unit="1", bounds=(0, 2**31 - 1), help="Seed of the drawing of pose pairs.")


# -- rotations as unit quaternions (x, y, z, w), the layout of scipy's Rotation.as_quat --------------
# scipy's Rotation does the same with about 0.1 ms of overhead a call; a fit evaluates its residuals
# a few hundred times with a dozen rotation operations each, so the few operations it needs are here.


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Products a b of quaternions (..., 4), broadcast."""
    av, aw, bv, bw = a[..., :3], a[..., 3:], b[..., :3], b[..., 3:]
    return np.concatenate(
        [aw * bv + bw * av + _cross(av, bv), aw * bw - np.sum(av * bv, -1, keepdims=True)], -1
    )


def _quat_inv(q: np.ndarray) -> np.ndarray:
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


def _quat_from_rotvec(v: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) of rotation vectors (..., 3), radians."""
    angle = _norm(v)
    small = angle < 1e-6
    half_sinc = np.where(small, 0.5 - angle**2 / 48, np.sin(angle / 2) / np.where(small, 1.0, angle))
    return np.concatenate([v * half_sinc, np.cos(angle / 2)], -1)


def _quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3), angle in [0, pi], of quaternions (..., 4)."""
    q = np.where(q[..., 3:] < 0, -q, q)
    sin_half = _norm(q[..., :3])
    angle = 2 * np.arctan2(sin_half, q[..., 3:])
    small = sin_half < 1e-9
    return q[..., :3] * np.where(small, 2.0, angle / np.where(small, 1.0, sin_half))


def _quat_apply(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectors (..., 3) rotated by quaternions (..., 4)."""
    u, w = q[..., :3], q[..., 3:]
    uv = _cross(u, v)
    return v + 2 * (w * uv + _cross(u, uv))


# -- rigid motions ---------------------------------------------------------------------------------------


def _hat(w: np.ndarray) -> np.ndarray:
    """Cross-product matrices, shape (..., 3, 3), of vectors (..., 3)."""
    z = np.zeros(w.shape[:-1])
    return np.stack(
        [
            np.stack([z, -w[..., 2], w[..., 1]], -1),
            np.stack([w[..., 2], z, -w[..., 0]], -1),
            np.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


def _series_coefficients(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(1 - cos θ) / θ² and (θ - sin θ) / θ³, with their series near 0."""
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24, (1 - np.cos(t)) / t**2)
    b = np.where(small, 1 / 6 - theta**2 / 120, (t - np.sin(t)) / t**3)
    return a, b


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of vectors (..., 3), broadcast (numpy's own is slow on small arrays)."""
    first = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out = np.empty(first.shape + (3,))
    out[..., 0] = first
    np.subtract(a[..., 2] * b[..., 0], a[..., 0] * b[..., 2], out=out[..., 1])
    np.subtract(a[..., 0] * b[..., 1], a[..., 1] * b[..., 0], out=out[..., 2])
    return out


def _norm(v: np.ndarray) -> np.ndarray:
    """Lengths (..., 1) of vectors (..., k) (numpy's ``linalg.norm`` does the same with more overhead)."""
    return np.sqrt(np.sum(v * v, axis=-1, keepdims=True))


def twist_exp(xi: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotations as quaternions (..., N, 4) and translations (..., N, 3) of the screw motions
    exp(q_i ξ), for twists ξ (..., 6) and states q (..., N) (leading dimensions broadcast)."""
    w, v = xi[..., None, :3], xi[..., None, 3:]
    q = np.asarray(q)[..., None]
    R = _quat_from_rotvec(q * w)
    a, b = _series_coefficients(np.abs(q) * _norm(w))
    wv = _cross(w, v)
    return R, q * v + a * q**2 * wv + b * q**3 * _cross(w, wv)


def twist_log(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Twists (..., 6) with exp(ξ) = (R, t), for rotations as quaternions (..., 4) and translations
    (..., 3)."""
    w = _quat_to_rotvec(R)
    theta = _norm(w)
    small = theta < 1e-4
    th = np.where(small, 1.0, theta)
    c = np.where(small, 1 / 12, (1 - th * np.sin(th) / (2 * (1 - np.cos(th)))) / th**2)
    wt = _cross(w, t)  # V^-1 t = t - (w x t) / 2 + c w x (w x t)
    return np.concatenate([w, t - 0.5 * wt + c * _cross(w, wt)], axis=-1)


def _tangent_basis(u: np.ndarray) -> np.ndarray:
    """Two unit vectors (2, 3) perpendicular to the unit vector ``u`` and to each other."""
    helper = np.eye(3)[np.argmin(np.abs(u))]
    e1 = _cross(u, helper)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, _cross(u, e1)])


# -- the models ------------------------------------------------------------------------------------------


@dataclass
class _Shape:
    """One model's joint parameters as small steps g from a starting twist (so least squares sees no
    constraint): a unit direction moves in its tangent plane, an axis point across the axis."""

    name: str
    start: np.ndarray  # starting twist (6,)
    anchor: np.ndarray | None = None  # an axis position is varied across the axis at this point

    @property
    def n_joint(self) -> int:
        return {"fixed": 0, "prismatic": 2, "revolute": 4, "screw": 6}[self.name]

    @property
    def dof(self) -> int:
        """Joint parameters that change the motion (the screw's twist has a free scale)."""
        return {"fixed": 0, "prismatic": 2, "revolute": 4, "screw": 5}[self.name]

    @functools.cached_property
    def _basis(self) -> np.ndarray:
        """Directions (2, 3) of the steps across the start's axis (revolute) or direction (prismatic)."""
        return _tangent_basis(self.start[3:] if self.name == "prismatic" else self.start[:3])

    @functools.cached_property
    def _axis_point(self) -> np.ndarray:
        """The revolute start's axis point nearest the origin, or nearest the anchor."""
        w0, v0 = self.start[:3], self.start[3:]
        c = _cross(w0, v0)
        return c if self.anchor is None else c + w0 * float((self.anchor - c) @ w0)

    @functools.cached_property
    def compiled(self) -> tuple:
        """The model as :func:`._compiled.fit_residuals` takes it: its number, starting twist, step
        directions and axis point."""
        model = ("fixed", "prismatic", "revolute", "screw").index(self.name)
        basis = self._basis if self.name in ("prismatic", "revolute") else np.zeros((2, 3))
        point = self._axis_point if self.name == "revolute" else np.zeros(3)
        return model, _rows(self.start), _rows(basis), _rows(point)

    def twist(self, g: np.ndarray) -> np.ndarray:
        """The twists (..., 6) of steps g (..., n_joint)."""
        if self.name == "fixed":
            return np.zeros(g.shape[:-1] + (6,))
        if self.name == "screw":
            xi = self.start + g
            return xi / _norm(xi)
        if self.name == "prismatic":
            d = self.start[3:] + g[..., :2] @ self._basis
            return np.concatenate([np.zeros_like(d), d / _norm(d)], axis=-1)
        u = self.start[:3] + g[..., :2] @ self._basis
        u = u / _norm(u)
        return np.concatenate([u, _cross(self._axis_point + g[..., 2:4] @ self._basis, u)], axis=-1)


def _start_twists(name: str, xi: np.ndarray, displacement: np.ndarray) -> np.ndarray:
    """The model's starting twists (K, 6) from pairs' relative motions ξ (K, 6) and origin
    displacements (K, 3); NaN where the pair shows none of the model's motion."""
    with np.errstate(invalid="ignore", divide="ignore"):
        if name == "fixed":
            return np.zeros_like(xi)
        if name == "prismatic":
            return np.concatenate([np.zeros_like(displacement), displacement / _norm(displacement)], axis=-1)
        if name == "screw":
            return xi / _norm(xi)
        w = xi[:, :3]
        theta = _norm(w)
        u = w / theta
        c = _cross(w, xi[:, 3:]) / theta**2  # the point of the screw axis nearest the origin
        return np.concatenate([u, _cross(c, u)], axis=-1)


@dataclass
class _Poses:
    """The known poses, and the noise levels their residuals are divided by."""

    R: np.ndarray  # (N, 4), quaternions
    t: np.ndarray  # (N, 3), the part's origin
    sigma_m: float
    sigma_rad: float

    def __post_init__(self):
        self.R, self.t = _rows(self.R), _rows(self.t)  # once, not at every evaluation

    def residuals(self, R_hat: np.ndarray, t_hat: np.ndarray) -> np.ndarray:
        """Normalised residuals (..., N, 6) of predicted poses (..., N, 4) and (..., N, 3): origin
        displacement, then rotation vector."""
        lead = R_hat.shape[:-2]
        out = _compiled.residuals(
            self.R,
            self.t,
            _rows(R_hat.reshape(-1, *R_hat.shape[-2:])),
            _rows(t_hat.reshape(-1, *t_hat.shape[-2:])),
            self.sigma_m,
            self.sigma_rad,
        )
        return out.reshape(lead + out.shape[1:])

    def state_std(self, xi: np.ndarray, t_hat: np.ndarray) -> np.ndarray:
        """One standard deviation (N,) of each projected state: the noise over the speed of the pose
        along the joint, at the predicted part origins (N, 3)."""
        speed_m = np.linalg.norm(_cross(xi[:3], t_hat) + xi[3:], axis=1)
        return 1.0 / np.sqrt((speed_m / self.sigma_m) ** 2 + (np.linalg.norm(xi[:3]) / self.sigma_rad) ** 2)


@dataclass
class _Fit:
    """A model's joint steps and pose at state 0 (a correction of R0, t0); the states follow by projection."""

    shape: _Shape
    x: np.ndarray  # joint steps (n_joint), then the pose correction (6)
    R0: np.ndarray  # (4,), quaternion
    t0: np.ndarray
    chi2: float = np.inf
    jac: np.ndarray | None = None

    def __post_init__(self):
        self.R0, self.t0 = _rows(self.R0), _rows(self.t0)

    def unpack(self, x: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(twist, R0, t0) from parameter vectors (..., n_joint + 6)."""
        x = self.x if x is None else x
        n = self.shape.n_joint
        return (
            self.shape.twist(x[..., :n]),
            _quat_mul(_quat_from_rotvec(x[..., n : n + 3]), self.R0),
            self.t0 + x[..., n + 3 : n + 6],
        )

    def predict(self, poses: _Poses, x: np.ndarray | None = None):
        """States (..., N) and predicted poses: rotations (..., N, 4) as quaternions, origins (..., N, 3)."""
        return _predict(poses, *self.unpack(x))

    def pose_residuals(self, x: np.ndarray, poses: _Poses) -> np.ndarray:
        """Normalised residuals (..., N, 6) of the poses."""
        _, R_hat, t_hat = self.predict(poses, x)
        return poses.residuals(R_hat, t_hat)

    def residuals(self, x: np.ndarray, poses: _Poses) -> np.ndarray:
        """What least squares minimises (..., M), in one compiled pass: the pose residuals, flattened
        (:meth:`pose_residuals`), then the gauge residuals. These are zero along the directions no
        pose can see, so that least squares has a unique optimum: the slide of the pose at state 0
        along the joint, ``x[n_joint:] · (ω / σ_rad, (ω × t0 + v) / σ_m)`` for the start's twist
        (ω, v), and the screw twist's scale, ``x[:n_joint] · start`` times that direction's length.

        The slide is measured in noise sigmas, as the pose residuals are, and the scale as stiffly:
        a gauge that costs as little as a step in the parameters' own units (radians, metres) is so
        soft next to the poses that the trust-region fit of the robust loss wanders along it for
        dozens of steps, dragging the poses' states with it."""
        out = _compiled.fit_residuals(
            _rows(x.reshape(-1, x.shape[-1])),
            *self.shape.compiled,
            self.R0,
            self.t0,
            poses.R,
            poses.t,
            poses.sigma_m,
            poses.sigma_rad,
        )
        return out.reshape(x.shape[:-1] + out.shape[-1:])

    def jacobian(self, x: np.ndarray, poses: _Poses) -> np.ndarray:
        """The Jacobian (M, P) of :meth:`residuals` at x (P,) by forward differences, all P steps in
        one batched evaluation with x itself (the steps of scipy's ``2-point`` scheme)."""
        step = np.sqrt(np.finfo(float).eps) * np.where(x >= 0, 1.0, -1.0) * np.maximum(1.0, np.abs(x))
        step = (x + step) - x
        f = self.residuals(x + np.vstack([np.zeros_like(x), np.diag(step)]), poses)  # x, then the steps
        return ((f[1:] - f[0]) / step[:, None]).T


def _predict(poses: _Poses, xi: np.ndarray, R0: np.ndarray, t0: np.ndarray):
    """States (..., N) of the poses along twists ξ (..., 6) from poses at state 0 (R0 (..., 4), t0
    (..., 3)), and the poses the joint predicts at those states: rotations (..., N, 4), origins
    (..., N, 3).

    A pose's state is the twist of its motion relative to the pose at state 0, about the part's
    origin t0, projected on ξ (about the same point), positions and angles weighed by their noise:
    exact for poses on the joint's path, 0 for a zero twist."""
    lead = xi.shape[:-1]
    q, R_hat, t_hat = _compiled.predict(
        _rows(xi.reshape(-1, 6)),
        _rows(np.broadcast_to(R0, lead + (4,)).reshape(-1, 4)),
        _rows(np.broadcast_to(t0, lead + (3,)).reshape(-1, 3)),
        poses.R,
        poses.t,
        poses.sigma_m,
        poses.sigma_rad,
    )
    n = len(poses.t)
    return q.reshape(lead + (n,)), R_hat.reshape(lead + (n, 4)), t_hat.reshape(lead + (n, 3))


def _rows(a: np.ndarray) -> np.ndarray:
    """``a`` as a writeable C-contiguous float array, the one type the compiled loops are compiled for
    (a read-only view, such as a broadcast, is copied)."""
    return np.require(a, dtype=float, requirements=["C", "W"])


def _best_start(name: str, poses: _Poses, pairs: np.ndarray) -> _Fit | None:
    """Least median of squares over starts from the drawn pose pairs (a, b): the model's twist closest
    to the pair's relative motion, and pose a as the pose at state 0."""
    R_rel = _quat_mul(poses.R[pairs[:, 1]], _quat_inv(poses.R[pairs[:, 0]]))
    xis = twist_log(R_rel, poses.t[pairs[:, 1]] - _quat_apply(R_rel, poses.t[pairs[:, 0]]))
    starts = _start_twists(name, xis, poses.t[pairs[:, 1]] - poses.t[pairs[:, 0]])
    valid = np.isfinite(starts).all(axis=1)
    if not valid.any():
        return None
    starts, first = starts[valid], pairs[valid, 0]
    # every start at once, with the pose of its pair's first frame as the pose at state 0
    _, R_hat, t_hat = _predict(poses, starts, poses.R[first], poses.t[first])
    score = np.median(np.sum(poses.residuals(R_hat, t_hat) ** 2, axis=-1), axis=-1)
    score = np.where(np.isnan(score), np.inf, score)
    if not np.isfinite(score).any():
        return None
    best = int(np.argmin(score))
    shape = _Shape(name, starts[best])
    return _Fit(shape, np.zeros(shape.n_joint + 6), poses.R[first[best]], poses.t[first[best]])


def _fixed(poses: _Poses) -> _Fit:
    """The fixed model's least-squares fit in closed form: the mean origin, and the mean orientation
    (the Karcher mean, which minimises the squared rotation angles to the poses; its fixed-point
    iteration from the chordal mean converges in a few steps)."""
    aligned = np.where(poses.R @ poses.R[0] < 0, -1.0, 1.0)[:, None] * poses.R
    R0 = aligned.sum(axis=0) / np.linalg.norm(aligned.sum(axis=0))
    for _ in range(KARCHER_STEPS):
        step = _quat_to_rotvec(_quat_mul(_quat_inv(R0), poses.R)).mean(axis=0)
        R0 = _quat_mul(R0, _quat_from_rotvec(step))
        if np.linalg.norm(step) < KARCHER_TOLERANCE_RAD:
            break
    fit = _Fit(_Shape("fixed", np.zeros(6)), np.zeros(6), R0, poses.t.mean(axis=0))
    fit.chi2 = float(np.sum(fit.pose_residuals(fit.x, poses) ** 2))
    return fit


def _refine(fit: _Fit, poses: _Poses, *, robust: bool) -> _Fit:
    """Least squares over the joint's parameters and the pose at state 0: Levenberg-Marquardt, or the
    trust-region method with a Cauchy loss when some poses may be outliers."""
    method = dict(method="trf", tr_solver="exact", loss="cauchy") if robust else dict(method="lm")
    result = least_squares(
        fit.residuals,
        fit.x,
        jac=fit.jacobian,
        args=(poses,),
        ftol=1e-5,
        xtol=1e-6,
        max_nfev=MAX_EVALUATIONS,
        **method,
    )
    out = _Fit(fit.shape, result.x, fit.R0, fit.t0)
    out.chi2 = float(np.sum(out.pose_residuals(result.x, poses) ** 2))
    out.jac = result.jac
    return out


def _recentred(fit: _Fit, poses: _Poses) -> _Fit:
    """The same fit with its steps folded into the start, so the parameters are 0 at the optimum and
    the axis point is varied at the part (the covariance of the steps is then that of the axis
    direction and of the axis position at the part), with its Jacobian there (the optimum is already
    found: a new least-squares run would only repeat it)."""
    xi, R0, t0 = fit.unpack()
    out = _Fit(_Shape(fit.shape.name, xi, anchor=t0), np.zeros(fit.shape.n_joint + 6), R0, t0, chi2=fit.chi2)
    out.jac = out.jacobian(out.x, poses)
    return out


# -- noise and outliers ----------------------------------------------------------------------------------


def _noise_levels(
    per_pose: np.ndarray, poses: _Poses, *, n_fitted: float, share: float, params: BICJointParams
) -> tuple[float, float, bool]:
    """Noise levels (m, rad) from the normalised residuals (N, 6) of the general model: the median
    squared position and rotation error against the median of chi-square with 3 degrees of freedom
    (robust to up to half the poses being outliers), scaled up for the ``n_fitted`` parameters that
    took part of the noise out of the ``share`` of the residuals that are independent, kept between
    the bounds unless given; and whether the orientations scatter beyond their bound (unless given)."""
    n_residuals = share * per_pose.size
    scale = np.sqrt(n_residuals / max(n_residuals - n_fitted, 1) / chi2.median(3))
    sigma_m = poses.sigma_m * scale * np.sqrt(np.median(np.sum(per_pose[:, :3] ** 2, axis=1)))
    sigma_rad = poses.sigma_rad * scale * np.sqrt(np.median(np.sum(per_pose[:, 3:] ** 2, axis=1)))
    scattered = params.sigma_orientation_rad is None and sigma_rad > params.max_sigma_orientation_rad
    sigma_m = float(np.clip(sigma_m, params.min_sigma_position_m, params.max_sigma_position_m))
    sigma_rad = float(np.clip(sigma_rad, params.min_sigma_orientation_rad, params.max_sigma_orientation_rad))
    return params.sigma_position_m or sigma_m, params.sigma_orientation_rad or sigma_rad, scattered


def _subset(poses: _Poses, keep: np.ndarray, sigma_m: float, sigma_rad: float) -> _Poses:
    return _Poses(poses.R[keep], poses.t[keep], sigma_m, sigma_rad)


def _draw_pairs(n: int, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` distinct pose pairs (a, b), a != b, or all of them when there are fewer."""
    all_pairs = np.argwhere(~np.eye(n, dtype=bool))  # (a, b) in row order
    if len(all_pairs) <= count:
        return all_pairs
    return all_pairs[np.sort(rng.choice(len(all_pairs), count, replace=False))]


# -- the estimate ----------------------------------------------------------------------------------------


def fit_joint(
    poses: np.ndarray,
    *,
    n_independent: int | None = None,
    reach_m: float | None = None,
    params: BICJointParams = BICJointParams(),
) -> JointEstimate:
    """Fit the fixed, prismatic, revolute and screw models to a part's poses and choose one by BIC.

    Parameters
    ----------
    poses : ndarray, shape (N, 4, 4)
        The part's pose in its parent's frame in each frame (``poses[i]`` maps part coordinates to
        parent coordinates, metres; the part's origin is a point of the part, e.g. its centroid).
        A frame whose pose is unknown is NaN.
    n_independent : int, optional
        How many of the known poses carry independent errors (default: all of them). When each
        measurement is given as several poses (a relative motion and its inverse), the chi-square,
        the BIC and the uncertainties count ``n_independent`` poses' worth of evidence, not N.
    reach_m : float, optional
        How far the object's points reach from the part's origin (metres). A joint lies where the
        part meets its parent, on the object: a revolute or screw axis that passes farther than
        ``params.axis_reach`` times this from the part's origin is not considered (a slide whose poses
        turn by noise can fit a hinge far off the object). None: no bound.
    params : BICJointParams

    Returns
    -------
    JointEstimate
        The chosen model, its axis in the parent's frame, the state per frame relative to the first
        known frame (radians or metres, NaN where unknown or an outlier), one standard deviation of
        each, and the BIC of every model in ``scores``.

    Raises
    ------
    InputError
        If ``poses`` is not (N, 4, 4), fewer than 3 poses are known, or ``n_independent`` is not
        between 1 and the number of known poses.

    Notes
    -----
    After Sturm, Stachniss & Burgard, "A probabilistic framework for learning kinematic models of
    articulated objects" (JAIR 41, 2011) and their ROS ``articulation_models`` package: every model
    predicts the part's pose from a state, the residual is the position and orientation error between
    predicted and observed pose under Gaussian noise (their ``sigma_position``, ``sigma_orientation``),
    the models start from minimal samples (here pose pairs, scored by least median of squares in the
    spirit of their MLESAC), are refined by non-linear least squares, and
    ``BIC = -2 log L + k log n`` chooses among them (n poses, k parameters), among the models whose
    distinguishing motion the poses show above the noise (``distinct_sigmas``): a revolute joint that
    turns less than the orientation noise is a slide, a screw that slides less than the position
    noise along its axis is a hinge. The screw, which they do not have, is a fallback: chosen only
    when the best of the others leaves residuals beyond the noise (chi-square test at
    ``outlier_level``) and the screw's BIC is lower. Three choices differ from theirs: (1) the
    per-frame states count in k, so a one-degree-of-freedom model that only absorbs noise (one
    residual component per pose) does not beat ``fixed``; (2) instead of a per-model inlier/outlier
    mixture, the poses the general screw model cannot
    explain (beyond the ``outlier_level`` quantile of chi-square with 6 degrees of freedom) are left
    out of every model's score, so all models are compared on the same poses; (3) a revolute joint,
    which holds the prismatic as its limit (the axis at infinity), is chosen over it only when the
    likelihood ratio test at ``outlier_level`` says so, not on BIC alone, which over a few poses lets a
    far-off axis fit a slide's orientation noise. With
    ``n_independent`` = m of N known poses, every pose counts m / N of an independent one (the
    chi-square and the number of poses in the BIC and in the degrees of freedom are scaled by m / N,
    the variances by N / m), as for m poses each given N / m times. The noise levels are
    the screw model's residual RMS unless given. Where that RMS exceeds
    ``max_sigma_orientation_rad``, the motion is ``free`` (their free-body alternative): a part's
    orientation, registered from hundreds of points of a few centimetres, errs by a degree or two,
    and poses that turn more than 5 degrees off every one-degree-of-freedom path follow none. So is
    a motion of which the chosen model explains fewer than ``min_inlier_fraction`` of the poses.
    Uncertainties are one standard deviation from the inverse of JᵀJ of the chosen model at its
    optimum.
    """
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise InputError(f"joint poses must have shape (N, 4, 4), got {poses.shape}")
    known = np.flatnonzero(np.isfinite(poses).all(axis=(1, 2)))
    if len(known) < 3:
        raise InputError(f"a joint needs at least 3 known poses, got {len(known)}")
    if n_independent is not None and not 1 <= n_independent <= len(known):
        raise InputError(
            f"n_independent must be between 1 and the {len(known)} known poses, got {n_independent}"
        )
    share = (n_independent or len(known)) / len(known)  # each pose's share of an independent one
    rng = np.random.default_rng(params.seed)
    observed = _Poses(
        Rotation.from_matrix(poses[known, :3, :3]).as_quat(),
        poses[known, :3, 3],
        params.sigma_position_m or params.min_sigma_position_m,
        params.sigma_orientation_rad or params.min_sigma_orientation_rad,
    )
    pairs = _draw_pairs(len(known), params.n_hypotheses, rng)

    # 1. the general model, robustly: noise levels and outliers
    start = _best_start("screw", observed, pairs) or _best_start("fixed", observed, pairs)
    general = _refine(start, observed, robust=True)
    sigma_m, sigma_rad, scattered = _noise_levels(
        general.pose_residuals(general.x, observed),
        observed,
        n_fitted=_n_params(general.shape, share * len(known)),
        share=share,
        params=params,
    )
    limit = chi2.ppf(params.outlier_level, 6)
    scaled = _subset(observed, np.ones(len(known), bool), sigma_m, sigma_rad)
    inlier = np.sum(general.pose_residuals(general.x, scaled) ** 2, axis=1) <= limit
    fitted = _subset(observed, inlier, sigma_m, sigma_rad)
    inlier_pairs = _draw_pairs(int(inlier.sum()), params.n_hypotheses, rng)

    # 2. every model on the same poses, scored by BIC
    n = share * len(fitted.t)  # independent poses
    log_norm = 3 * np.log(2 * np.pi * sigma_m**2) + 3 * np.log(2 * np.pi * sigma_rad**2)
    fits, scores = {}, {}
    for name in MODELS:
        if name == "fixed":
            fits[name] = _fixed(fitted)
        else:
            start = _best_start(name, fitted, inlier_pairs)
            if start is None:
                continue
            fits[name] = _refine(start, fitted, robust=False)
        scores[name] = share * fits[name].chi2 + n * log_norm + _n_params(fits[name].shape, n) * np.log(n)
    shown = [
        name
        for name in scores
        if _shows_itself(fits[name], fitted, params.distinct_sigmas)
        and (reach_m is None or _axis_distance(fits[name]) <= params.axis_reach * reach_m)
    ]
    chosen = min([name for name in shown if name != "screw"] or ["fixed"], key=scores.get)
    # a slide is a hinge with its axis at infinity: the hinge is kept only where it lowers the
    # chi-square by more than its extra parameters do from noise alone (the likelihood ratio test at
    # outlier_level); BIC's log n per parameter is too little over a few poses
    if chosen == "revolute" and "prismatic" in shown:
        extra = fits["revolute"].shape.dof - fits["prismatic"].shape.dof
        if share * (fits["prismatic"].chi2 - fits["revolute"].chi2) <= chi2.ppf(params.outlier_level, extra):
            chosen = "prismatic"
    # the screw is the fallback: only when the simpler joint does not explain the poses within the
    # noise (its chi-square beyond the outlier_level quantile) and the screw pays for itself by BIC
    dof = max(6 * n - _n_params(fits[chosen].shape, n), 1)
    if (
        "screw" in shown
        and scores["screw"] < scores[chosen]
        and share * fits[chosen].chi2 > chi2.ppf(params.outlier_level, dof)
    ):
        chosen = "screw"

    # 3. the chosen model's parameters and their uncertainty
    best = _recentred(fits[chosen], fitted)
    return _estimate(
        best,
        known=known,
        inlier=inlier,
        n_frames=len(poses),
        fitted=fitted,
        scores=scores,
        share=share,
        params=params,
        free=scattered,
        info=dict(
            sigma_position_m=float(sigma_m),
            sigma_orientation_rad=float(sigma_rad),
            n_known=int(len(known)),
            n_outliers=int((~inlier).sum()),
            n_independent=float(share * len(known)),
        ),
    )


def _shows_itself(fit: _Fit, poses: _Poses, factor: float) -> bool:
    """Whether the poses show what sets the model apart by more than ``factor`` noise sigmas over the
    video: a turn (revolute, screw), a travel (prismatic) and a slide along the axis (screw)."""
    if fit.shape.name == "fixed":
        return True
    xi, R0, t0 = fit.unpack()
    q = _predict(poses, xi, R0, t0)[0]
    span = float(np.ptp(q)) if len(q) else 0.0
    w = np.linalg.norm(xi[:3])
    turn, slide = span * w, span * (abs(float(xi[:3] @ xi[3:])) / w if w > 0 else np.linalg.norm(xi[3:]))
    if fit.shape.name == "prismatic":
        return slide > factor * poses.sigma_m
    if fit.shape.name == "revolute":
        return turn > factor * poses.sigma_rad
    return turn > factor * poses.sigma_rad and slide > factor * poses.sigma_m


def _axis_distance(fit: _Fit) -> float:
    """How far (metres) the axis of a revolute or screw fit passes from the part's origin at state 0
    (0 for the other models, which have no axis)."""
    if fit.shape.name not in ("revolute", "screw"):
        return 0.0
    xi, _, t0 = fit.unpack()
    w, v = xi[:3], xi[3:]
    turn = float(w @ w)
    if turn < 1e-12:
        return np.inf
    offset = t0 - _cross(w, v) / turn  # from the axis point nearest the origin to the part's origin
    return float(np.linalg.norm(offset - (offset @ w) / turn * w))


def _n_params(shape: _Shape, n_poses: float) -> float:
    """BIC's k: the pose at state 0 (6), the joint's own parameters, and a state per independent
    pose but one."""
    return 6 + shape.dof + (n_poses - 1 if shape.name != "fixed" else 0)


def _estimate(
    fit: _Fit,
    *,
    known: np.ndarray,
    inlier: np.ndarray,
    n_frames: int,
    fitted: _Poses,
    scores: dict,
    share: float,
    params: BICJointParams,
    free: bool,
    info: dict,
) -> JointEstimate:
    xi, R0, t0 = fit.unpack()
    name = fit.shape.name
    q, _, t_hat = fit.predict(fitted)
    q_std = fitted.state_std(xi, t_hat) if name != "fixed" else np.zeros(len(q))
    q = q - q[0]  # relative to the first pose the model explains
    std = np.sqrt(np.clip(np.diag(np.linalg.pinv(share * fit.jac.T @ fit.jac)), 0.0, None))
    direction = point = None
    dir_std = point_std = float("nan")
    if name in ("revolute", "screw"):
        w = xi[:3]
        scale = np.linalg.norm(w)
        direction, q, q_std = w / scale, q * scale, q_std * scale
        point = _cross(w, xi[3:]) / scale**2
        point = point + direction * float((t0 - point) @ direction)  # nearest the part at state 0
        if name == "screw":
            info["pitch_m_per_rad"] = float(w @ xi[3:] / scale**2)
        else:
            dir_std, point_std = float(np.hypot(*std[:2])), float(np.hypot(*std[2:4]))
    elif name == "prismatic":
        direction, point = xi[3:], t0
        dir_std = float(np.hypot(*std[:2]))
    if direction is not None and q[np.argmax(np.abs(q))] < 0:
        direction, q = -direction, -q  # positive states: the part moves along +axis
    states, states_std = np.full(n_frames, np.nan), np.full(n_frames, np.nan)
    inliers = np.zeros(n_frames, bool)
    inliers[known[inlier]] = True
    states[inliers], states_std[inliers] = q, q_std
    joint_type = "free" if free or inlier.mean() < params.min_inlier_fraction else name
    if joint_type == "free":
        direction = point = None
        states[:], states_std[:] = np.nan, np.nan
    return JointEstimate(
        joint_type,
        direction,
        point,
        states,
        inliers,
        dir_std,
        point_std,
        states_std,
        {k: float(v) for k, v in scores.items()},
        info,
    )
