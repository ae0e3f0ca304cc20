"""Projective data association: a moved point is compared with the target pixel it projects onto.

This is the association of KinectFusion (Newcombe et al. 2011) and of Open3D's RGB-D odometry: no
k-d tree, one image look-up per point. It gives both the point-to-plane ICP of any number of point
groups at once (:func:`icp`) and, for each motion hypothesis, what each moved point finds in the
target image (:func:`look_all`): the surface, something in front of it (occluded), nothing where it
should be (free space), or a surface that is not the object.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from artclass_core import ArtclassError, Cloud, Intrinsics

from .image import bounding_box, finite_depth, normal_map, valid_median, vertex_map

# Gauss-Newton damping, relative to the trace of the normal equations: keeps the step of a group whose
# points cannot fix all six degrees of freedom (a flat patch slides in its plane) small and unique.
_DAMPING = 1e-6
COARSE_THINNING = 4
# How far from the object's mask the target's distance image is exact (pixels).
NEAR_MASK_PX = 8
# The first robust fit keeps this share of its pairs, the closest.
_FIRST_SHARE = 0.66


@dataclass
class Target:
    """What the association looks up in the target frame (all images full-resolution)."""

    intrinsics: Intrinsics
    scene_m: np.ndarray  # (H, W) the whole frame's depth, 0 = none
    object_m: np.ndarray  # (H, W) the object's filtered depth, 0 outside it
    normals: np.ndarray  # (H, W, 3) normals of object_m's pixels, 0 = none
    # distance to the object's mask (0 inside) in the mask's box widened by NEAR_MASK_PX, whose
    # top-left pixel is outside_origin (row, column); inf beyond the box
    outside_px: np.ndarray
    outside_origin: tuple[int, int]
    covered: np.ndarray  # (H, W) bool: pixels a hand may cover (a point there is hidden); (0, 0): none

    @classmethod
    def of(cls, cloud: Cloud) -> Target:
        view = cloud.view
        if view is None or view.normals is None or view.mask is None:
            raise ArtclassError(
                "the dense registrar needs clouds that keep their image (pixels, normals and mask), "
                "as the 'image' preprocessor gives; use it, or a per-cell registrar"
            )
        covered = np.zeros((0, 0), bool) if view.covered is None else np.ascontiguousarray(view.covered, bool)
        return cls(
            view.intrinsics, view.scene_depth_m, view.depth_m, view.normals, *_outside(view.mask), covered
        )


def _outside(mask: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
    """Distance (pixels, float32) of each pixel to the mask, exact up to ``NEAR_MASK_PX``: in the mask's
    box widened by that, with the box's top-left pixel (row, column); every pixel beyond it is farther.
    An empty mask gives an empty box."""
    box = bounding_box(mask, margin_px=NEAR_MASK_PX)
    if box is None:
        return np.zeros((0, 0), np.float32), (0, 0)
    (v0, v1), (u0, u1) = box
    return cv2.distanceTransform((~mask[v0:v1, u0:u1]).astype(np.uint8), cv2.DIST_L2, 3), (v0, u0)


def look_all(
    motions: np.ndarray, points: np.ndarray, target: Target, *, reach_m: np.ndarray, off_object_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """What each source point, moved by each motion hypothesis, finds at its target pixel.

    Parameters
    ----------
    motions : (H, 4, 4) ``T_target_from_source`` of each hypothesis
    points : (N, 3) source points, metres
    target : the target frame
    reach_m : (N,) how far from the observed depth a point still counts as on a surface
    off_object_px : a point on a surface farther than this from the object's mask is off the object,
        or hidden where the target's ``covered`` pixels say a hand may cover the object

    Returns
    -------
    status : (H, N) int8, one of SURFACE, OCCLUDED, FREE_SPACE, OFF_OBJECT, UNSEEN
    residual_m : (H, N) float32, the point-to-plane (or, without a normal, along-the-ray) distance of
        the SURFACE points; NaN elsewhere
    """
    status = np.empty((len(motions), len(points)), np.int8)
    residual = np.empty((len(motions), len(points)), np.float32)
    kernels().look_kernel(
        np.ascontiguousarray(motions, np.float64),
        np.ascontiguousarray(points, np.float64),
        target.scene_m,
        target.object_m,
        target.normals,
        target.outside_px,
        *target.outside_origin,
        target.covered,
        _camera(target.intrinsics),
        np.ascontiguousarray(reach_m, np.float64),
        float(off_object_px),
        status,
        residual,
    )
    return status, residual


def flow_misfit(
    motions: np.ndarray, points: np.ndarray, flow_px: np.ndarray, across: np.ndarray, intrinsics: Intrinsics
) -> np.ndarray:
    """How far (pixels) from where optical flow took each point each motion projects it.

    Parameters
    ----------
    motions : (H, 4, 4) ``T_target_from_source`` of each hypothesis
    points : (N, 3) source points, metres
    flow_px, across : (N, 2) where the flow takes each point, and the direction across the edge at an
        edge point; NaN where unknown (see :mod:`.flow`)
    intrinsics : the target camera

    Returns
    -------
    (H, N) float32: the distance, or at an edge point its component across the edge; NaN where the
    flow is unknown
    """
    out = np.empty((len(motions), len(points)), np.float32)
    kernels().flow_kernel(
        np.ascontiguousarray(motions, np.float64),
        np.ascontiguousarray(points, np.float64),
        np.ascontiguousarray(flow_px, np.float64),
        np.ascontiguousarray(across, np.float64),
        _camera(intrinsics),
        out,
    )
    return out


def hypothesis_costs(
    residual_m: np.ndarray,
    status: np.ndarray,
    flow_px: np.ndarray,
    *,
    noise_m: float,
    flow_sigma_px: float,
    worst: float,
) -> np.ndarray:
    """Each point's cost (H, N) float32 under each hypothesis: its squared residual in units of
    ``noise_m`` and its squared flow misfit in units of ``flow_sigma_px``, each at most ``worst``;
    ``worst`` for a point sent into free space or off the object, half of it for one hidden or out
    of view; a NaN flow misfit adds nothing.

    Parameters
    ----------
    residual_m, flow_px : (H, N) float32, metres and pixels (NaN where unknown)
    status : (H, N) int8, one of SURFACE, OCCLUDED, FREE_SPACE, OFF_OBJECT, UNSEEN

    Notes
    -----
    One compiled pass, with numpy's arithmetic: each term is computed in the dtype numpy gives it
    (float32, or float64 when a scale is a NumPy float64), so the costs equal the numpy expression
    ``min((r / noise)^2, worst)`` etc. to the bit.
    """
    out = np.empty(residual_m.shape, np.float32)
    depth = np.result_type(residual_m, noise_m, worst).type
    flow = np.result_type(flow_px, flow_sigma_px, worst).type
    kernels().cost_kernel(
        np.ascontiguousarray(residual_m),
        np.ascontiguousarray(status),
        np.ascontiguousarray(flow_px),
        depth(noise_m),
        depth(worst),
        depth(worst / 2),
        flow(flow_sigma_px),
        flow(worst),
        out,
    )
    return out


def icp(
    points: np.ndarray,
    groups: np.ndarray,
    T: np.ndarray,
    target: Target,
    *,
    reach_m: list[float],
    min_points: int = 6,
    flow_px: np.ndarray | None = None,
    across: np.ndarray | None = None,
    metres_per_px: float = 0.0,
    index: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Projective point-to-plane ICP of several point groups at once, each with its own motion, with
    optical flow as a second term where it is known (as RGB-D odometry's hybrid term).

    Parameters
    ----------
    points : (N, 3) source points, metres
    groups : (M,) int in [0, G): the group of each point fitted (of each entry of ``index``)
    T : (G, 4, 4) initial ``T_target_from_source`` of each group
    target : the target frame
    reach_m : one correspondence distance per iteration (coarse to fine), metres
    min_points : a group with fewer correspondences keeps its motion for that iteration
    flow_px, across : (N, 2) where optical flow takes each point, and the direction across the edge at
        an edge point (compare along it only); NaN where unknown (see :mod:`.flow`)
    metres_per_px : how much one pixel of flow misfit weighs against one metre of depth misfit
        (depth noise / flow noise); 0 leaves the flow out
    index : (M,) int, optional: the points fitted are ``points[index]``, so that a point can be in
        several groups without copies of the points and their flow; every point once by default

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

    Coarse iterations (reach more than twice the last) use every ``COARSE_THINNING``-th point of a
    group that has points to spare: the coarse motion needs few, as an image pyramid's coarse levels.
    The loop over the points is compiled (Numba): one pass per iteration projects, looks up and sums
    each group's normal equations, where numpy makes a dozen temporary arrays of the points.
    """
    T = np.array(T, dtype=np.float64, copy=True)
    points = np.ascontiguousarray(points, np.float64)
    groups = np.ascontiguousarray(groups, np.int64)
    index = np.arange(len(points)) if index is None else np.ascontiguousarray(index, np.int64)
    centre = np.zeros((len(T), 3))
    thin = np.empty(len(index), np.bool_)
    kernels().group_centres(
        points, index, groups, COARSE_THINNING, 4 * COARSE_THINNING * min_points, centre, thin
    )
    use_flow = flow_px is not None and metres_per_px > 0
    unknown = np.full((len(points), 2), np.nan)
    inliers = np.zeros(len(T), np.int64)
    kernels().icp_kernel(
        points,
        index,
        groups,
        T,
        centre,
        thin,
        np.asarray(reach_m, np.float64),
        target.object_m,
        target.normals,
        _camera(target.intrinsics),
        np.ascontiguousarray(flow_px if use_flow else unknown, np.float64),
        np.ascontiguousarray(across if use_flow else unknown, np.float64),
        float(metres_per_px) if use_flow else 0.0,
        _DAMPING,
        int(min_points),
        inliers,
    )
    return T, inliers


