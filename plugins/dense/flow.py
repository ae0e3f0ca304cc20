"""Where optical flow says each source point went, on texture only.

Depth alone cannot see a motion that keeps a surface in place (a drawer's top sliding along itself,
a disc spinning about its own axis); the texture on the surface can. OpenCV's DIS flow is run both
ways on the two objects' crop, at most ``FLOW_WIDTH_PX`` wide (DIS reaches further on a coarser
image). On two-dimensional texture (both eigenvalues of the structure tensor above ``min_texture``)
a point's flow is taken in full; on an edge or a stripe (only the larger eigenvalue above it) only
the flow across the edge is known (the aperture problem), so the point keeps the edge's normal and is
compared along it. Either way the backward flow must bring the point back within
``max_roundtrip_px``.

Each thread keeps one DIS object, which keeps its image pyramids and buffers from one pair to the next
(about a tenth of the flow's CPU time, against a new one for every pair) and nothing else: a pair's
flow does not depend on the pairs before it.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import cv2
import numpy as np

from artclass_core import Cloud

from .image import bounding_box

FLOW_WIDTH_PX = 320
_MARGIN_PX = 24  # well beyond what the structure tensor reads about a point (3 px)
STRUCTURE_WINDOW_PX = 5
_REMAP_ROWS = 32000
_thread = threading.local()


def _dis() -> cv2.DISOpticalFlow:
    """This thread's DIS optical flow (OpenCV's ``MEDIUM`` preset)."""
    if not hasattr(_thread, "dis"):
        _thread.dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return _thread.dis


def structure(
    gray: np.ndarray, pixels: np.ndarray, *, window_px: int = STRUCTURE_WINDOW_PX
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The structure tensor at some pixels of an image.

    Parameters
    ----------
    gray : (H, W) uint8 image
    pixels : (N, 2) int (column, row) of the pixels asked about
    window_px : side of the square window (pixels) the gradients' products are averaged over

    Returns
    -------
    small, large : (N,) float32 smaller and larger eigenvalue (grey levels per pixel, squared)
    angle : (N,) float32 angle (radians) of the larger one's eigenvector, the direction across an edge
    """
    return eigen(tensor(gray, window_px=window_px), pixels)


def tensor(gray: np.ndarray, *, window_px: int = STRUCTURE_WINDOW_PX) -> tuple[np.ndarray, ...]:
    """The structure tensor of every pixel of ``gray``: the gradients' products (xx, yy, xy), each
    (H, W) float32, averaged over a square window of ``window_px``."""
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
    k = (window_px, window_px)
    return tuple(cv2.blur(a, k) for a in (gx * gx, gy * gy, gx * gy))


