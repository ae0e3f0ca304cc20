"""Projective data association: a moved point is compared with the target pixel it projects onto.

This is the association of KinectFusion (Newcombe et al. 2011) and of Open3D's RGB-D odometry: no
k-d tree, one image look-up per point. It gives both the point-to-plane ICP of any number of point
groups at once (:func:`icp`) and, for a motion hypothesis, what each moved point finds in the
target image (:func:`look`): the surface, something in front of it (occluded), nothing where it
should be (free space), or a surface that is not the object.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import csr_matrix

from artclass_core import ArtclassError, Cloud, Intrinsics
from artclass_core.types import FREE_SPACE, OCCLUDED, OFF_OBJECT, SURFACE, UNSEEN

# Gauss-Newton damping, relative to the trace of the normal equations: keeps the step of a group whose
# points cannot fix all six degrees of freedom (a flat patch slides in its plane) small and unique.
_DAMPING = 1e-6
COARSE_THINNING = 4
_UPPER = np.triu_indices(6)


@dataclass
class Target:
    """What the association looks up in the target frame (all images full-resolution)."""

    intrinsics: Intrinsics
    scene_m: np.ndarray        # (H, W) the whole frame's depth, 0 = none
    object_m: np.ndarray       # (H, W) the object's filtered depth, 0 outside it
    normals: np.ndarray        # (H, W, 3) normals of object_m's pixels, 0 = none
    outside_px: np.ndarray     # (H, W) distance to the object's mask, 0 inside

    @classmethod
    def of(cls, cloud: Cloud) -> Target:
        view = cloud.view
        if view is None or view.normals is None or view.mask is None:
            raise ArtclassError("the dense registrar needs clouds that keep their image (pixels, normals and mask), "
                                "as the 'image' preprocessor gives; use it, or a per-cell registrar")
        outside = cv2.distanceTransform((~view.mask).astype(np.uint8), cv2.DIST_L2, 3)
        return cls(view.intrinsics, view.scene_depth_m, view.depth_m, view.normals, outside)


def _project(points: np.ndarray, intr: Intrinsics, shape: tuple[int, int]):
    """Nearest pixel (column, row) of each point, and whether it falls in the image in front of the camera."""
    z = points[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(intr.fx * points[:, 0] / z + intr.cx)
        v = np.rint(intr.fy * points[:, 1] / z + intr.cy)
    inside = (z > 0) & (u >= 0) & (u < shape[1]) & (v >= 0) & (v < shape[0])
    return np.where(inside, u, 0).astype(np.intp), np.where(inside, v, 0).astype(np.intp), inside


def _surface_residual(moved: np.ndarray, target: Target, u: np.ndarray, v: np.ndarray):
    """Signed point-to-plane distance of each moved point to the object surface at its pixel, and
    whether the pixel has that surface (depth and normal)."""
    z = target.object_m[v, u]
    n = target.normals[v, u]
    has = (z > 0) & n.any(axis=1)
    K = target.intrinsics
    y = np.column_stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z])
    return np.einsum("ij,ij->i", moved - y, n), has


def look(moved: np.ndarray, target: Target, *, reach_m: np.ndarray, off_object_px: float):
    """What each moved point finds at its target pixel.

    Parameters
    ----------
    moved : (N, 3) source points moved by a hypothesis, metres
    target : the target frame
    reach_m : (N,) how far from the observed depth a point still counts as on a surface
    off_object_px : a point on a surface farther than this from the object's mask is off the object

    Returns
    -------
    status : (N,) int8, one of SURFACE, OCCLUDED, FREE_SPACE, OFF_OBJECT, UNSEEN
    residual_m : (N,) float32, the point-to-plane (or, without a normal, along-the-ray) distance of the
        SURFACE points; NaN elsewhere
    """
    u, v, inside = _project(moved, target.intrinsics, target.scene_m.shape)
    scene = np.where(inside, target.scene_m[v, u], 0)
    seen = inside & (scene > 0)
    gap = scene - moved[:, 2]
    status = np.full(len(moved), UNSEEN, np.int8)
    status[seen & (gap < -reach_m)] = OCCLUDED
    status[seen & (gap > reach_m)] = FREE_SPACE
    near = seen & (np.abs(gap) <= reach_m)
    off = near & (target.outside_px[v, u] > off_object_px)
    status[off] = OFF_OBJECT
    on = near & ~off
    status[on] = SURFACE
    plane, has = _surface_residual(moved, target, u, v)
    residual = np.where(on, np.where(has, plane, -gap), np.nan).astype(np.float32)
    return status, residual


def _rotations(omega: np.ndarray) -> np.ndarray:
    """Rotation matrices (G, 3, 3) of rotation vectors (G, 3) (Rodrigues)."""
    out = np.empty((len(omega), 3, 3))
    for g, w in enumerate(omega):
        out[g] = cv2.Rodrigues(w)[0]
    return out


def _moved(T: np.ndarray, groups: np.ndarray, points: np.ndarray, keep: np.ndarray | None = None) -> np.ndarray:
    """Each point moved by its group's motion (only the ``keep`` ones, if given)."""
    if keep is not None:
        groups, points = groups[keep], points[keep]
    return np.einsum("nij,nj->ni", T[groups, :3, :3], points) + T[groups, :3, 3]


