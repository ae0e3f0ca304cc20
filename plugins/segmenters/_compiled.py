"""The compiled (Numba) per-pixel loops of the segmenters, one pass over an image where numpy makes
several full-image temporaries: the projector's shadows (a scan of each row)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def shadow_kernel(depth, step, out):
    """Mark in ``out`` (bool (H, W), all False) the pixels without a reading (``depth`` == 0, float32
    (H, W)) whose nearest readings to the left and to the right in their row differ by more than
    ``step`` (float32)."""
    h, w = depth.shape
    for v in range(h):
        left = -1  # the last column with a reading
        for u in range(w):
            if depth[v, u] == 0:
                continue
            if left >= 0 and u > left + 1 and abs(depth[v, left] - depth[v, u]) > step:
                out[v, left + 1 : u] = True
            left = u


@njit(cache=True, nogil=True)
def distinct_kernel(colour, around, where, least_sq, out):
    """Mark in ``out`` (bool (H, W)) the pixels of ``where`` (bool (H, W)) whose ``colour`` differs
    from ``around`` (float32 (H, W, 3) each) by a squared distance of at least ``least_sq``
    (float32)."""
    h, w = where.shape
    for v in range(h):
        for u in range(w):
            if where[v, u]:
                d0 = colour[v, u, 0] - around[v, u, 0]
                d1 = colour[v, u, 1] - around[v, u, 1]
                d2 = colour[v, u, 2] - around[v, u, 2]
                out[v, u] = d0 * d0 + d1 * d1 + d2 * d2 >= least_sq


@njit(cache=True, nogil=True)
def step_kernel(depth, step, out):
    """Mark in ``out`` (bool (H, W)) the pixels whose 3x3 neighbourhood (inside the image) holds
    readings (``depth`` > 0, float32 (H, W)) that differ by more than ``step`` (float32)."""
    h, w = depth.shape
    for v in range(h):
        for u in range(w):
            near = np.float32(np.inf)
            far = np.float32(0)
            for y in range(max(v - 1, 0), min(v + 2, h)):
                for x in range(max(u - 1, 0), min(u + 2, w)):
                    z = depth[y, x]
                    if z > 0:
                        near = min(near, z)
                        far = max(far, z)
            out[v, u] = far - near > step
