"""The compiled (Numba) per-pixel loops of the segmenters, one pass over an image where numpy makes
several full-image temporaries or OpenCV a slow generic pass: the projector's shadows (a scan of
each row), the colour difference of the thin-object search, the statistics of labelled regions, the
plane search's points and their least-squares refit, a flood from the image's border, and the
depth's heights above the planes and its range masks."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def shadow_kernel(depth, step, disparity, out):
    """Mark in ``out`` (bool (H, W), all False) the pixels without a reading (``depth`` == 0, float32
    (H, W)) whose nearest readings to the left and to the right in their row differ by more than
    ``step`` (float32), in a gap no wider than ``disparity`` (float32, pixel metres) times the
    difference of their inverse depths, plus a pixel."""
    h, w = depth.shape
    for v in range(h):
        left = -1  # the last column with a reading
        for u in range(w):
            if depth[v, u] == 0:
                continue
            if left >= 0 and u > left + 1 and abs(depth[v, left] - depth[v, u]) > step:
                if u - left - 2 <= disparity * abs(1 / depth[v, left] - 1 / depth[v, u]):
                    out[v, left + 1 : u] = True
            left = u


@njit(cache=True, nogil=True)
def step_kernel(depth, step, out):
    """Mark in ``out`` (bool (H, W)) the pixels whose 3x3 neighbourhood (within the image) holds
    readings (``depth`` > 0, float32 (H, W)) whose farthest minus nearest exceeds ``step`` (float32):
    the nearest and farthest over each row's three pixels first (the row padded with a pixel without
    a reading at each end), then over three rows."""
    h, w = depth.shape
    inf = np.float32(np.inf)
    near = np.empty((h, w), np.float32)  # +inf where none of the three has a reading
    far = np.empty((h, w), np.float32)  # 0 where none has one
    row_near = np.full(w + 2, inf, np.float32)
    row_far = np.zeros(w + 2, np.float32)
    for v in range(h):
        for u in range(w):
            z = depth[v, u]
            row_near[u + 1] = z if z > 0 else inf
            row_far[u + 1] = z if z > 0 else np.float32(0)
        for u in range(w):
            near[v, u] = min(min(row_near[u], row_near[u + 1]), row_near[u + 2])
            far[v, u] = max(max(row_far[u], row_far[u + 1]), row_far[u + 2])
    for v in range(h):
        a, b = max(v - 1, 0), min(v + 1, h - 1)
        for u in range(w):
            lo = min(min(near[a, u], near[v, u]), near[b, u])
            hi = max(max(far[a, u], far[v, u]), far[b, u])
            out[v, u] = hi - lo > step


@njit(inline="always")
def _lesser(a, b):
    return a if a < b else b  # a compare and a select, which vectorise (no NaN here)


@njit(inline="always")
def _greater(a, b):
    return a if a > b else b


@njit(cache=True, nogil=True)
def _row_range(row, near, far):
    """The nearest and farthest of each pixel of ``row`` and its left and right neighbours (those in
    the row) into ``near`` and ``far``."""
    w = row.shape[0]
    near[0] = far[0] = row[0]
    if w > 1:
        near[0], far[0] = _lesser(row[0], row[1]), _greater(row[0], row[1])
        near[w - 1], far[w - 1] = _lesser(row[w - 2], row[w - 1]), _greater(row[w - 2], row[w - 1])
    for u in range(1, w - 1):
        a, b, c = row[u - 1], row[u], row[u + 1]
        near[u] = _lesser(_lesser(a, b), c)
        far[u] = _greater(_greater(a, b), c)


@njit(cache=True, nogil=True)
def steady_kernel(depth, step, out):
    """Mark in ``out`` (bool (H, W)) the pixels with a reading (``depth`` > 0, float32 (H, W), no NaN)
    whose 3x3 neighbourhood (within the image, pixels without a reading as 0) spans at most ``step``
    (float32): farthest minus nearest, as OpenCV's morphological gradient computes it; over each
    row's three pixels first, then over three rows."""
    h, w = depth.shape
    near = np.empty((h, w), np.float32)
    far = np.empty((h, w), np.float32)
    for v in range(h):
        _row_range(depth[v], near[v], far[v])
    for v in range(h):
        a, b = max(v - 1, 0), min(v + 1, h - 1)
        for u in range(w):
            lo = _lesser(_lesser(near[a, u], near[v, u]), near[b, u])
            hi = _greater(_greater(far[a, u], far[v, u]), far[b, u])
            out[v, u] = (depth[v, u] > 0) & (hi - lo <= step)