@functools.cache
def kernels():
    """The compiled per-point loops (:mod:`._compiled`), imported on first use: importing Numba
    takes a few tenths of a second that a command which registers nothing need not wait for. The
    module is kept, so that the dozen calls of a pair do not each go through the import system."""
    from . import _compiled

    return _compiled


def warm_up() -> None:
    """Load the compiled loops: import them and run each once on a tiny frame, so that the first pair
    does not pay for loading Numba's cached machine code (a few tenths of a second per process)."""
    n, shape = 4, (8, 8)
    depth = np.full(shape, 0.5, np.float32)
    normals = np.zeros(shape + (3,), np.float32)
    normals[..., 2] = -1
    target = Target(
        Intrinsics(8.0, 8.0, 3.5, 3.5, width=8, height=8),
        depth,
        depth,
        normals,
        np.zeros(shape, np.float32),
        (0, 0),
        np.zeros((0, 0), bool),
    )
    points = np.column_stack([np.zeros((n, 2)), np.full(n, 0.5)])
    motions = np.eye(4)[None]
    look_all(motions, points, target, reach_m=np.full(n, 0.01), off_object_px=1.0)
    flow_misfit(motions, points, np.zeros((n, 2)), np.full((n, 2), np.nan), target.intrinsics)
    residual = np.zeros((1, n), np.float32)
    for noise in (0.001, np.float64(0.001)):  # float32 and float64 depth terms
        hypothesis_costs(
            residual, np.zeros((1, n), np.int8), residual, noise_m=noise, flow_sigma_px=1.0, worst=9.0
        )
    icp(
        points,
        np.zeros(n, np.int64),
        motions,
        target,
        reach_m=[0.01],
        flow_px=np.zeros((n, 2)),
        across=np.full((n, 2), np.nan),
        metres_per_px=0.001,
    )
    robust_kabsch(
        np.eye(3) + [0, 0, 0.5], np.eye(3) + [0, 0, 0.5], inlier_m=0.01, groups=np.zeros(3, np.int64)
    )
    kernels().distinct_kernel(motions[:, :3].copy(), np.eye(4), 0.001, np.empty(1, np.bool_))
    costs = np.zeros((2, n), np.float32)[:, np.ones(n, bool)]  # as selection has them: point by point
    kernels().totals_kernel(costs, np.empty(2, np.float32))
    kernels().savings_kernel(costs, costs[0].copy(), np.empty(2, np.float32))
    kernels().second_differences_kernel(np.zeros(shape), 1, 1, np.empty(2 * depth.size))
    valid_median(finite_depth(depth), depth > 0)
    normal_map(vertex_map(depth, target.intrinsics))


