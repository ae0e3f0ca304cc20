"""The ``image`` preprocessor: the masked depth image kept as an organised cloud.

Every step of the paper's Algorithm 1 is done on image neighbourhoods instead of k-d trees, so a
frame costs a few milliseconds at 640x480 and keeps, for every point, the pixel it came from:

1. outlier removal (s): a pixel whose depth is more than ``outlier_sigmas`` noise (plus one pixel's
   footprint) away from the median of the valid pixels of its 5x5 neighbourhood is dropped; this
   removes the flying pixels along depth edges, where a sensor mixes the depths of the two surfaces,
   and keeps a surface whose pixels the sensor loses one in two (at a grazing angle);
2. smoothing (r): an edge-preserving (bilateral) filter whose depth range is the same tolerance, so
   two surfaces one above the other are never averaged;
3. normals from the image neighbourhood (central differences of the back-projected pixels,
   averaged over their valid neighbours, so that sparse surfaces keep normals);
4. downsampling (v): a regular pixel stride chosen so that the cloud holds at most ``max_points``.

The depth noise is measured on every frame (``info["noise_m"]``: the robust spread of the pixels
about their neighbourhood's median, never below the sensor model), and so is what is left of it after
smoothing (``info["smoothed_noise_m"]``: the smoothing averages about (2 r + 1)^2 pixels), and so is the
depth's quantisation step (``info["depth_step_m"]``), which smoothing does not average away. The sensor
model itself (``depth_noise_m``, the noise at 1 m) goes with the cloud (``info["depth_noise_m"]``) for
the registration.

The cloud's :class:`~artclass_core.types.View` keeps the full-resolution filtered depth, normals and
mask, which is what a projective (KinectFusion-style) registration of the next frame looks up.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from artclass_core import Cloud, Frame, Intrinsics, Params, Preprocessor, View, param

MIN_POINTS = 10


@dataclass(frozen=True)
class ImageParams(Params):
    depth_noise_m: float = param(
        0.0015,
        unit="m",
        bounds=(1e-5, 0.05),
        help="Depth noise (one standard deviation) of the sensor at 1 m; it grows with "
        "the square of the depth (structured-light and stereo sensors). The floor of "
        "the noise measured on each frame and pair, and the scale of the registration's "
        "reach.",
    )
    outlier_sigmas: float = param(
        3.0,
        symbol="s",
        unit="sigma",
        bounds=(0.5, 20.0),
        help="Drop a pixel whose depth is more than this many noise sigmas (plus one "
        "pixel's footprint) from the median of the valid pixels of its 5x5 neighbourhood.",
    )
    smoothing_px: int = param(
        2, unit="px", bounds=(0, 10), help="Radius of the edge-preserving depth smoothing (0 = none)."
    )
    max_points: int = param(
        3000,
        unit="points",
        bounds=(50, 200000),
        help="The cloud keeps every n-th pixel of every n-th row, with n the smallest "
        "stride that leaves at most this many points.",
    )
    edge_px: int | None = param(
        None,
        unit="px",
        bounds=(0, 50),
        auto="image width / 160 (4 px at 640x480)",
        help="Peel this many pixels off the mask first (a silhouette slides over the "
        "surface when the view changes); where the object is thinner than twice "
        "this, half of each side.",
    )


def noise_m(depth_m: np.ndarray | float, at_1m: float) -> np.ndarray | float:
    """Axial depth noise (one sigma, metres) at ``depth_m``: ``at_1m`` times the depth squared."""
    return at_1m * np.square(depth_m)


def finite_depth(depth_m: np.ndarray) -> np.ndarray:
    """A copy (H, W) float32 of a depth image (metres) with its non-finite pixels set to 0."""
    from . import _compiled  # Numba, on first use

    out = np.empty(depth_m.shape, np.float32)
    _compiled.finite_or_zero(depth_m, out)
    return out


def bounding_box(mask: np.ndarray, *, margin_px: int = 0) -> tuple[tuple[int, int], tuple[int, int]] | None:
    """Rows (first, last + 1) and columns (first, last + 1) of a mask's pixels, widened by
    ``margin_px`` on every side within the image; None for an empty mask."""
    u, v, w, h = cv2.boundingRect(mask.view(np.uint8) if mask.dtype == bool else mask.astype(np.uint8))
    if w == 0:
        return None
    rows, cols = mask.shape[:2]
    return (
        (max(v - margin_px, 0), min(v + h + margin_px, rows)),
        (max(u - margin_px, 0), min(u + w + margin_px, cols)),
    )


def vertex_map(depth_m: np.ndarray, intrinsics: Intrinsics, *, u0: int = 0, v0: int = 0) -> np.ndarray:
    """Back-projected points (H, W, 3) of a depth image whose top-left pixel is (``u0``, ``v0``)."""
    h, w = depth_m.shape
    u = np.arange(u0, u0 + w, dtype=np.float32)
    v = np.arange(v0, v0 + h, dtype=np.float32)
    x = (u[None, :] - intrinsics.cx) / intrinsics.fx * depth_m
    y = (v[:, None] - intrinsics.cy) / intrinsics.fy * depth_m
    return np.dstack([x, y, depth_m]).astype(np.float32)


def normal_map(vertices: np.ndarray, *, window_px: int = 5, min_support: float = 0.25) -> np.ndarray:
    """Unit normals (H, W, 3) of a vertex map whose missing pixels are zero, facing the camera.

    The vertex map is first averaged over ``window_px`` windows by normalised convolution (each
    window's valid pixels only), so that a surface the sensor sees sparsely (at a grazing angle, half
    its pixels are lost) still has normals; then central differences across the window. Zero where
    fewer than ``min_support`` of a window's pixels are valid.
    """
    k = (window_px, window_px)
    support = cv2.blur((vertices[..., 2] > 0).astype(np.float32), k)
    # Missing pixels are zero, so the blur of the vertices is already the sum over the valid ones;
    # the kernel divides it by the support only at the pixels it differentiates.
    total = cv2.blur(vertices, k)
    normals = np.zeros_like(vertices)
    from . import _compiled  # Numba, on first use

    _compiled.normals_kernel(vertices, total, support, window_px // 2, np.float32(min_support), normals)
    return normals


def peel(mask: np.ndarray, edge_px: int) -> np.ndarray:
    """The mask without its outer ``edge_px`` pixels, except where it is thinner than twice that:
    there only the outer half of each side goes (a lever a few pixels wide keeps its middle)."""
    inside = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 3)
    kernel = np.ones((4 * edge_px + 1, 4 * edge_px + 1), np.uint8)
    half_width = cv2.dilate(inside, kernel)  # the largest distance to the edge nearby
    return mask & (inside > np.minimum(edge_px, half_width / 2))


def median_5x5(depth_m: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The depth (H, W) float32 with its invalid pixels 0, and its plain 5x5 median filter (H, W)
    float32 (``cv2.medianBlur``), which :func:`measured_noise` and :func:`valid_median` both start from."""
    depth = _masked(depth_m, valid)
    return depth, cv2.medianBlur(depth, 5)


