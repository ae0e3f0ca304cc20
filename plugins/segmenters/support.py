"""Scene background from depth alone: the depth range and the large planes (table, floor, wall).

Shared by the ``depth_threshold`` and ``u2net`` segmenters. A pixel is *background* when its depth
is outside ``[near_m, far_m]``, or when it lies on, or behind (seen from the camera), one of the
large planes of the scene: the support plane the objects stand on (points below the table, such as
the floor beyond its edge, are behind it) and a second large plane such as a wall behind the table.

Planes are found by RANSAC on the valid depth back-projected on a coarse pixel grid (every
``stride``-th pixel), with a seeded generator, then refitted by least squares on their inliers; the
full-resolution test is one multiply-add per pixel against precomputed camera rays.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from artclass_core import Intrinsics, Params, param

from ._compiled import all_finite, height_kernel, plane_moments, range_kernel, region_stats, strided_points

__all__ = [
    "BackgroundParams",
    "Plane",
    "fit_planes",
    "background_mask",
    "above_planes",
    "range_mask",
    "as_numpy_compares",
    "ransac_plane",
    "refine_plane",
    "clean_depth",
    "plane_height_m",
    "DEPTH_STEP_M",
    "label_regions",
    "as_uint8",
    "rows_for_opencv",
    "label_box",
    "region_mask",
    "grown_box",
]


@dataclass(frozen=True)
class Plane:
    """A plane ``normal . p + offset_m = 0`` in the camera frame, oriented towards the camera.

    ``normal`` is a unit vector and ``offset_m`` > 0 is the camera's distance to the plane, so the
    signed distance of a point is positive on the camera's side and negative behind the plane.
    """

    normal: tuple[float, float, float]
    offset_m: float
    inlier_fraction: float  # share of the sampled valid points on the plane
    noise_m: float = 0.0  # robust spread of its inliers' distances to it (1.4826 x median)

    def signed_distance_m(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (metres) of points (N, 3): > 0 on the camera's side."""
        return points @ np.asarray(self.normal) + self.offset_m


@dataclass(frozen=True)
class BackgroundParams(Params):
    """Depth range and large-plane removal (shared by the depth-based segmenters)."""

    near_m: float = param(
        0.2,
        unit="m",
        bounds=(0.0, 20.0),
        help="Depth readings nearer than this are ignored (sensor minimum range).",
    )
    far_m: float = param(
        2.0,
        unit="m",
        bounds=(0.05, 50.0),
        help="Depth readings farther than this are background (room, far wall).",
    )
    max_planes: int = param(
        2,
        unit="planes",
        bounds=(0, 4),
        help="Large planes removed as background: the support plane first, then e.g. a wall or the floor.",
    )
    plane_distance_m: float = param(
        0.012,
        unit="m",
        bounds=(0.001, 0.2),
        help="Points closer than this to a background plane belong to it; "
        "about 3-4 times the depth noise at the working distance.",
    )
    min_plane_fraction: float = param(
        0.15,
        unit="fraction",
        bounds=(0.01, 1.0),
        help="A plane is background only if it holds at least this share of "
        "the valid depth pixels (a handled object's face is smaller).",
    )
    min_wall_fraction: float = param(
        0.05,
        unit="fraction",
        bounds=(0.01, 1.0),
        help="A further plane with the whole support plane in front of it (a wall, "
        "the floor) is background from this share of the valid depth pixels: "
        "no handled object's face has the table in front of it, and a wall an "
        "opening lid hides in part is still a wall.",
    )
    plane_stride_px: int = param(
        4, unit="px", bounds=(1, 32), help="The plane fit uses every n-th pixel in x and y (speed)."
    )
    plane_iterations: int = param(
        150, unit="iterations", bounds=(10, 5000), help="RANSAC hypotheses tried per plane."
    )
    plane_seed: int = param(
        0, unit="1", bounds=(0, 2**31 - 1), help="Seed of the RANSAC sampling (reproducible masks)."
    )

    def __post_init__(self):
        super().__post_init__()
        if self.far_m <= self.near_m:
            from artclass_core import ParamError

            raise ParamError(f"parameter far_m = {self.far_m} must be greater than near_m = {self.near_m}")


