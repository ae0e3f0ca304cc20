"""The compiled (Numba) loops of finding parts, one pass over the points where numpy makes a dozen
temporary arrays: the parts' look-ups (object points moved by each part's motion into another frame
and looked up in its depth and intensity images), the choice of each point's part from them, the
overlaps of two pairs' labellings, and how far a part reaches. Imported when first needed, so that
importing the plugins does not load Numba."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _mirrored(i, n):
    """Index i mirrored into 0 .. n - 1 about the edge pixels (OpenCV's default border)."""
    i = -i if i < 0 else i
    i = 2 * n - 2 - i if i >= n else i
    return min(max(i, 0), n - 1)


@njit(cache=True, nogil=True)
def _smoothed(gray, row, col):
    """The intensity at (row, col) smoothed over its 3 x 3 neighbours, weighed (1, 2, 1) x (1, 2, 1) /
    16, the image's edges mirrored: ``cv2.GaussianBlur(gray, (3, 3), 0)`` there, to the bit."""
    rows, cols = gray.shape
    total = 0
    for dr in range(-1, 2):
        r = _mirrored(row + dr, rows)
        for dc in range(-1, 2):
            total += (2 - abs(dr)) * (2 - abs(dc)) * np.int64(gray[r, _mirrored(col + dc, cols)])
    return (total + 8) >> 4


@njit(cache=True, nogil=True)
def smoothed_at(gray, pixels):
    """The smoothed intensities (N,) of :func:`_smoothed` at pixels (N, 2), (column, row) each."""
    out = np.empty(pixels.shape[0])
    for n in range(pixels.shape[0]):
        out[n] = _smoothed(gray, pixels[n, 1], pixels[n, 0])
    return out


@njit(cache=True, nogil=True)
def look_kernel(points, motions, depth, gray, camera, reach_m, shade, residual, change, landings):
    """Move each point (N, 3) by each motion (H, 4, 4), project it with ``camera`` (fx, fy, cx, cy)
    to its nearest pixel of ``depth`` (metres, 0 = no reading) and update, per motion and point:

    - ``residual`` (H, N), the nearest yet: the distance along the ray to the surface seen there;
      inf where the camera measured nothing; NaN (no evidence) where the surface is more than
      ``reach_m`` in front of the point (it hides the point) or the point leaves the image;
    - where it lands on the surface (within ``reach_m``) and ``gray`` (the view's intensities) is not
      empty: ``change`` (H, N) += the change of the intensity there (smoothed over the pixel's
      neighbours, :func:`_smoothed`) from the point's own ``shade`` (N,), and ``landings`` (H, N)
      += 1.
    """
    rows, cols = depth.shape
    fx, fy, cx, cy = camera[0], camera[1], camera[2], camera[3]
    shaded = gray.shape[0] > 0
    for h in range(motions.shape[0]):
        T = motions[h]
        for n in range(points.shape[0]):
            p0, p1, p2 = points[n, 0], points[n, 1], points[n, 2]
            x = T[0, 0] * p0 + T[0, 1] * p1 + T[0, 2] * p2 + T[0, 3]
            y = T[1, 0] * p0 + T[1, 1] * p1 + T[1, 2] * p2 + T[1, 3]
            z = T[2, 0] * p0 + T[2, 1] * p1 + T[2, 2] * p2 + T[2, 3]
            found = math.nan
            if z > 0:
                u = fx * x / z + cx + 0.5  # + 0.5: the nearest pixel, by truncation
                v = fy * y / z + cy + 0.5
                if u >= 0 and u < cols and v >= 0 and v < rows:
                    iu, iv = int(u), int(v)
                    surface = depth[iv, iu]
                    if surface <= 0:
                        found = math.inf
                    elif surface >= z - reach_m:
                        found = abs(z - surface)
                        if shaded and found < reach_m:
                            change[h, n] += abs(np.float64(_smoothed(gray, iv, iu)) - shade[n])
                            landings[h, n] += 1
            if math.isnan(residual[h, n]) or found < residual[h, n]:
                residual[h, n] = found


@njit(cache=True, nogil=True)
def contingency(keys_a, order_a, labels_a, keys_b, order_b, labels_b):
    """The contingency table (A + 2, B + 2) of two labellings (labels >= -1, -1: no motion) over the
    pixels both label: entry (m + 1, n + 1) counts the pixels labelled m in the first and n in the
    second. A labelling's pixels are given as unique keys with the order that sorts them."""
    table = np.zeros((labels_a.max() + 2, labels_b.max() + 2), np.int64)
    i = j = 0
    while i < len(order_a) and j < len(order_b):
        a, b = order_a[i], order_b[j]
        if keys_a[a] < keys_b[b]:
            i += 1
        elif keys_b[b] < keys_a[a]:
            j += 1
        else:
            table[labels_a[a] + 1, labels_b[b] + 1] += 1
            i += 1
            j += 1
    return table


@njit(cache=True, nogil=True)
def _two_lowest(values):
    """The index of the lowest of ``values`` (H,) (the first, among equals) and the lowest of the
    others (inf when there are none)."""
    first = 0
    for h in range(1, len(values)):
        first = h if values[h] < values[first] else first
    second = math.inf
    for h in range(len(values)):
        if h != first and values[h] < second:
            second = values[h]
    return first, second


@njit(cache=True, nogil=True)
def by_depth(residual, change, landings, reach_m, margin):
    """Each point's part by depth, from the nearest each part's motion puts it to a surface seen
    (``residual`` (H, N), as :func:`look_kernel` leaves it): a part pays that distance when the point
    lands on the surface, infinitely when it lands off it (the camera sees past it, or no object),
    ``reach_m`` when it is hidden (no evidence: better than landing off the surface, worse than
    landing on it). Returns the cheapest part (N,); whether the next costs more than ``margin`` more
    (N,); and the mean change of intensity (H, N) where the parts that cost within ``margin`` of the
    cheapest landed the point (inf for the other parts, and where a part never landed it)."""
    H, N = residual.shape
    best, decisive, candidate = np.empty(N, np.int64), np.empty(N, np.bool_), np.empty((H, N))
    cost = np.empty(H)
    for n in range(N):
        for h in range(H):
            r = residual[h, n]
            cost[h] = reach_m if math.isnan(r) else (r if r < reach_m else math.inf)
        first, second = _two_lowest(cost)
        best[n] = first
        decisive[n] = second - cost[first] > margin  # never where both are infinite
        for h in range(H):
            landed = cost[h] <= cost[first] + margin and landings[h, n] > 0
            candidate[h, n] = change[h, n] / landings[h, n] if landed else math.inf
    return best, decisive, candidate


@njit(cache=True, nogil=True)
def by_shade(best, decisive, change, limit):
    """Points ``decisive`` leaves undecided take the part with the lowest ``change`` (H, N) when the
    next is higher by more than ``limit``; returns the parts and whether each is decided, (N,) each."""
    best, decisive = best.copy(), decisive.copy()
    for n in range(len(best)):
        if decisive[n]:
            continue
        first, second = _two_lowest(change[:, n])
        if second - change[first, n] > limit:
            best[n], decisive[n] = first, True
    return best, decisive


@njit(cache=True, nogil=True)
def farthest(points, centre):
    """The largest distance of the points (N, 3) from ``centre`` (3,); 0 for none."""
    most = 0.0
    for n in range(points.shape[0]):
        d0, d1, d2 = points[n, 0] - centre[0], points[n, 1] - centre[1], points[n, 2] - centre[2]
        most = max(most, d0 * d0 + d1 * d1 + d2 * d2)
    return math.sqrt(most)


def warm_up() -> None:
    """Load the compiled loops (Numba's cached machine code, or compile them) with the argument types
    of the parts' calls."""
    none, one = np.zeros((1, 1)), np.zeros(1, np.int64)
    contingency(one, one, one, one, one, one)
    smoothed_at(np.zeros((1, 1), np.uint8), np.zeros((1, 2), np.int64))
    best, decisive, candidate = by_depth(none.copy(), none.copy(), none.copy(), 0.01, 0.001)
    by_shade(best, decisive, candidate, 1.0)
    farthest(np.zeros((1, 3)), np.zeros(3))
    look_kernel(
        np.zeros((1, 3)),
        np.eye(4)[None],
        np.zeros((1, 1), np.float32),
        np.zeros((1, 1), np.uint8),
        np.ones(4),
        0.01,
        np.zeros(1),
        none.copy(),
        none.copy(),
        none.copy(),
    )
