"""Image-space evidence for the robust rule: where optical flow says each point went.

Depth alone cannot see a motion that keeps a surface in place: a drawer's top sliding along itself,
a lever turning in its own plane, a globe spinning on its axis. The texture on the surface can. Dense
optical flow (OpenCV's DIS) from the source image to the target image, read at a source point's pixel
and back-projected with the target's depth, gives the 3D point it went to. Only points on texture
(both eigenvalues of the image's structure tensor above ``min_gradient``, so the aperture problem
cannot slide the flow along an edge) whose flow comes back to them when run backwards are used.
Where the flow cannot jump from frame i to frame i + k in one step (a fast spin changes how the
surface looks), it is followed through the frames in between, one checked step at a time.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from artclass_core import Cloud, View
from artclass_core.pipeline import pair_memo

# Pixels of context kept around the two objects' boxes, so that flow has room to match.
_MARGIN_PX = 24
# Flow is computed on images at most this wide: DIS reaches further (in pixels of the frame) on a
# coarser image, and a hand-held object moves tens of pixels between frames i and i + k at 640x480.
FLOW_WIDTH_PX = 320
FLOW_ERROR_PX, FLOW_ERROR_SHARE = 1.5, 0.15


def flow_targets(source: Cloud, target: Cloud, points: np.ndarray, *, between: Sequence[Cloud] = (),
                 min_gradient: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """For source ``points`` (P, 3): the target point each went to along the optical flow (NaN rows
    where that is unknown: no texture, occluded, inconsistent, no target depth), and how far from it
    (m) the point may truly have gone: FLOW_ERROR_PX pixels of the flow's image per flow step plus
    FLOW_ERROR_SHARE of the displacement (measured on the synthetic carries: DIS is good to about a
    pixel on slow motions and drifts by 2-3 pixels on 20-pixel ones).

    The flow is read from the source image straight to the target's. Where that fails (a globe spun
    by 50 degrees between frames i and i + k no longer looks the same), and the clouds of the frames
    ``between`` are given, it is followed from frame to frame instead, each step checked forwards and
    backwards; a point lost on the way has no flow target.
    """
    out, tol = np.full((len(points), 3), np.nan), np.zeros(len(points))
    views = [c.view for c in (source, *between, target)]
    if any(v is None for v in views) or not len(points) or len({v.gray.shape for v in views}) > 1:
        return out, tol
    K = source.view.intrinsics
    u0, v0 = K.pixels(points)
    u, v, ok, scale = _Flow(source.view, target.view).follow(u0, v0, points[:, 2] > 0, min_gradient=min_gradient)
    steps = np.ones(len(points))
    if between and not ok.all():
        clouds = (source, *between, target)
        uc, vc, oc = u0, v0, ~ok & (points[:, 2] > 0)
        for a, b in zip(clouds[:-1], clouds[1:]):
            uc, vc, oc, _ = _link(a, b).follow(uc, vc, oc, min_gradient=min_gradient if a is source else 0.0)
        u, v, ok = np.where(oc, uc, u), np.where(oc, vc, v), ok | oc
        steps[oc] = len(clouds) - 1
    depth = _median_depth(target.view.depth_m, np.round(v).astype(int), np.round(u).astype(int), ok)
    idx = np.flatnonzero(depth > 0)
    out[idx] = K.points(u[idx], v[idx], depth[idx])
    shift_px = np.hypot(u - u0, v - v0)
    tol[idx] = ((FLOW_ERROR_PX * np.sqrt(steps[idx])) / scale + FLOW_ERROR_SHARE * shift_px[idx]) \
        * points[idx, 2] / K.fx
    return out, tol


def _link(a: Cloud, b: Cloud) -> "_Flow":
    """The flow between two consecutive clouds' images, kept while both clouds live: the pairs
    (i, i + k) that span the step share it."""
    memo = pair_memo(a, b)
    if "flow" not in memo:
        memo["flow"] = _Flow(a.view, b.view)
    return memo["flow"]


class _Flow:
    """Forward and backward DIS flow between two views, and the first view's texture, on the box
    around both objects (plus a margin), at most FLOW_WIDTH_PX wide."""

    def __init__(self, a: View, b: View):
        h, w = a.gray.shape
        ys, xs = np.nonzero((a.depth_m > 0) | (b.depth_m > 0))
        self.scale = min(1.0, FLOW_WIDTH_PX / w)
        self.x0 = self.y0 = 0
        if not len(ys):
            self.forward = None
            return
        self.y0, y1 = max(0, ys.min() - _MARGIN_PX), min(h, ys.max() + _MARGIN_PX + 1)
        self.x0, x1 = max(0, xs.min() - _MARGIN_PX), min(w, xs.max() + _MARGIN_PX + 1)
        ga, gb = (np.ascontiguousarray(g[self.y0:y1, self.x0:x1]) for g in (a.gray, b.gray))
        if self.scale < 1.0:
            ga, gb = (cv2.resize(g, None, fx=self.scale, fy=self.scale, interpolation=cv2.INTER_AREA)
                      for g in (ga, gb))
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        self.forward, self.backward = dis.calc(ga, gb, None), dis.calc(gb, ga, None)
        self.texture = _min_eigenvalue(ga)

    def follow(self, u: np.ndarray, v: np.ndarray, ok: np.ndarray, *, min_gradient: float,
               max_round_trip_px: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Move full-image pixels (u, v) along the flow. Kept (``ok``) are pixels on texture of at least
        ``min_gradient`` grey levels per pixel of the flow's image whose backward flow brings them back
        within ``max_round_trip_px`` of that image; returns the moved u, v, ok and the flow's scale."""
        u, v, ok = u.astype(float), v.astype(float), ok.copy()
        if self.forward is None:
            return u, v, np.zeros_like(ok), self.scale
        h, w = self.texture.shape
        xs, ys = (u - self.x0) * self.scale, (v - self.y0) * self.scale
        ok &= (xs >= 0) & (xs <= w - 1) & (ys >= 0) & (ys <= h - 1)
        if min_gradient > 0:
            ok[ok] &= _sample(self.texture, xs[ok], ys[ok]) >= min_gradient ** 2
        fx, fy = _sample(self.forward, xs[ok], ys[ok]).T
        xt, yt = xs[ok] + fx, ys[ok] + fy
        inside = (xt >= 0) & (xt <= w - 1) & (yt >= 0) & (yt <= h - 1)
        bx, by = _sample(self.backward, np.clip(xt, 0, w - 1), np.clip(yt, 0, h - 1)).T
        good = inside & (np.hypot(xt + bx - xs[ok], yt + by - ys[ok]) <= max_round_trip_px)
        idx = np.flatnonzero(ok)
        u[idx], v[idx] = xt / self.scale + self.x0, yt / self.scale + self.y0
        ok[idx[~good]] = False
        return u, v, ok, self.scale