def measured_noise(depth_m: np.ndarray, valid: np.ndarray, *, median: np.ndarray | None = None) -> float:
    """Depth noise (metres, one sigma) measured on an image: the RMS deviation of the valid pixels from
    the median of their 5x5 neighbourhood, over pixels whose neighbourhood is all valid, the largest 5%
    (creases, flying pixels) left out; 0 when too few pixels have such a neighbourhood. ``median``, if
    given, is the second result of :func:`median_5x5`, not computed again.

    Notes
    -----
    Not a median absolute deviation: a sensor that quantises depth (disparity steps) gives most pixels
    exactly their neighbours' depth, and the MAD of that is zero however coarse the steps are.
    """
    depth, plain = median_5x5(depth_m, valid) if median is None else (_masked(depth_m, valid), median)
    # Only pixels whose whole neighbourhood is valid: at an edge the median mixes in another surface.
    interior = cv2.erode(valid.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    spread = np.abs(depth - plain)[interior]
    if len(spread) < MIN_POINTS:
        return 0.0
    kept = np.sort(spread)[: max(1, int(0.95 * len(spread)))]
    return float(np.sqrt(np.mean(np.square(kept))))


def valid_median(
    depth: np.ndarray, valid: np.ndarray, *, min_count: int = 3, median: np.ndarray | None = None
) -> np.ndarray:
    """The median of each valid pixel's valid 5x5 neighbours (itself included); 0 where fewer than
    ``min_count`` are valid, and at invalid pixels. ``median``, if given, is the second result of
    :func:`median_5x5` (left as it is), not computed again.

    Missing pixels must not vote: where a sensor loses half the pixels of a surface seen at a grazing
    angle, a plain median filter of the image with zeros for them returns zero."""
    depth, out = median_5x5(depth, valid) if median is None else (_masked(depth, valid), median.copy())
    # Where a window is all valid and inside the image, the plain median is the same.
    whole = cv2.erode(valid.astype(np.uint8), np.ones((5, 5), np.uint8), borderValue=0) > 0
    from . import _compiled  # Numba, on first use

    _compiled.valid_median_kernel(depth, valid, valid & ~whole, out, 2, min_count)
    return np.where(valid, out, 0).astype(np.float32, copy=False)


def _masked(depth_m: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The depth (H, W) float32 with its invalid pixels 0."""
    return np.where(valid, depth_m, 0).astype(np.float32, copy=False)


def depth_step(depth_m: np.ndarray, valid: np.ndarray, *, min_levels: int = 8) -> float:
    """The depth's quantisation step (metres) measured on an image: the mean gap between neighbouring
    distinct depths of the valid pixels (gaps over 1.5 times the median, levels no pixel took, left
    out); 0 when they take fewer than ``min_levels`` values (too few to tell a step from the surface's
    shape), and about 0 for a depth that is not quantised. A depth rounded to a unit after its
    disparity was quantised has gaps of two sizes (3 and 4 mm for a 3.4 mm step): the mean is the step.

    A structured-light sensor quantises disparity, so its depth steps grow with the square of the
    depth (about 3 mm at 1 m); smoothing leaves plateaus one step apart, whole patches of pixels off
    by up to half a step, which is no evidence of motion."""
    levels = np.unique(depth_m[valid])
    if len(levels) < min_levels:
        return 0.0
    gaps = np.diff(levels)
    return float(np.mean(gaps[gaps <= 1.5 * np.median(gaps)]))


def filter_depth(
    depth_m: np.ndarray,
    valid: np.ndarray,
    *,
    tolerance_m: np.ndarray,
    smoothing_px: int,
    median: np.ndarray | None = None,
) -> np.ndarray:
    """Depth with outliers removed (0) and, if ``smoothing_px``, smoothed within ``tolerance_m``.

    A pixel is an outlier when it is farther than ``tolerance_m`` from the median of the valid pixels
    of its 5x5 neighbourhood, or when fewer than three of them are valid (a lone pixel). ``median``, if
    given, is the second result of :func:`median_5x5`, not computed again."""
    depth = _masked(depth_m, valid)
    median = valid_median(depth, valid, median=median)
    keep = valid & (median > 0) & (np.abs(depth - median) <= tolerance_m)
    depth = np.where(keep, depth, 0).astype(np.float32, copy=False)
    if smoothing_px:
        sigma = float(np.median(tolerance_m[keep])) if keep.any() else 0.01
        smooth = cv2.bilateralFilter(depth, 2 * smoothing_px + 1, sigma, smoothing_px)
        # Missing pixels (0) lie far outside the depth range and get no weight, except next to a hole,
        # where the filter's range term cannot tell; those pixels keep their own depth.
        depth = np.where(keep & (np.abs(smooth - depth) <= tolerance_m), smooth, depth).astype(
            np.float32, copy=False
        )
    return depth


class ImagePreprocessor(Preprocessor):
    """Outlier removal, smoothing and normals on image neighbourhoods; a strided organised cloud."""

    name = "image"
    description = "image-space filtering of the masked depth: an organised cloud with normals (default)"
    Params = ImageParams

    def process(self, frame: Frame, mask: np.ndarray, *, intrinsics: Intrinsics) -> Cloud:
        p = self.params
        raw = finite_depth(frame.depth_m)
        mask = mask.astype(bool)
        px = p.edge_px if p.edge_px is not None else max(1, round(intrinsics.width / 160))
        # Everything below works on the mask's bounding box, with a margin wider than the filters reach.
        box = bounding_box(mask, margin_px=4 + p.smoothing_px)
        if box is None:
            return _empty(frame.index, 0)
        (v0, v1), (u0, u1) = box
        crop, inner = raw[v0:v1, u0:u1], mask[v0:v1, u0:u1]
        inside = (peel(inner, px) if px else inner) & (crop > 0)
        n_raw = int(np.count_nonzero(inside))
        if n_raw < MIN_POINTS:
            return _empty(frame.index, n_raw)
        footprint = crop / intrinsics.fx
        _, median = median_5x5(crop, inside)
        sigma = max(
            measured_noise(crop, inside, median=median),
            float(noise_m(np.median(crop[inside]), p.depth_noise_m)),
        )
        tolerance = p.outlier_sigmas * sigma + footprint
        depth = filter_depth(crop, inside, tolerance_m=tolerance, smoothing_px=p.smoothing_px, median=median)
        vertices = vertex_map(depth, intrinsics, u0=u0, v0=v0)
        normals = normal_map(vertices)
        usable = (depth > 0) & ((normals[..., 0] != 0) | (normals[..., 1] != 0) | (normals[..., 2] != 0))
        n_usable = int(usable.sum())
        if n_usable < MIN_POINTS:
            return _empty(frame.index, n_raw)
        stride = max(1, int(np.ceil(np.sqrt(n_usable / p.max_points))))
        grid = np.zeros_like(usable)
        grid[(-v0) % stride :: stride, (-u0) % stride :: stride] = True
        rr, cc = np.nonzero(usable & grid)
        points = vertices[rr, cc].astype(np.float64)
        full_depth = np.zeros_like(raw)
        full_depth[v0:v1, u0:u1] = depth
        full_normals = np.zeros(raw.shape + (3,), np.float32)
        full_normals[v0:v1, u0:u1] = normals
        pixels = np.column_stack([cc + u0, rr + v0])
        view = View(
            cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY),
            full_depth,
            intrinsics,
            raw,
            mask=mask,
            normals=full_normals,
        )
        info = dict(
            n_raw=n_raw,
            n_inliers=n_usable,
            n_points=len(points),
            stride_px=stride,
            edge_px=px,
            diameter_m=_extent(points),
            depth_m=float(np.median(points[:, 2])),
            noise_m=sigma,
            smoothed_noise_m=sigma / (2 * p.smoothing_px + 1),
            depth_step_m=depth_step(crop, inside),
            depth_noise_m=p.depth_noise_m,
        )
        return Cloud(
            frame.index,
            points,
            normals[rr, cc].astype(np.float64),
            info,
            colors=frame.rgb[rr + v0, cc + u0].astype(np.float64) / 255.0,
            view=view,
            pixels=pixels,
        )


def _empty(index: int, n_raw: int) -> Cloud:
    """The cloud of a frame with too few usable pixels."""
    return Cloud(
        index,
        np.zeros((0, 3)),
        np.zeros((0, 3)),
        dict(n_raw=n_raw),
        colors=np.zeros((0, 3)),
        pixels=np.zeros((0, 2), int),
    )


def _extent(points: np.ndarray) -> float:
    """Diagonal of the points' bounding box (metres): the object's size, for display and the grid."""
    return float(np.linalg.norm(np.ptp(points, axis=0))) if len(points) else 0.0