@njit(cache=True, nogil=True)
def colour_distance_kernel(colour, around, scale, out):
    """Write in ``out`` (float32 (H, W)) the squared distance between ``colour`` and ``around``
    (float32 (H, W, 3) each), each channel's difference times its ``scale`` (float32 (3,))."""
    h, w = out.shape
    s0, s1, s2 = scale[0], scale[1], scale[2]
    for v in range(h):
        for u in range(w):
            d0 = (colour[v, u, 0] - around[v, u, 0]) * s0
            d1 = (colour[v, u, 1] - around[v, u, 1]) * s1
            d2 = (colour[v, u, 2] - around[v, u, 2]) * s2
            out[v, u] = d0 * d0 + d1 * d1 + d2 * d2


@njit(cache=True, nogil=True)
def share_mean_kernel(total, share, fallback, out):
    """Write in ``out`` (float32 (H, W, 3)) the mean of the samples a window kept: its mean ``total``
    over all its samples (the others counted as 0) divided by the ``share`` (float32 (H, W)) it kept;
    ``fallback`` where it kept none (float32 (H, W, 3) each)."""
    h, w = share.shape
    for v in range(h):
        for u in range(w):
            s = share[v, u]
            for c in range(3):
                out[v, u, c] = total[v, u, c] / s if s > 0 else fallback[v, u, c]


@njit(cache=True, nogil=True, fastmath={"reassoc"})
def all_finite(values):
    """Whether every value of ``values`` (float32 (H, W)) is finite: a row's values times 0 sum to 0
    when they are, to NaN when one is NaN or infinite, in whatever order they are added (which lets
    the sum vectorise)."""
    h, w = values.shape
    zero = np.float32(0)
    for v in range(h):
        total = zero
        for u in range(w):
            total += values[v, u] * zero
        if total != zero:
            return False
    return True


@njit(cache=True, nogil=True)
def region_stats(labels, n):
    """OpenCV's component statistics (left, top, width, height, area; int32 (n, 5)) of the labels
    1 .. n - 1 of ``labels`` (int32 (H, W)), in one pass; row 0 (the background) is left zero."""
    h, w = labels.shape
    stats = np.zeros((n, 5), np.int32)
    x0 = np.full(n, w, np.int32)
    y0 = np.full(n, h, np.int32)
    x1 = np.full(n, -1, np.int32)
    y1 = np.full(n, -1, np.int32)
    for v in range(h):
        for u in range(w):
            k = labels[v, u]
            if k:
                if u < x0[k]:
                    x0[k] = u
                if u > x1[k]:
                    x1[k] = u
                if y0[k] == h:
                    y0[k] = v
                y1[k] = v
                stats[k, 4] += 1
    for k in range(1, n):
        stats[k, 0] = x0[k]
        stats[k, 1] = y0[k]
        stats[k, 2] = x1[k] - x0[k] + 1
        stats[k, 3] = y1[k] - y0[k] + 1
    return stats