def _flow_rows(moved: np.ndarray, groups: np.ndarray, flow_px: np.ndarray, across: np.ndarray,
               intr: Intrinsics, metres_per_px: float):
    """Optical-flow residuals of moved points as rows like point-to-plane ones: for each known flow,
    the residual (metres-equivalent) and the gradient of the projected pixel (per metre of motion) of
    the column and the row, or, at an edge point, of the component across the edge."""
    known = np.isfinite(flow_px[:, 0]) & (moved[:, 2] > 0)
    q, f, e, g = moved[known], flow_px[known], across[known], groups[known]
    z = q[:, 2]
    du = intr.fx * q[:, 0] / z + intr.cx - f[:, 0]
    dv = intr.fy * q[:, 1] / z + intr.cy - f[:, 1]
    zero = np.zeros_like(z)
    gu = np.column_stack([intr.fx / z, zero, -intr.fx * q[:, 0] / z ** 2])
    gv = np.column_stack([zero, intr.fy / z, -intr.fy * q[:, 1] / z ** 2])
    edge = np.isfinite(e[:, 0])
    full = ~edge
    en = np.nan_to_num(e)
    r = np.concatenate([du[full], dv[full], (du * en[:, 0] + dv * en[:, 1])[edge]])
    grad = np.concatenate([gu[full], gv[full], (gu * en[:, :1] + gv * en[:, 1:])[edge]])
    at = np.concatenate([q[full], q[full], q[edge]])
    return r * metres_per_px, grad * metres_per_px, at, np.concatenate([g[full], g[full], g[edge]])