def eigen(products: tuple[np.ndarray, ...], pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`structure`'s eigenvalues and angle at ``pixels`` (N, 2: column, row) of a :func:`tensor`."""
    xx, yy, xy = (a[pixels[:, 1], pixels[:, 0]] for a in products)
    half = np.sqrt(np.square((xx - yy) / 2) + np.square(xy))
    return (xx + yy) / 2 - half, (xx + yy) / 2 + half, 0.5 * np.arctan2(2 * xy, xx - yy)


@dataclass(frozen=True)
class CropFlow:
    """DIS optical flow both ways on the two objects' crop (the union of their masks' boxes, widened
    by ``_MARGIN_PX``), at the crop's working scale, and the source image's structure tensor there
    (full resolution: :func:`tensor`)."""

    forward: np.ndarray  # (h, w, 2) float32, crop pixels
    backward: np.ndarray  # (h, w, 2) float32, crop pixels
    box: tuple[int, int, int, int]  # (row0, row1, column0, column1) of the crop in the image
    scale: tuple[float, float]  # (sx, sy): crop pixels per image pixel
    texture: tuple[np.ndarray, ...]  # the source's tensor on the crop, full resolution


def crop_flow(source: Cloud, target: Cloud) -> CropFlow | None:
    """The optical flow between the two clouds' images about the objects; None without their masks."""
    a, b = source.view, target.view
    boxes = [bounding_box(v.mask) for v in (a, b) if v is not None and v.mask is not None]
    if len(boxes) < 2 or None in boxes:
        return None
    h, w = a.gray.shape
    ((r0, r1), (c0, c1)), ((s0, s1), (d0, d1)) = boxes
    r0, c0 = max(min(r0, s0) - _MARGIN_PX, 0), max(min(c0, d0) - _MARGIN_PX, 0)
    r1, c1 = min(max(r1, s1) + _MARGIN_PX, h), min(max(c1, d1) + _MARGIN_PX, w)
    scale = min(1.0, FLOW_WIDTH_PX / max(c1 - c0, 1))
    size = (max(int(round((c1 - c0) * scale)), 8), max(int(round((r1 - r0) * scale)), 8))
    ga = cv2.resize(a.gray[r0:r1, c0:c1], size, interpolation=cv2.INTER_AREA)
    gb = cv2.resize(b.gray[r0:r1, c0:c1], size, interpolation=cv2.INTER_AREA)
    dis = _dis()
    forward = dis.calc(ga, gb, None)
    backward = dis.calc(gb, ga, None)
    return CropFlow(
        forward,
        backward,
        (r0, r1, c0, c1),
        (size[0] / (c1 - c0), size[1] / (r1 - r0)),
        tensor(a.gray[r0:r1, c0:c1]),
    )


def flow_targets(
    source: Cloud,
    target: Cloud,
    *,
    min_texture: float,
    max_roundtrip_px: float,
    flow: CropFlow | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Where optical flow takes each source point (``flow``: the pair's :func:`crop_flow`, computed
    when not given).

    Returns
    -------
    pixel : (N, 2) target (column, row), not rounded; NaN where unknown
    normal : (N, 2) unit image direction across the edge at an edge point (compare along it only);
        NaN at points with two-dimensional texture and where the flow is unknown
    """
    out = np.full((len(source), 2), np.nan)
    normal = np.full((len(source), 2), np.nan)
    flow = flow or crop_flow(source, target)
    if flow is None:
        return out, normal
    forward, backward = flow.forward, flow.backward
    (r0, _, c0, _), (sx, sy) = flow.box, flow.scale
    size = forward.shape[1::-1]
    px = (source.pixels[:, 0] - c0) * sx
    py = (source.pixels[:, 1] - r0) * sy
    iu = np.clip(np.rint(px).astype(int), 0, size[0] - 1)
    iv = np.clip(np.rint(py).astype(int), 0, size[1] - 1)
    f = forward[iv, iu]
    back = cv2.remap(
        backward,
        (px + f[:, 0]).astype(np.float32)[:, None],
        (py + f[:, 1]).astype(np.float32)[:, None],
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )[:, 0]
    small, large, angle = eigen(flow.texture, source.pixels - [c0, r0])
    across = np.column_stack([np.cos(angle), np.sin(angle)])
    miss = np.column_stack([(f[:, 0] + back[:, 0]) / sx, (f[:, 1] + back[:, 1]) / sy])
    full = (small >= min_texture) & (np.hypot(miss[:, 0], miss[:, 1]) <= max_roundtrip_px)
    edge = ~full & (large >= min_texture) & (np.abs(np.sum(miss * across, axis=1)) <= max_roundtrip_px)
    ok = full | edge
    out[ok, 0] = source.pixels[ok, 0] + f[ok, 0] / sx
    out[ok, 1] = source.pixels[ok, 1] + f[ok, 1] / sy
    normal[edge] = across[edge]
    return out, normal


def patch_difference(
    source_gray: np.ndarray, target_gray: np.ndarray, pixels: np.ndarray, landings: np.ndarray
) -> np.ndarray:
    """Mean absolute difference (grey levels) between the source's window about each of ``pixels``
    (N, 2, int column and row) and the target's about each of ``landings`` (N, 2, float: sampled
    bilinearly), both ``STRUCTURE_WINDOW_PX`` wide: the window in which the texture was judged."""
    half = STRUCTURE_WINDOW_PX // 2
    offsets = np.arange(-half, half + 1)
    du, dv = (o.ravel() for o in np.meshgrid(offsets, offsets))
    h, w = source_gray.shape
    a = source_gray[
        np.clip(pixels[:, 1, None] + dv, 0, h - 1), np.clip(pixels[:, 0, None] + du, 0, w - 1)
    ].astype(np.float32)
    b = np.empty_like(a)
    for s in range(0, len(pixels), _REMAP_ROWS):  # cv2.remap's maps have fewer than 32767 rows
        b[s : s + _REMAP_ROWS] = cv2.remap(
            target_gray,
            (landings[s : s + _REMAP_ROWS, 0, None] + du).astype(np.float32),
            (landings[s : s + _REMAP_ROWS, 1, None] + dv).astype(np.float32),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
    return np.abs(a - b).mean(axis=1)


class Landings:
    """How unlike the source's texture the texture is where a motion lands each point, where the motion
    and the optical flow disagree; and how unlike it is at the flow's own matches (noise, shading)."""

    def __init__(self, source: Cloud, target: Cloud, flow_px: np.ndarray, *, beyond_px: float):
        self.gray = source.view.gray, target.view.gray
        self.pixels, self.beyond_px = source.pixels, beyond_px
        known = np.isfinite(flow_px).all(axis=1)
        own = patch_difference(*self.gray, self.pixels[known], flow_px[known])
        centre = float(np.median(own)) if len(own) else np.nan
        self.flow_grey = [centre, float(1.4826 * np.median(np.abs(own - centre))) if len(own) else np.nan]

    def __call__(self, misfit: np.ndarray, landing) -> np.ndarray:
        """(H, N) float32: the difference where ``misfit`` (H, N) exceeds ``beyond_px``, NaN elsewhere;
        ``landing(h, i)`` gives the target pixels (M, 2) where motions ``h`` put points ``i``."""
        h, i = np.nonzero(np.nan_to_num(misfit) > self.beyond_px)
        out = np.full(misfit.shape, np.nan, np.float32)
        out[h, i] = patch_difference(*self.gray, self.pixels[i], landing(h, i))
        return out