@njit(cache=True, nogil=True)
def plane_moments(points, normal, offset, distance, inliers):
    """Mark in ``inliers`` (bool (N,)) the ``points`` (float64 (N, 3)) within ``distance`` of the plane
    ``points @ normal + offset == 0``; return their number, their centre (3,) and their scatter about
    it (3, 3), two passes over the points instead of numpy's several temporaries."""
    n = 0
    centre = np.zeros(3)
    for i in range(points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        inliers[i] = abs(x * normal[0] + y * normal[1] + z * normal[2] + offset) < distance
        if inliers[i]:
            n += 1
            centre[0] += x
            centre[1] += y
            centre[2] += z
    scatter = np.zeros((3, 3))
    if n == 0:
        return n, centre, scatter
    centre /= n
    for i in range(points.shape[0]):
        if inliers[i]:
            for a in range(3):
                d = points[i, a] - centre[a]
                for b in range(a, 3):
                    scatter[a, b] += d * (points[i, b] - centre[b])
    for a in range(3):
        for b in range(a):
            scatter[a, b] = scatter[b, a]
    return n, centre, scatter


@njit(cache=True, nogil=True)
def strided_points(depth, stride, near, far, rx, ry):
    """The back-projected points (float64 (N, 3)) of every ``stride``-th pixel in x and y of ``depth``
    (float32 (H, W), metres) with a reading in [``near``, ``far``] (float32), in row-major order; ``rx``
    (W,) and ``ry`` (H,) are the pixels' ray slopes (float32)."""
    h, w = depth.shape
    n = 0
    for v in range(0, h, stride):
        for u in range(0, w, stride):
            z = depth[v, u]
            if z >= near and z <= far and z > 0:
                n += 1
    out = np.empty((n, 3))
    i = 0
    for v in range(0, h, stride):
        for u in range(0, w, stride):
            z = depth[v, u]
            if z >= near and z <= far and z > 0:
                out[i, 0] = np.float64(rx[u]) * np.float64(z)
                out[i, 1] = np.float64(ry[v]) * np.float64(z)
                out[i, 2] = z
                i += 1
    return out


@njit(cache=True, nogil=True)
def border_reach(mask, out):
    """Mark in ``out`` (bool (H, W), all False) the pixels of ``mask`` (bool (H, W)) connected
    (8-connected) through ``mask`` to the image border: a flood from the border's pixels, which
    visits only what it reaches, where labelling every region of the image visits them all."""
    h, w = mask.shape
    stack = np.empty(h * w, np.int64)
    top = 0
    for v in range(h):
        for u in range(w):
            if (v == 0 or v == h - 1 or u == 0 or u == w - 1) and mask[v, u] and not out[v, u]:
                out[v, u] = True
                stack[top] = v * w + u
                top += 1
    while top:
        top -= 1
        v, u = divmod(stack[top], w)
        for dv in range(-1, 2):
            for du in range(-1, 2):
                y, x = v + dv, u + du
                if 0 <= y < h and 0 <= x < w and mask[y, x] and not out[y, x]:
                    out[y, x] = True
                    stack[top] = y * w + x
                    top += 1


@njit(cache=True, nogil=True)
def height_kernel(depth, ray_x, ray_y, nz, offset, out):
    """Write to ``out`` (float32 (H, W)) each pixel's signed distance to the plane ``n . p + offset =
    0`` of its back-projected ``depth`` (float32 (H, W)): ``depth * ((ray_x[u] + ray_y[v]) + nz) +
    offset``, where ``ray_x`` (W,) and ``ray_y`` (H,) are the pixels' ray slopes times the normal's x
    and y (float32), all in float32, as numpy's broadcasting computes it, in one pass."""
    h, w = depth.shape
    for v in range(h):
        for u in range(w):
            out[v, u] = depth[v, u] * ((ray_x[u] + ray_y[v]) + nz) + offset


@njit(cache=True, nogil=True)
def range_kernel(depth, near, far, valid, inside, outside):
    """Mark, per pixel of ``depth`` (float32 (H, W), 0 = no reading), in ``valid`` a reading, in
    ``inside`` a reading in [``near``, ``far``], in ``outside`` a reading out of it (float32 bounds;
    bool (H, W) outputs), in one pass."""
    h, w = depth.shape
    for v in range(h):
        for u in range(w):
            z = depth[v, u]
            seen = z > 0
            within = z >= near and z <= far
            valid[v, u] = seen
            inside[v, u] = seen and within
            outside[v, u] = seen and not within


def warm_up() -> None:
    """Load the compiled loops: run each once on a tiny image with the argument types of the
    segmenters' calls, so that the first frame does not pay for loading Numba's cached machine code
    (or compiling it)."""
    depth = np.full((4, 6), 0.5, np.float32)
    flags = np.zeros(depth.shape, bool)
    shadow_kernel(depth, np.float32(0.01), np.float32(30.0), flags)
    step_kernel(depth, np.float32(0.01), flags)
    steady_kernel(depth, np.float32(0.01), flags)
    colour = np.zeros(depth.shape + (3,), np.float32)
    colour_distance_kernel(colour, colour, np.ones(3, np.float32), depth.copy())
    share_mean_kernel(colour, depth, colour, colour.copy())
    region_stats(np.zeros(depth.shape, np.int32), 1)
    all_finite(depth)
    one = np.float32(1.0)
    height_kernel(depth, np.zeros(6, np.float32), np.zeros(4, np.float32), one, one, depth.copy())
    range_kernel(depth, np.float32(0.1), one, flags.copy(), flags.copy(), flags.copy())
    border_reach(flags.copy(), flags)
    rays = np.zeros(6, np.float32), np.zeros(4, np.float32)
    strided_points(depth, 2, np.float32(0.1), np.float32(1.0), *rays)
    plane_moments(np.zeros((3, 3)), np.array([0.0, 0.0, 1.0]), 0.0, 0.01, np.zeros(3, bool))