def clean_depth(depth_m: np.ndarray) -> np.ndarray:
    """Depth as float32 with NaN and infinities replaced by 0 (no reading); no copy when already clean."""
    d = np.asarray(depth_m, dtype=np.float32)
    if d.ndim == 2 and all_finite(d):  # a compiled check, at a third of the cost of isfinite
        return d
    bad = ~np.isfinite(d)
    if bad.any():
        d = np.where(bad, np.float32(0), d)
    return d


def as_uint8(mask: np.ndarray) -> np.ndarray:
    """``mask`` as uint8 for OpenCV: a bool array's own bytes (0 or 1, no copy), anything else
    converted."""
    m = np.asarray(mask)
    return m.view(np.uint8) if m.dtype == bool else m.astype(np.uint8)


#: A region within this many pixels of the picture's border reaches it.
BORDER_PX = 2


def border_band(shape: tuple[int, int]) -> np.ndarray:
    """The pixels within :data:`BORDER_PX` of the picture's border: bool ``shape``."""
    band = np.zeros(shape, bool)
    band[:BORDER_PX], band[-BORDER_PX:], band[:, :BORDER_PX], band[:, -BORDER_PX:] = (True,) * 4
    return band


def rows_for_opencv(image: np.ndarray) -> np.ndarray:
    """An 8-bit image (H, W[, C]) as OpenCV takes it without a copy: as it is when each of its rows
    is contiguous (a crop of a larger image, whose rows OpenCV steps over), else a contiguous copy."""
    a = np.asarray(image, dtype=np.uint8)
    return a if a.ndim >= 2 and a.strides[0] > 0 and a[0].flags.c_contiguous else np.ascontiguousarray(a)