def _camera(intr: Intrinsics) -> np.ndarray:
    """fx, fy, cx, cy (pixels) as one array, for the compiled loops."""
    return np.array([intr.fx, intr.fy, intr.cx, intr.cy], np.float64)


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


def robust_kabsch(
    source: np.ndarray,
    target: np.ndarray,
    *,
    inlier_m: float,
    rounds: int = 3,
    groups: np.ndarray | None = None,
) -> np.ndarray:
    """:func:`kabsch` refitted on the pairs within ``inlier_m`` of the previous fit (the first fit
    drops the worst third), so that a few wrong matches do not pull the motion.

    Parameters
    ----------
    source, target : (N, 3) matched points, metres
    inlier_m : a pair this far apart (metres) under the previous fit still counts
    rounds : refits at most
    groups : (N,) int in [0, G), optional: fit each group of pairs on its own, all at once (every
        group in [0, G) needs at least 3 pairs)

    Returns
    -------
    (4, 4) ``T_target_from_source``, or (G, 4, 4) one per group when ``groups`` is given

    Notes
    -----
    The loop over the groups and their pairs is compiled (Numba): the seeds of a pair are a few
    dozen small groups, where numpy would spend its time on many small array operations.
    """
    one = groups is None
    groups = np.zeros(len(source), np.int64) if one else np.asarray(groups, np.int64)
    G = int(groups.max()) + 1 if len(groups) else 0
    order = np.argsort(groups, kind="stable")
    T = np.empty((G, 4, 4))
    kernels().robust_kabsch_kernel(
        np.ascontiguousarray(source[order], np.float64),
        np.ascontiguousarray(target[order], np.float64),
        np.searchsorted(groups[order], np.arange(G)),
        float(inlier_m),
        int(rounds),
        _FIRST_SHARE,
        T,
    )
    return T[0] if one else T