def _sample(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of an (H, W) or (H, W, C) image at the points (x, y) inside it."""
    x0 = np.clip(np.floor(x).astype(int), 0, image.shape[1] - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, image.shape[0] - 2)
    ax, ay = x - x0, y - y0
    if image.ndim == 3:
        ax, ay = ax[:, None], ay[:, None]
    top = image[y0, x0] * (1 - ax) + image[y0, x0 + 1] * ax
    bottom = image[y0 + 1, x0] * (1 - ax) + image[y0 + 1, x0 + 1] * ax
    return top * (1 - ay) + bottom * ay


def _min_eigenvalue(gray: np.ndarray) -> np.ndarray:
    """Smaller eigenvalue of the 5x5 structure tensor, in (grey levels per pixel)^2."""
    g = gray.astype(np.float32)
    gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8, cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8
    xx, yy, xy = (cv2.boxFilter(m, -1, (5, 5)) for m in (gx * gx, gy * gy, gx * gy))
    return (xx + yy) / 2 - np.sqrt(((xx - yy) / 2) ** 2 + xy ** 2)


def _median_depth(depth: np.ndarray, v: np.ndarray, u: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Median of the valid depths in the 3x3 window at each used (v, u) (0 where fewer than 5 are valid,
    the window leaves the image, or the pixel is not used)."""
    h, w = depth.shape
    use = use & (u >= 1) & (u < w - 1) & (v >= 1) & (v < h - 1)
    med = np.zeros(len(v))
    v, u = v[use], u[use]
    win = np.stack([depth[v + dv, u + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)], axis=1)
    win = np.where(win > 0, win, np.nan)
    enough = np.sum(np.isfinite(win), axis=1) >= 5
    out = np.zeros(len(v))
    out[enough] = np.nanmedian(win[enough], axis=1)
    med[use] = out
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