def label_regions(mask: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """``cv2.connectedComponentsWithStats(mask, connectivity=8)``, computed on the bounding box of
    the mask's pixels only: the same (count, labels (H, W) int32, stats (count, 5)) in a fraction
    of the time when the mask covers part of the image. :func:`label_box` gives the labels of that
    box alone.
    """
    n, crop, stats, box = label_box(mask)
    labels = np.zeros(np.shape(mask), np.int32)
    labels[box] = crop
    return n, labels, stats


def label_box(mask: np.ndarray) -> tuple[int, np.ndarray, np.ndarray, tuple[slice, slice]]:
    """:func:`label_regions` without the labels outside the bounding box of the mask's pixels (all 0):
    (count, labels of the box (h, w) int32, stats (count, 5) in image coordinates, the box as (rows,
    columns) slices; empty for an empty mask)."""
    m = as_uint8(mask)
    x, y, w, h = cv2.boundingRect(m)
    box = (slice(y, y + h), slice(x, x + w))
    if not w:
        return (
            1,
            np.zeros((0, 0), np.int32),
            np.array([[0, 0, m.shape[1], m.shape[0], m.size]], np.int32),
            box,
        )
    # the labels without OpenCV's statistics pass, then the statistics in one compiled pass: the
    # same numbers in less than half the time
    n, crop = cv2.connectedComponents(m[box], connectivity=8)
    stats = region_stats(crop, n)
    stats[1:, 0] += x
    stats[1:, 1] += y
    stats[0] = (0, 0, m.shape[1], m.shape[0], m.size - int(stats[1:, 4].sum()))
    return n, crop, stats, box


def region_mask(
    k: int, labels: np.ndarray, stats: np.ndarray, box: tuple[slice, slice], shape: tuple[int, int]
) -> np.ndarray:
    """The pixels of region ``k`` (>= 1) of :func:`label_box`'s ``labels``, ``stats`` and ``box``, in
    an image of ``shape``: bool (H, W)."""
    x, y, w, h = (int(v) for v in stats[k, :4])
    out = np.zeros(shape, bool)
    y0, x0 = y - box[0].start, x - box[1].start
    out[y : y + h, x : x + w] = labels[y0 : y0 + h, x0 : x0 + w] == k
    return out


def grown_box(mask: np.ndarray, margin_px: int) -> tuple[slice, slice]:
    """The bounding box of ``mask``'s pixels (bool (H, W), not empty) grown by ``margin_px`` on each
    side, within the image: (rows, columns) slices. A filter of half-width ``margin_px`` gives the
    same values on the mask's pixels whether it runs on this crop or on the whole image."""
    x, y, w, h = cv2.boundingRect(mask.view(np.uint8))
    rows, cols = mask.shape
    return (
        slice(max(y - margin_px, 0), min(y + h + margin_px, rows)),
        slice(max(x - margin_px, 0), min(x + w + margin_px, cols)),
    )


@functools.lru_cache(maxsize=8)
def _rays(
    fx: float, fy: float, cx: float, cy: float, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel ray slopes ((u - cx) / fx, (v - cy) / fy), float32, shapes (1, W) and (H, 1)."""
    rx = ((np.arange(width, dtype=np.float32) - cx) / fx)[None, :]
    ry = ((np.arange(height, dtype=np.float32) - cy) / fy)[:, None]
    return rx, ry


def range_mask(depth_m: np.ndarray, *, near_m: float, far_m: float) -> np.ndarray:
    """Pixels with a depth reading inside ``[near_m, far_m]``: ndarray of bool, shape (H, W)."""
    return _range_masks(clean_depth(depth_m), near_m=near_m, far_m=far_m)[1]


def _range_masks(d: np.ndarray, *, near_m: float, far_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixels of the clean depth ``d`` with a reading, with one inside ``[near_m, far_m]`` and with
    one outside it: bool (H, W) x 3."""
    valid, inside, outside = (np.empty(d.shape, bool) for _ in range(3))
    range_kernel(
        np.ascontiguousarray(d),
        as_numpy_compares(d, near_m),
        as_numpy_compares(d, far_m),
        valid,
        inside,
        outside,
    )
    return valid, inside, outside


def as_numpy_compares(image: np.ndarray, value: float) -> np.generic:
    """``value`` of the type numpy compares ``image`` (an array) with it: the image's float32 for a
    Python number, float64 for a numpy float64 (NEP 50). A compiled pass given it compares as numpy
    does."""
    return np.result_type(image, value).type(value)


def ransac_plane(
    points: np.ndarray,
    *,
    distance_m: float,
    iterations: int,
    rng: np.random.Generator,
    max_scored: int = 1000,
) -> tuple[np.ndarray, float, np.ndarray] | None:
    """The plane with the most inliers among ``points`` (N, 3), refined by least squares.

    Hypotheses from random point triplets are scored on at most ``max_scored`` points, all at once.

    Returns
    -------
    (normal (3,), offset_m, inliers (N,) bool) with the normal oriented towards the origin
    (``offset_m`` >= 0), or None when fewer than 3 points or only degenerate triplets.
    """
    n = len(points)
    if n < 3:
        return None
    tri = points[rng.integers(0, n, size=(iterations, 3))]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norms = np.linalg.norm(normals, axis=1)
    ok = norms > 1e-12
    if not ok.any():
        return None
    normals = normals[ok] / norms[ok, None]
    offsets = -np.einsum("ij,ij->i", normals, tri[ok, 0])
    scored = points if n <= max_scored else points[rng.choice(n, max_scored, replace=False)]
    distances = scored @ normals.T  # (max_scored, hypotheses), reused in place
    distances += offsets
    np.abs(distances, out=distances)
    counts = np.count_nonzero(distances < distance_m, axis=0)
    best = int(np.argmax(counts))
    return refine_plane(points, normals[best], float(offsets[best]), distance_m=distance_m)


def refine_plane(
    points: np.ndarray, normal: np.ndarray, offset_m: float, *, distance_m: float
) -> tuple[np.ndarray, float, np.ndarray]:
    """A plane refitted by least squares (twice) on the ``points`` (N, 3) within ``distance_m`` of it.

    Returns
    -------
    (normal (3,), offset_m, inliers (N,) bool), the normal oriented towards the origin (``offset_m`` >= 0)
    """
    normal, offset = np.asarray(normal, dtype=np.float64), float(offset_m)
    points = np.ascontiguousarray(points, dtype=np.float64)
    inliers = np.empty(len(points), np.bool_)
    for _ in range(2):  # least-squares refit on the inliers, then re-select them
        n, centre, scatter = plane_moments(points, normal, offset, distance_m, inliers)
        if n < 3:
            break
        normal = np.linalg.eigh(scatter)[1][:, 0]  # the direction of least spread
        offset = -float(normal @ centre)
    plane_moments(points, normal, offset, distance_m, inliers)
    if offset < 0:
        normal, offset = -normal, -offset
    return normal, float(offset), inliers


# The plane search gives up on finding a wall behind the support after this many object faces or slices.
MAX_FACES_PASSED = 3


def fit_planes(
    depth_m: np.ndarray, intrinsics: Intrinsics, *, params: BackgroundParams, hints: list[Plane] | None = None
) -> list[Plane]:
    """The large background planes of a depth image, largest first.

    The first (largest) plane is the support plane. Each plane found removes its inliers and the
    points behind it before the next is sought. A further plane is background (a wall, the floor)
    only if the support plane lies in front of it (95 % of the support's inliers on its camera side);
    a plane with the support partly behind it is an object's face or a slice through the objects:
    its points are set aside and the search goes on past it (it gives up after ``MAX_FACES_PASSED``).
    The search stops at ``max_planes`` or when a plane holds fewer than ``min_plane_fraction`` (the
    support) or ``min_wall_fraction`` (a further plane) of the sampled valid points.

    Parameters
    ----------
    depth_m : ndarray, shape (H, W), metres (0 or NaN = no reading)
    intrinsics : the depth camera's pinhole intrinsics
    params : range and plane settings
    hints : the planes of another frame of the same scene (e.g. its first): the k-th plane is sought
        first by refitting the k-th hint to this frame's points, and by RANSAC only when the refit
        holds less than half the hint's share of the points (the camera or the scene moved)

    Returns
    -------
    list of Plane, oriented towards the camera
    """
    s = params.plane_stride_px
    rx, ry = _rays(
        intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, intrinsics.width, intrinsics.height
    )
    pts = strided_points(
        np.ascontiguousarray(depth_m, dtype=np.float32),
        s,
        np.float32(params.near_m),
        np.float32(params.far_m),
        rx[0],
        ry[:, 0],
    )
    total = len(pts)
    rng = None  # made when RANSAC first needs it (a refitted hint draws nothing)
    planes: list[Plane] = []
    support = pts[:0]  # the first plane's inliers, once it is found
    faces = 0
    while len(planes) < params.max_planes and faces < MAX_FACES_PASSED:
        least = params.min_wall_fraction if planes else params.min_plane_fraction
        if total == 0 or len(pts) < max(3, least * total):
            break
        found = None
        hint = hints[len(planes)] if hints is not None and len(planes) < len(hints) else None
        if hint is not None:
            found = refine_plane(
                pts, np.asarray(hint.normal), hint.offset_m, distance_m=params.plane_distance_m
            )
            if np.count_nonzero(found[2]) < max(least, 0.5 * hint.inlier_fraction) * total:
                found = None
        if found is None:
            rng = np.random.default_rng(params.plane_seed) if rng is None else rng
            found = ransac_plane(
                pts, distance_m=params.plane_distance_m, iterations=params.plane_iterations, rng=rng
            )
        if found is None:
            break
        normal, offset, inliers = found
        fraction = np.count_nonzero(inliers) / total
        if fraction < least:
            break
        if planes and np.mean(support @ normal + offset > -params.plane_distance_m) < 0.95:
            # the support plane is (partly) behind it: an object's face or a slice through the objects,
            # not background; a wall may still lie beyond it
            pts, faces = np.compress(~inliers, pts, axis=0), faces + 1
            continue
        # rows picked by np.compress: the same as boolean indexing, in a fraction of the time
        on = np.compress(inliers, pts, axis=0)
        if not planes:
            support = on
        noise = 1.4826 * float(np.median(np.abs(on @ normal + offset)))
        planes.append(Plane(tuple(float(v) for v in normal), offset, float(fraction), noise))
        pts = np.compress(~inliers & (pts @ normal + offset >= -params.plane_distance_m), pts, axis=0)
    return planes


def _signed(d: np.ndarray, rays: tuple[np.ndarray, np.ndarray], plane: Plane) -> np.ndarray:
    """Per-pixel signed distance (m) of the back-projected depth ``d`` to ``plane`` (> 0 in front)."""
    nx, ny, nz = (np.float32(v) for v in plane.normal)
    out = np.empty(d.shape, np.float32)
    # d * (nx * rays[0] + ny * rays[1] + nz) + offset, the same float32 operations in one pass
    height_kernel(
        np.ascontiguousarray(d), nx * rays[0][0], ny * rays[1][:, 0], nz, np.float32(plane.offset_m), out
    )
    return out


def plane_height_m(depth_m: np.ndarray, intrinsics: Intrinsics, plane: Plane) -> np.ndarray:
    """Per-pixel signed distance (metres) of the back-projected depth to ``plane``: > 0 on the camera's
    side. float32 (H, W); pixels without a reading give ``offset_m``."""
    rays = _rays(
        intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, intrinsics.width, intrinsics.height
    )
    return _signed(clean_depth(depth_m), rays, plane)


def background_mask(
    depth_m: np.ndarray,
    intrinsics: Intrinsics,
    planes: list[Plane],
    *,
    params: BackgroundParams,
    heights: list[np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Which pixels are known background, and which have a usable depth reading.

    Parameters
    ----------
    depth_m : ndarray, shape (H, W), metres
    intrinsics : pinhole intrinsics of the depth image
    planes : background planes from :func:`fit_planes`
    params : range and plane settings
    heights : list of ndarray, shape (H, W), metres, optional -- each plane's
        :func:`plane_height_m`, when already computed

    Returns
    -------
    background : ndarray of bool, shape (H, W)
        valid readings out of ``[near_m, far_m]``, or within ``plane_distance_m`` of a plane or behind it
    valid : ndarray of bool, shape (H, W)
        pixels with a depth reading (> 0, finite)
    """
    d = clean_depth(depth_m)
    valid, _, background = _range_masks(d, near_m=params.near_m, far_m=params.far_m)
    for height in _heights(d, intrinsics, planes, heights):
        background |= valid & (height < params.plane_distance_m)
    return background, valid


def _heights(
    d: np.ndarray, intrinsics: Intrinsics, planes: list[Plane], heights: list[np.ndarray] | None
) -> list[np.ndarray]:
    """``heights`` when given, else each plane's :func:`plane_height_m` of the clean depth ``d``."""
    return heights if heights is not None else [plane_height_m(d, intrinsics, plane) for plane in planes]


# Depth images store millimetres: a plane's own pixels stray this far from it with no noise at all.
DEPTH_STEP_M = 0.001


def above_planes(
    depth_m: np.ndarray,
    intrinsics: Intrinsics,
    planes: list[Plane],
    *,
    params: BackgroundParams,
    sigmas: float,
    window_px: int = 1,
    heights: list[np.ndarray] | None = None,
    inside: np.ndarray | None = None,
) -> np.ndarray:
    """Pixels inside ``[near_m, far_m]`` that lie in front of every plane by more than ``sigmas``
    times its measured noise (``Plane.noise_m``, at least DEPTH_STEP_M): off the plane by more than
    its noise explains, though maybe nearer than ``plane_distance_m``. bool (H, W).

    With ``window_px`` > 1 a pixel's height is the mean over the ``window_px`` x ``window_px`` square
    around it (all with a reading), judged against the noise of that mean measured on the plane in
    this image (the robust sigma of the means within ``plane_distance_m`` of it): up to
    ``window_px`` times smaller than a single reading's where the sensor's noise is independent from
    pixel to pixel, so that a surface a few millimetres proud of the plane stands out of it though
    its single readings do not. ``heights``: each plane's :func:`plane_height_m`, and ``inside``:
    :func:`range_mask` of the depth, when already computed (the depth is then not read)."""
    d = clean_depth(depth_m) if inside is None or heights is None else depth_m
    if inside is None:
        inside = range_mask(d, near_m=params.near_m, far_m=params.far_m)
    if window_px > 1:
        size = (window_px, window_px)
        out = cv2.erode(as_uint8(inside), np.ones(size, np.uint8), borderValue=0) > 0
    else:
        out = inside.copy()  # a given ``inside`` is left as it was
    for plane, height in zip(planes, _heights(d, intrinsics, planes, heights)):
        noise = max(plane.noise_m, DEPTH_STEP_M)
        if window_px > 1:
            height = cv2.blur(height, size)
            sample = np.abs(height[::4, ::4][out[::4, ::4]])  # a sixteenth is plenty for a median
            sample = sample[sample < params.plane_distance_m]
            if sample.size:
                noise = max(1.4826 * float(np.median(sample)), DEPTH_STEP_M / window_px)
        out &= height > sigmas * noise
    return out
