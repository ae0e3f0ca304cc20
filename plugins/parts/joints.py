"""Step 4, joints: a part's motions relative to its parent, fitted by a joint estimator, and its
state in every frame."""

from __future__ import annotations

import inspect
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from artclass_core import RunResult
from artclass_core.articulation import JointEstimate
from artclass_core.interfaces import JointEstimator

from .motions import _translation


def frame_states(
    n_frames: int, pairs: list[tuple[int, int]], deltas: np.ndarray, stds: np.ndarray, *, smoothness: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame states (n_frames,) and their standard deviations from pair differences
    ``q_j - q_i = deltas`` (with standard deviations ``stds``), by weighted least squares.

    Neighbouring frames are tied by ``q_{f-1} - 2 q_f + q_{f+1} = 0`` (constant speed) at
    ``smoothness`` times the weight of the best pair: this decides only what the pairs leave open (how
    the interleaved chains of pairs (i, i + k) sit relative to each other, and a part's motion while
    it was hidden), as the smoothest motion. States are relative to the first
    frame of any pair; NaN for frames no pair reaches.
    """
    seen = sorted({f for p in pairs for f in p})
    states, std = np.full(n_frames, np.nan), np.full(n_frames, np.nan)
    if not seen:
        return states, std
    frames = list(range(seen[0], seen[-1] + 1))  # frames between the pairs' are tied through too
    col = {f: c for c, f in enumerate(frames)}
    weights = 1.0 / np.maximum(np.asarray(stds, float), 1e-12)
    tie = smoothness * float(weights.max())
    A = np.zeros((len(pairs) + len(frames), len(frames)))
    y = np.zeros(len(A))
    for r, ((i, j), d, w) in enumerate(zip(pairs, deltas, weights)):
        A[r, col[j]], A[r, col[i]], y[r] = w, -w, d * w
    for r, c in enumerate(range(1, len(frames) - 1), start=len(pairs)):
        A[r, c - 1], A[r, c], A[r, c + 1] = tie, -2 * tie, tie
    A[-1, 0] = tie  # the first frame's state is 0
    q = np.linalg.lstsq(A, y, rcond=None)[0]
    cov = np.linalg.pinv(A.T @ A)
    rows = [col[f] for f in seen]
    states[seen] = q[rows] - q[0]
    std[seen] = np.sqrt(np.clip(np.diag(cov) + cov[0, 0] - 2 * cov[:, 0], 0, None))[rows]
    return states, std


def _pair_joint(
    relative: list[tuple[int, int, np.ndarray]],
    centre_m: np.ndarray,
    n_frames: int,
    *,
    estimator: JointEstimator,
    smoothness: float,
    reach_m: float | None = None,
) -> tuple[JointEstimate, int]:
    """The joint from a part's relative motions (i, j, motion in the base's first-frame coordinates)
    and the number of pairs it explains. The estimator sees the part's pose (origin ``centre_m``)
    moved by each relative motion and by its inverse, and unmoved: for a one-degree-of-freedom joint
    all lie on one path, ``exp(±Δq ξ)``; one pose per pair is independent. ``reach_m``: how far the
    object reaches from ``centre_m``."""
    start = _translation(centre_m)
    poses = np.stack(
        [start] + [M @ start for _, _, M in relative] + [np.linalg.inv(M) @ start for _, _, M in relative]
    )
    n = len(relative)
    estimate = estimate_joint(estimator, poses, n_independent=n, reach_m=reach_m)
    forward, backward = np.arange(1, n + 1), np.arange(n + 1, 2 * n + 1)
    explained = (
        estimate.inliers[forward]
        & estimate.inliers[backward]
        & np.isfinite(estimate.states[forward])
        & np.isfinite(estimate.states[backward])
    )
    keep = np.flatnonzero(explained) if estimate.type not in ("fixed", "free") else np.zeros(0, int)
    states = np.full(n_frames, np.nan)
    std = np.full(n_frames, np.nan)
    direction = estimate.axis_direction
    misfit = 0.0
    if len(keep):
        deltas = (estimate.states[forward[keep]] - estimate.states[backward[keep]]) / 2
        misfit = smooth_misfit(_pair_residuals(estimate, [relative[k][2] for k in keep], deltas, centre_m))
        spread = estimate.states_std if estimate.states_std is not None else np.ones(len(poses))
        pair_std = np.nan_to_num(np.hypot(spread[forward[keep]], spread[backward[keep]]) / 2, nan=1.0)
        states, std = frame_states(
            n_frames, [relative[k][:2] for k in keep], deltas, pair_std, smoothness=smoothness
        )
        if states[np.nanargmax(np.abs(states))] < 0:
            states, direction = -states, -direction  # rising states; the axis turns with them
    elif estimate.type == "fixed":
        states[sorted({f for i, j, _ in relative for f in (i, j)})] = 0.0
        std = np.where(np.isfinite(states), 0.0, np.nan)
    info = dict(
        estimate.info,
        n_pairs=n,
        n_pairs_explained=int(explained.sum()),
        n_poses_explained=float(estimate.inliers.sum() * n / len(poses)),  # independent ones
        smooth_misfit=misfit,
    )
    return JointEstimate(
        estimate.type,
        direction,
        estimate.axis_point_m,
        states,
        np.isfinite(states),
        estimate.axis_direction_std_rad,
        estimate.axis_point_std_m,
        std,
        estimate.scores,
        info,
    ), int(explained.sum())


def _pair_residuals(
    estimate: JointEstimate, motions: list[np.ndarray], deltas: np.ndarray, centre_m: np.ndarray
) -> np.ndarray:
    """How far each pair's relative motion (4, 4) is from the joint's motion over the pair's change of
    state ``deltas`` (K,): the part's centre ``centre_m`` moved by the difference (metres), then the
    rotation vector of the difference (radians), (K, 6)."""
    predicted = estimate.motion(deltas)
    error = np.linalg.inv(predicted) @ np.stack(motions)
    moved = error[:, :3, :3] @ centre_m + error[:, :3, 3] - centre_m
    return np.hstack([moved, Rotation.from_matrix(error[:, :3, :3]).as_rotvec()])


#: Pairs a joint must explain before its residuals are judged against their neighbours' (two
#: differences of neighbouring pairs, the fewest a median of them needs).
_MIN_NEIGHBOURS = 3


def smooth_misfit(residuals: np.ndarray) -> float:
    """How much of a joint's misfit is smooth in time, per pose: 0 when its residuals are noise.

    Parameters
    ----------
    residuals : ndarray, shape (K, 6)
        Each pair's position (metres) and rotation (radians) residual against the joint, pairs in
        the order of their frames.

    Returns
    -------
    float
        ``3 (rho_pos - 1) + 3 (rho_rot - 1)`` (each term at least 0), with rho the median squared
        residual over half the median squared difference of neighbouring pairs' residuals: the noise
        of two pairs is independent, so their difference has twice its variance; a path the joint
        does not follow (a part carried along a curve by a linkage, which keeps its orientation
        and is fitted as a slide) leaves residuals that neighbouring pairs share, small differences
        and a large rho. With the noise taken from the differences, rho - 1 per component is what
        the misfit adds to the chi-square of a pose. 0 for fewer than ``_MIN_NEIGHBOURS`` pairs.
    """
    residuals = np.asarray(residuals, float)
    if len(residuals) < _MIN_NEIGHBOURS:
        return 0.0
    steps = np.diff(residuals, axis=0)
    out = 0.0
    for part in (slice(0, 3), slice(3, 6)):
        spread = float(np.median(np.sum(residuals[:, part] ** 2, axis=1)))
        noise = float(np.median(np.sum(steps[:, part] ** 2, axis=1))) / 2
        if noise > 0:
            out += 3 * max(spread / noise - 1, 0.0)
    return out


def estimate_joint(estimator: JointEstimator, poses: np.ndarray, **evidence: Any) -> JointEstimate:
    """``estimator.estimate(poses, **evidence)``, leaving out the keywords (``n_independent``,
    ``reach_m``) that an estimator written before they existed does not take."""
    parameters = inspect.signature(estimator.estimate).parameters.values()
    if not any(p.kind is p.VAR_KEYWORD for p in parameters):
        taken = {p.name for p in parameters}
        evidence = {k: v for k, v in evidence.items() if k in taken}
    return estimator.estimate(poses, **evidence)


def _relative_motions(
    result: RunResult,
    child: dict[int, np.ndarray],
    parent: dict[int, np.ndarray],
    parent_poses: np.ndarray,
) -> list[tuple[int, int, np.ndarray]]:
    """(i, j, the child's motion relative to the parent) of each AM pair that found both, in the
    parent's coordinates at state 0: ``G_i^-1 Q^-1 P G_i`` with P and Q the pair's child and parent
    motions and G_i (``parent_poses[i]``) the parent's pose in frame i."""
    relative = []
    for pair, P in child.items():
        p = result.pairs[pair]
        G = parent_poses[p.i]
        if pair in parent and p.decision == "AM" and np.isfinite(G).all():
            relative.append((p.i, p.j, np.linalg.inv(G) @ np.linalg.inv(parent[pair]) @ P @ G))
    return relative