def icp(points: np.ndarray, groups: np.ndarray, T: np.ndarray, target: Target, *, reach_m: list[float],
        min_points: int = 6, flow_px: np.ndarray | None = None, across: np.ndarray | None = None,
        metres_per_px: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Projective point-to-plane ICP of several point groups at once, each with its own motion, with
    optical flow as a second term where it is known (as RGB-D odometry's hybrid term).

    Parameters
    ----------
    points : (N, 3) source points, metres
    groups : (N,) int in [0, G): the group of each point
    T : (G, 4, 4) initial ``T_target_from_source`` of each group
    target : the target frame
    reach_m : one correspondence distance per iteration (coarse to fine), metres
    min_points : a group with fewer correspondences keeps its motion for that iteration
    flow_px, across : (N, 2) where optical flow takes each point, and the direction across the edge at
        an edge point (compare along it only); NaN where unknown (see :mod:`.flow`)
    metres_per_px : how much one pixel of flow misfit weighs against one metre of depth misfit
        (depth noise / flow noise); 0 leaves the flow out

    Returns
    -------
    T : (G, 4, 4) refined motions
    inliers : (G,) correspondences of each group in the last iteration

    Notes
    -----
    Each group is linearised about its own centroid: about the camera a metre away, a few degrees of
    rotation of a small patch become centimetres of coupled translation that one Gauss-Newton step
    gets wrong. Residuals are weighted with Tukey's biweight at the iteration's reach. Depth alone
    cannot fix a motion that keeps a surface in place (a cylinder turning about its axis, a plane
    sliding in itself); the flow on its texture can, so both terms are solved together.
    """
    T = np.array(T, dtype=np.float64, copy=True)
    G = len(T)
    count = np.bincount(groups, minlength=G)
    centre = np.stack([np.bincount(groups, points[:, d], minlength=G) for d in range(3)], 1) / np.maximum(count, 1)[:, None]
    use_flow = flow_px is not None and metres_per_px > 0
    # Coarse iterations (reach more than twice the last) use every COARSE_THINNING-th point of a group
    # that has points to spare: the coarse motion needs few, as an image pyramid's coarse levels.
    order = np.argsort(groups, kind="stable")
    rank = np.empty(len(groups), int)
    rank[order] = np.arange(len(groups)) - np.repeat(np.cumsum(count) - count, count)
    thin = (rank % COARSE_THINNING == 0) | (count[groups] < 4 * COARSE_THINNING * min_points)
    inliers = np.zeros(G, int)
    for reach in reach_m:
        if reach > 2 * reach_m[-1] and not thin.all():
            moved, g_all, sub = _moved(T, groups, points, thin), groups[thin], thin
        else:
            moved, g_all, sub = _moved(T, groups, points), groups, slice(None)
        u, v, inside = _project(moved, target.intrinsics, target.scene_m.shape)
        r, has = _surface_residual(moved, target, u, v)
        ok = inside & has & (np.abs(r) < reach)
        r, grad, at, g = r[ok], target.normals[v[ok], u[ok]].astype(np.float64), moved[ok], g_all[ok]
        inliers = np.bincount(g, minlength=G)
        if use_flow:
            fr, fgrad, fat, fg = _flow_rows(moved, g_all, flow_px[sub], across[sub], target.intrinsics, metres_per_px)
            near = np.abs(fr) < reach
            r, grad = np.concatenate([r, fr[near]]), np.concatenate([grad, fgrad[near]])
            at, g = np.concatenate([at, fat[near]]), np.concatenate([g, fg[near]])
        arm = at - (T[g, :3, :3] @ centre[g][..., None])[..., 0] - T[g, :3, 3]
        J = np.concatenate([np.cross(arm, grad), grad], axis=1)          # (M, 6)
        w = np.square(1 - np.square(r / reach))                           # Tukey biweight
        # Per-group sums of w J^T J (its 21 distinct entries) and w J^T r: one sparse (G, M) by dense
        # (M, 27) product.
        terms = np.concatenate([J[:, _UPPER[0]] * J[:, _UPPER[1]], J * r[:, None]], axis=1)
        sums = csr_matrix((w, (g, np.arange(len(g)))), shape=(G, len(g))) @ terms
        A = np.zeros((G, 6, 6))
        A[:, _UPPER[0], _UPPER[1]] = sums[:, :21]
        A[:, _UPPER[1], _UPPER[0]] = sums[:, :21]
        b = sums[:, 21:]
        solvable = np.bincount(g, minlength=G) >= min_points
        if not solvable.any():
            break
        A = A[solvable] + _DAMPING * np.einsum("gii->g", A[solvable])[:, None, None] * np.eye(6) + 1e-12 * np.eye(6)
        x = -np.linalg.solve(A, b[solvable][..., None])[..., 0]
        R = _rotations(x[:, :3])
        step = np.tile(np.eye(4), (len(x), 1, 1))
        step[:, :3, :3] = R
        # A turn about the group's moved centroid c' followed by a shift: x -> R (x - c') + c' + t.
        moved_centre = (T[solvable, :3, :3] @ centre[solvable][..., None])[..., 0] + T[solvable, :3, 3]
        step[:, :3, 3] = moved_centre - (R @ moved_centre[..., None])[..., 0] + x[:, 3:]
        T[solvable] = step @ T[solvable]
    return T, inliers


def kabsch(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The rigid motion (4, 4) that best maps ``source`` (N, 3) onto ``target`` (N, 3), least squares."""
    w = np.ones(len(source)) if weights is None else weights
    w = w / w.sum()
    cs, ct = w @ source, w @ target
    H = (source - cs).T @ ((target - ct) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, ct - R @ cs
    return T


def robust_kabsch(source: np.ndarray, target: np.ndarray, *, inlier_m: float, rounds: int = 3) -> np.ndarray:
    """:func:`kabsch` refitted on the pairs within ``inlier_m`` of the previous fit (the first fit
    drops the worst third), so that a few wrong matches do not pull the motion."""
    keep = np.ones(len(source), bool)
    T = kabsch(source, target)
    for _ in range(rounds):
        err = np.linalg.norm(source @ T[:3, :3].T + T[:3, 3] - target, axis=1)
        new = err <= max(inlier_m, np.quantile(err, 0.66) if keep.all() else inlier_m)
        if new.sum() < 3 or (new == keep).all():
            break
        keep = new
        T = kabsch(source[keep], target[keep])
    return T
