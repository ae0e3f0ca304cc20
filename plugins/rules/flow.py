"""Image-space evidence for the robust rule: where optical flow says each point went.

Depth alone cannot see a motion that keeps a surface in place: a drawer's top sliding along itself,
a lever turning in its own plane, a globe spinning on its axis. The texture on the surface can. Dense
optical flow (OpenCV's DIS) from the source image to the target image, read at a source point's pixel
and back-projected with the target's depth, gives the 3D point it went to. Only points on texture
whose flow comes back to them when run backwards are used. On two-dimensional texture (both
eigenvalues of the image's structure tensor above ``min_gradient``) the flow is taken in full; on an
edge or a stripe (wood grain, a seam) only its component across the edge counts, since the aperture
problem lets it slide along the edge.
Where the flow cannot jump from frame i to frame i + k in one step (a fast spin changes how the
surface looks), it is followed through the frames in between, one checked step at a time.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from artclass_core import Cloud, Intrinsics, View

# Pixels of context kept around the two objects' boxes, so that flow has room to match.
_MARGIN_PX = 24
# Flow is computed on images at most this wide: DIS reaches further (in pixels of the frame) on a
# coarser image, and a hand-held object moves tens of pixels between frames i and i + k at 640x480.
FLOW_WIDTH_PX = 320
FLOW_ERROR_PX, FLOW_ERROR_SHARE = 1.5, 0.15
# An edge (one strong gradient direction) is used when its gradient is this many times min_gradient.
EDGE_FACTOR = 3.0


@dataclass(frozen=True)
class FlowEvidence:
    """Where the optical flow says each of P source points went.

    On two-dimensional texture (a corner, a blob) the flow is known in full: ``target`` holds the 3D
    point the flow leads to. On an edge or a stripe it is known only across the edge (the aperture
    problem: the flow along it is a guess), so such points have no ``target``; they keep the ``pixel``
    the flow leads to and the image ``normal`` of the edge, and a motion is checked along that normal
    only. Rows without any flow are NaN in all three.

    Attributes
    ----------
    target : (P, 3) metres, NaN where the flow is not known in full
    pixel : (P, 2) target image (u, v), NaN where there is no flow
    normal : (P, 2) unit image direction across the edge, NaN except at edge points
    tol : (P,) metres: how far from the flow's answer the point may truly have gone
    intrinsics : of the images (pixels of edge points are compared through them)
    """

    target: np.ndarray
    pixel: np.ndarray
    normal: np.ndarray
    tol: np.ndarray
    intrinsics: Intrinsics | None = None

    @classmethod
    def none(cls, n: int) -> FlowEvidence:
        return cls(np.full((n, 3), np.nan), np.full((n, 2), np.nan), np.full((n, 2), np.nan), np.zeros(n))

    @property
    def full(self) -> np.ndarray:
        return np.isfinite(self.target[:, 0])

    @property
    def edge(self) -> np.ndarray:
        return np.isfinite(self.normal[:, 0])

    def misfit(self, moved: np.ndarray) -> np.ndarray:
        """How far (m) each moved point lands from where the flow says it went, beyond the flow's
        tolerance (-inf where the flow says nothing); at edge points, measured across the edge.
        ``moved`` is (P, 3), or (H, P, 3) for H placements of the points at once."""
        out = np.full(moved.shape[:-1], -np.inf)
        f, e = self.full, self.edge
        out[..., f] = np.linalg.norm(moved[..., f, :] - self.target[f], axis=-1) - self.tol[f]
        if e.any():
            out[..., e] = self._across(moved[..., e, :], self.pixel[e], e) - self.tol[e]
        return out

    def apart(self, a: np.ndarray, b: np.ndarray, normals: np.ndarray, tau: float) -> np.ndarray:
        """Whether the flow can tell two placements a, b (P, 3) of the points apart: along the surface
        (``normals``) by more than tau plus its tolerance where it is known in full, across the edge
        where only that is known."""
        gap = a - b
        along = np.linalg.norm(gap - np.einsum("ij,ij->i", gap, normals)[:, None] * normals, axis=1)
        out = self.full & (along > tau + self.tol)
        e = self.edge
        if e.any():
            u, v = self.intrinsics.pixels(b[e])
            out[e] = self._across(a[e], np.stack([u, v], axis=1), e) > tau + self.tol[e]
        return out

    def constraints(self, moved: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the flow says about a small further displacement d of the points ``moved`` (the rows
        ``rows`` of this evidence, moved by some motion): linear equations g . d = b (metres), three for
        a point whose flow is known in full, one (across the edge) for an edge point. Returns the
        position in ``rows`` of each equation's point, the g (M, 3) and the b (M,)."""
        f, e = self.full[rows], self.edge[rows]
        fi, ei = np.flatnonzero(f), np.flatnonzero(e)
        g_full = np.tile(np.eye(3), (len(fi), 1))
        b_full = (self.target[rows[fi]] - moved[fi]).ravel()
        if not len(ei):
            return np.repeat(fi, 3), g_full, b_full
        P, n = moved[ei], self.normal[rows[ei]]
        K, z = self.intrinsics, np.abs(moved[ei, 2])
        u, v = K.pixels(P)
        # d(pixel across the edge)/dP, scaled by z/fx into metres at the point's depth
        g_edge = (
            np.column_stack(
                [n[:, 0] * K.fx / z, n[:, 1] * K.fy / z, -(n[:, 0] * (u - K.cx) + n[:, 1] * (v - K.cy)) / z]
            )
            * (z / K.fx)[:, None]
        )
        b_edge = (
            (n[:, 0] * (self.pixel[rows[ei], 0] - u) + n[:, 1] * (self.pixel[rows[ei], 1] - v)) * z / K.fx
        )
        return (
            np.concatenate([np.repeat(fi, 3), ei]),
            np.concatenate([g_full, g_edge]),
            np.concatenate([b_full, b_edge]),
        )

    def _across(self, moved: np.ndarray, pixel: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Distance (m, at the moved points' depth) between the moved points' pixels and ``pixel``,
        across the edge of each row."""
        u, v = self.intrinsics.pixels(moved)
        off = np.abs((u - pixel[:, 0]) * self.normal[rows, 0] + (v - pixel[:, 1]) * self.normal[rows, 1])
        return off * np.abs(moved[..., 2]) / self.intrinsics.fx


def flow_targets(
    source: Cloud,
    target: Cloud,
    points: np.ndarray,
    *,
    between: Sequence[Cloud] = (),
    min_gradient: float = 1.0,
    scratch: dict | None = None,
) -> FlowEvidence:
    """Where the optical flow says source ``points`` (P, 3) went (see :class:`FlowEvidence`), and how
    far from there (m) each may truly have gone: FLOW_ERROR_PX pixels of the flow's image per flow step
    plus FLOW_ERROR_SHARE of the displacement. Measured on the rigid carries of the 640x480 benchmark
    (``benchmarks/flow_accuracy.py``), in full-resolution pixels: on 2-D texture DIS errs by 0.85-1.1 px
    (median) and 3.5-3.9 px (90th percentile), more the further the point moved; across an edge by
    0.4-0.5 px and 1.4-2.6 px. A tighter tolerance across edges (1 px of the flow's image instead of
    1.5) called 8 more drawer pairs right, but put false AM pairs on a carried open box (depth_threshold).

    Points are used on texture: two-dimensional (both eigenvalues of the structure tensor at least
    ``min_gradient`` grey levels per pixel, squared) or an edge (the larger one at least EDGE_FACTOR
    times that, the smaller below it). The flow is read from the source image straight to the
    target's. Where that fails (a globe spun by 50 degrees between frames i and i + k no longer looks
    the same), and the clouds of the frames ``between`` are given, it is followed from frame to frame
    instead, each step checked forwards and backwards; a point lost on the way has no flow. The flows of
    those steps are kept in ``scratch`` (the pair's scratch dict), when given.
    """
    out = FlowEvidence.none(len(points))
    views = [c.view for c in (source, *between, target)]
    if any(v is None for v in views) or not len(points) or len({v.gray.shape for v in views}) > 1:
        return out
    K = source.view.intrinsics
    u0, v0 = K.pixels(points)
    first = _Flow(source.view, target.view)
    corner, normal = first.texture(u0, v0, min_gradient)
    use = (points[:, 2] > 0) & (corner | np.isfinite(normal[:, 0]))
    u, v, ok = first.follow(u0, v0, use, normal)
    steps = np.ones(len(points))
    if between and not ok.all():
        clouds = (source, *between, target)
        uc, vc, oc = u0, v0, use & ~ok
        for a, b in zip(clouds[:-1], clouds[1:]):
            uc, vc, oc = _link(a, b, {} if scratch is None else scratch).follow(uc, vc, oc, normal)
        u, v, ok = np.where(oc, uc, u), np.where(oc, vc, v), ok | oc
        steps[oc] = len(clouds) - 1
    full = ok & corner
    depth = _median_depth(target.view.depth_m, np.round(v).astype(int), np.round(u).astype(int), full)
    full &= depth > 0
    ok &= full | ~corner
    edge = ok & ~corner
    shift_px = offset_px(u - u0, v - v0, normal)  # along an edge the flow is a guess
    tol = np.where(
        ok,
        (FLOW_ERROR_PX * np.sqrt(steps) / first.scale + FLOW_ERROR_SHARE * shift_px) * points[:, 2] / K.fx,
        0.0,
    )
    pixel = np.where(ok[:, None], np.stack([u, v], axis=1), np.nan)
    target_pts = np.full((len(points), 3), np.nan)
    target_pts[full] = K.points(u[full], v[full], depth[full])
    return FlowEvidence(target_pts, pixel, np.where(edge[:, None], normal, np.nan), tol, K)


def offset_px(du: np.ndarray, dv: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Length (px) of image offsets (du, dv): across the edge where ``normal`` (N, 2) gives its
    direction, in full where it is NaN (no edge)."""
    across = np.abs(du * np.nan_to_num(normal[:, 0]) + dv * np.nan_to_num(normal[:, 1]))
    return np.where(np.isfinite(normal[:, 0]), across, np.hypot(du, dv))


def _link(a: Cloud, b: Cloud, scratch: dict) -> _Flow:
    """The flow between two consecutive clouds' images, kept in the pair's ``scratch`` (re-deciding the
    pair under other thresholds finds it again)."""
    key = ("flow", a.frame_index, b.frame_index)
    if key not in scratch:
        scratch[key] = _Flow(a.view, b.view)
    return scratch[key]


class _Flow:
    """Forward and backward DIS flow between two views, and the first view's structure tensor, on the
    box around both objects (plus a margin), at most FLOW_WIDTH_PX wide."""

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
        ga, gb = (np.ascontiguousarray(g[self.y0 : y1, self.x0 : x1]) for g in (a.gray, b.gray))
        if self.scale < 1.0:
            ga, gb = (
                cv2.resize(g, None, fx=self.scale, fy=self.scale, interpolation=cv2.INTER_AREA)
                for g in (ga, gb)
            )
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        self.forward, self.backward = dis.calc(ga, gb, None), dis.calc(gb, ga, None)
        self.tensor = _structure_tensor(ga)

    def _image_xy(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Full-image pixels in the flow's image, and whether they are inside it."""
        h, w = self.tensor.shape[:2]
        xs, ys = (u - self.x0) * self.scale, (v - self.y0) * self.scale
        return xs, ys, (xs >= 0) & (xs <= w - 1) & (ys >= 0) & (ys <= h - 1)

    def texture(self, u: np.ndarray, v: np.ndarray, min_gradient: float) -> tuple[np.ndarray, np.ndarray]:
        """At full-image pixels (u, v): whether the texture is two-dimensional, and the unit direction
        across the edge where it is an edge (NaN rows elsewhere); see :func:`flow_targets`."""
        corner, normal = np.zeros(len(u), bool), np.full((len(u), 2), np.nan)
        if self.forward is None:
            return corner, normal
        xs, ys, inside = self._image_xy(u, v)
        xx, yy, xy = _sample(self.tensor, xs[inside], ys[inside]).T
        half = np.sqrt(((xx - yy) / 2) ** 2 + xy**2)
        big, small = (xx + yy) / 2 + half, (xx + yy) / 2 - half
        idx = np.flatnonzero(inside)
        corner[idx] = small >= min_gradient**2
        edge = ~corner[idx] & (big >= (EDGE_FACTOR * min_gradient) ** 2)
        angle = 0.5 * np.arctan2(2 * xy[edge], xx[edge] - yy[edge])  # the gradient's direction
        normal[idx[edge]] = np.stack([np.cos(angle), np.sin(angle)], axis=1)
        return corner, normal

    def follow(
        self,
        u: np.ndarray,
        v: np.ndarray,
        ok: np.ndarray,
        normal: np.ndarray,
        *,
        max_round_trip_px: float = 1.0,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Move the ``ok`` full-image pixels (u, v) along the flow; kept are those whose backward flow
        brings them back within ``max_round_trip_px`` of the flow's image (across the edge, at rows
        with an edge ``normal``). Returns the moved u, v and which were kept."""
        u, v, ok = u.astype(float), v.astype(float), ok.copy()
        if self.forward is None:
            return u, v, np.zeros_like(ok)
        h, w = self.tensor.shape[:2]
        xs, ys, inside = self._image_xy(u, v)
        ok &= inside
        fx, fy = _sample(self.forward, xs[ok], ys[ok]).T
        xt, yt = xs[ok] + fx, ys[ok] + fy
        inside = (xt >= 0) & (xt <= w - 1) & (yt >= 0) & (yt <= h - 1)
        bx, by = _sample(self.backward, np.clip(xt, 0, w - 1), np.clip(yt, 0, h - 1)).T
        good = inside & (offset_px(xt + bx - xs[ok], yt + by - ys[ok], normal[ok]) <= max_round_trip_px)
        idx = np.flatnonzero(ok)
        u[idx], v[idx] = xt / self.scale + self.x0, yt / self.scale + self.y0
        ok[idx[~good]] = False
        return u, v, ok


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


def _structure_tensor(gray: np.ndarray) -> np.ndarray:
    """The 5x5 structure tensor (gx^2, gy^2, gx gy), shape (H, W, 3), in (grey levels per pixel)^2."""
    g = gray.astype(np.float32)
    gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8, cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8
    return np.dstack([cv2.boxFilter(m, -1, (5, 5)) for m in (gx * gx, gy * gy, gx * gy)])


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
