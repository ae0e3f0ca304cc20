"""Image-space evidence for the robust rule: where optical flow says each point went.

Depth alone cannot see a motion that keeps a surface in place: a drawer's top sliding along itself,
a lever turning in its own plane, a globe spinning on its axis. The texture on the surface can. Dense
optical flow (OpenCV's DIS) from the source image to the target image, read at a source point's pixel
and back-projected with the target's depth, gives the 3D point it went to. Only points on texture
(both eigenvalues of the image's structure tensor above ``min_gradient``, so the aperture problem
cannot slide the flow along an edge) whose flow comes back to them when run backwards are used.
"""

from __future__ import annotations

import cv2
import numpy as np

from artclass_core import Cloud

# Pixels of context kept around the two objects' boxes, so that flow has room to match.
_MARGIN_PX = 24
# Flow is computed on images at most this wide: DIS reaches further (in pixels of the frame) on a
# coarser image, and a hand-held object moves tens of pixels between frames i and i + k at 640x480.
FLOW_WIDTH_PX = 320
FLOW_ERROR_PX, FLOW_ERROR_SHARE = 1.5, 0.15


def flow_targets(source: Cloud, target: Cloud, points: np.ndarray, *, min_gradient: float = 1.0,
                 max_round_trip_px: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """For source ``points`` (P, 3): the target point each went to along the optical flow (NaN rows
    where that is unknown: no texture, occluded, inconsistent, no target depth), and how far from it
    (m) the point may truly have gone: FLOW_ERROR_PX pixels of the flow's image plus FLOW_ERROR_SHARE
    of the displacement (measured on the synthetic carries: DIS is good to about a pixel on slow
    motions and drifts by 2-3 pixels on 20-pixel ones)."""
    out, tol = np.full((len(points), 3), np.nan), np.zeros(len(points))
    a, b = source.view, target.view
    if a is None or b is None or not len(points) or a.gray.shape != b.gray.shape:
        return out, tol
    K = a.intrinsics
    ys, xs = np.nonzero((a.depth_m > 0) | (b.depth_m > 0))
    if not len(ys):
        return out, tol
    h, w = a.gray.shape
    scale = min(1.0, FLOW_WIDTH_PX / w)
    y0, y1 = max(0, ys.min() - _MARGIN_PX), min(h, ys.max() + _MARGIN_PX + 1)
    x0, x1 = max(0, xs.min() - _MARGIN_PX), min(w, xs.max() + _MARGIN_PX + 1)
    ga, gb = (np.ascontiguousarray(g[y0:y1, x0:x1]) for g in (a.gray, b.gray))
    forward, backward, texture = _flow(ga, gb, scale=scale)

    z = points[:, 2]
    u, v = K.pixels(points)
    u, v = u - x0, v - y0
    ui, vi = np.round(u).astype(int), np.round(v).astype(int)
    ok = (z > 0) & (ui >= 0) & (ui < x1 - x0) & (vi >= 0) & (vi < y1 - y0)
    ok[ok] &= texture[vi[ok], ui[ok]] >= min_gradient ** 2
    ut, vt = u.copy(), v.copy()
    ut[ok] += forward[vi[ok], ui[ok], 0]
    vt[ok] += forward[vi[ok], ui[ok], 1]
    uti, vti = np.round(ut).astype(int), np.round(vt).astype(int)
    ok &= (uti >= 1) & (uti < x1 - x0 - 1) & (vti >= 1) & (vti < y1 - y0 - 1)
    back = backward[vti[ok], uti[ok]]
    ok[ok] &= np.hypot(ut[ok] + back[:, 0] - u[ok], vt[ok] + back[:, 1] - v[ok]) <= max_round_trip_px / scale
    depth = _median_depth(b.depth_m[y0:y1, x0:x1], vti[ok], uti[ok])
    good = depth > 0
    idx = np.flatnonzero(ok)[good]
    zt = depth[good]
    out[idx] = K.points(ut[idx] + x0, vt[idx] + y0, zt)
    shift_px = np.hypot(ut - u, vt - v)
    tol[idx] = (FLOW_ERROR_PX / scale + FLOW_ERROR_SHARE * shift_px[idx]) * points[idx, 2] / K.fx
    return out, tol


def _flow(ga: np.ndarray, gb: np.ndarray, *, scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Forward and backward DIS flow, and the texture (structure tensor's smaller eigenvalue), all
    computed on the images resized by ``scale`` and returned at the given images' size and pixels."""
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    small = [cv2.resize(g, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) for g in (ga, gb)] \
        if scale < 1.0 else [ga, gb]
    maps = [dis.calc(small[0], small[1], None), dis.calc(small[1], small[0], None), _min_eigenvalue(small[0])]
    if scale >= 1.0:
        return tuple(maps)
    size = (ga.shape[1], ga.shape[0])
    return (cv2.resize(maps[0], size) / scale, cv2.resize(maps[1], size) / scale,
            cv2.resize(maps[2], size, interpolation=cv2.INTER_NEAREST))


def _min_eigenvalue(gray: np.ndarray) -> np.ndarray:
    """Smaller eigenvalue of the 5x5 structure tensor, in (grey levels per pixel)^2."""
    g = gray.astype(np.float32)
    gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8, cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8
    xx, yy, xy = (cv2.boxFilter(m, -1, (5, 5)) for m in (gx * gx, gy * gy, gx * gy))
    return (xx + yy) / 2 - np.sqrt(((xx - yy) / 2) ** 2 + xy ** 2)


def _median_depth(depth: np.ndarray, v: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Median of the valid depths in the 3x3 window at each (v, u); 0 where fewer than 5 are valid."""
    win = np.stack([depth[v + dv, u + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)], axis=1)
    win = np.where(win > 0, win, np.nan)
    enough = np.sum(np.isfinite(win), axis=1) >= 5
    med = np.zeros(len(v))
    med[enough] = np.nanmedian(win[enough], axis=1)
    return med


def kabsch(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Least-squares rigid T (4x4) with T p ~ q."""
    cp, cq = p.mean(0), q.mean(0)
    U, _, Vt = np.linalg.svd((p - cp).T @ (q - cq))
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, cq - R @ cp
    return T
