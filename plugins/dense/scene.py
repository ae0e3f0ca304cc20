"""The sensor's systematic depth error about the object, measured on the still scene beside it.

A depth sensor errs by more than its noise where the scene near a surface changes: a time-of-flight
camera reads a surface farther when a hand comes near it (light the hand scatters lengthens the path:
multipath), and a structured-light camera's pattern shifts where an arm shadows it. Such an error
moves with the hand over many pixels, the object's and the scene's alike, and a motion fitted to it
(a still object sliding and tilting a little) explains the object's depth better than staying still.

On a still camera the scene beside the object shows the error: surfaces that the optical flow says did
not move, whose depth changed nonetheless between the two frames. Its robust size about each point
is the depth change there that the sensor alone makes: a motion that misses the point by less is not
refuted by it. A moving camera leaves little still scene: its texture flows.

The flow cannot follow a plain surface (a plain or faintly textured table), so a plain pixel counts
as still where the flow finds no motion, as a textured one does, unless a hand may cover it (the
segmenter's ``covered`` pixels): beside an object on a still camera, what moves towards the camera
unseen is a hand or an arm. A plain surface that slides along itself unseen keeps its depth, so it
understates the error, never overstates it.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from artclass_core import Cloud

from .flow import CropFlow

#: The error is summarised on square cells of this side, pixels.
CELL_PX = 8
#: The scene is read at every second pixel each way.
_STEP = 2


def still_scene_error(
    source: Cloud,
    target: Cloud,
    flow: CropFlow | None,
    reach: Callable[[np.ndarray], np.ndarray],
    *,
    still_px: float,
    spread_px: float,
) -> np.ndarray | None:
    """How much the depth of the still scene changed between the two frames about each point.

    Parameters
    ----------
    source, target : the pair's clouds, with their views (masks and whole frames' depth)
    flow : the pair's optical flow about the objects
    reach : the depth change (metres) beyond which a pixel shows another surface, come or gone, not
        the same one read differently, as a function of the depth
    still_px : a surface that the flow moves less than this, both ways, did not move (pixels)
    spread_px : the error is taken as smooth over this many pixels (a Gaussian's sigma)

    Returns
    -------
    The error about each point of ``source`` and then of ``target``, metres, shape (N_source +
    N_target,): the absolute median change of the still pixels of each cell, averaged over the
    cells about the point; where none is near, that of all cells. None when nothing was seen still.
    """
    a, b = source.view, target.view
    if flow is None or a.scene_depth_m is None or b.scene_depth_m is None:
        return None
    r0, r1, c0, c1 = flow.box
    (sx, sy), crop = flow.scale, (slice(r0, r1, _STEP), slice(c0, c1, _STEP))
    za, zb = a.scene_depth_m[crop], b.scene_depth_m[crop]
    size = za.shape[::-1]

    def moved(f: np.ndarray) -> np.ndarray:
        full = cv2.resize(f, size, interpolation=cv2.INTER_LINEAR)
        return np.hypot(full[..., 0] / sx, full[..., 1] / sy) >= still_px

    edge = 2 * int(source.info.get("edge_px", 1)) + 1
    near = cv2.dilate((a.mask | b.mask)[r0:r1, c0:c1].astype(np.uint8), np.ones((edge, edge), np.uint8))
    near = near[::_STEP, ::_STEP]
    change = zb - za
    scene = (near == 0) & (za > 0) & (zb > 0) & (np.abs(change) <= reach(np.maximum(za, zb)))
    for view in (a, b):
        if view.covered is not None:
            scene &= ~view.covered[crop]
    still = scene & ~moved(flow.forward) & ~moved(flow.backward)
    if not still.any():
        return None
    cell = CELL_PX // _STEP
    rows, cols = -(-size[1] // cell), -(-size[0] // cell)
    grid = np.full((rows * cell, cols * cell), np.nan, np.float32)
    grid[: size[1], : size[0]] = np.where(still, change, np.nan)
    cells = grid.reshape(rows, cell, cols, cell).transpose(0, 2, 1, 3).reshape(rows, cols, -1)
    seen = np.isfinite(cells).sum(axis=2) >= cell**2 // 4
    if not seen.any():
        return None
    error = np.zeros((rows, cols), np.float32)
    error[seen] = np.abs(_median(cells[seen]))
    sigma = spread_px / CELL_PX
    weight = cv2.GaussianBlur(seen.astype(np.float32), (0, 0), sigma)
    spread = cv2.GaussianBlur(error, (0, 0), sigma) / np.maximum(weight, 1e-6)
    spread = np.where(weight > 1e-3, spread, np.median(error[seen]))
    pixels = np.vstack([source.pixels, target.pixels])
    v = np.clip((pixels[:, 1] - r0) // CELL_PX, 0, rows - 1)
    u = np.clip((pixels[:, 0] - c0) // CELL_PX, 0, cols - 1)
    return spread[v, u]


def _median(rows: np.ndarray) -> np.ndarray:
    """The median of each row of ``rows`` (M, K) over its finite values (at least one a row)."""
    ordered = np.sort(rows, axis=1)  # NaN last
    n = np.isfinite(rows).sum(axis=1)
    at = np.arange(len(rows))
    return (ordered[at, (n - 1) // 2] + ordered[at, n // 2]) / 2
