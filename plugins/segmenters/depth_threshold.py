"""The ``depth_threshold`` segmenter: what stands out of the scene's large planes, by depth alone.

Per frame: keep the depth readings inside ``[near_m, far_m]``; remove the large background planes
(the support plane, the points behind it such as the floor beyond a table's edge, and a second large
plane such as a wall; see :mod:`.support`); open the remaining mask by ``open_px``; its connected
components of at least ``min_area_fraction`` of the image are the instances, each with the
dropouts (pixels without a reading) that a closing of radius ``fill_px`` puts inside it; the shared
selection (:mod:`.selection`) picks the one being manipulated.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from artclass_core import Frame, Sequence, param

from .selection import InstanceSegmenter, SelectionParams
from .support import BackgroundParams, background_mask, fit_planes

__all__ = ["DepthThresholdParams", "DepthThresholdSegmenter", "components", "fill_dropouts"]


@dataclass(frozen=True)
class DepthThresholdParams(SelectionParams, BackgroundParams):
    open_px: int = param(0, unit="px", bounds=(0, 10),
                         help="Morphological opening radius: removes speckle and thin bridges (flying "
                              "pixels) between objects and the background.")
    min_area_fraction: float = param(0.002, unit="fraction", bounds=(0.0, 0.5),
                                     help="Connected regions smaller than this share of the image are not "
                                          "instances (about 600 px at 640x480).")
    fill_px: int = param(2, unit="px", bounds=(0, 20),
                         help="Pixels without a depth reading that a closing of this radius puts inside an "
                              "instance join it (sensor dropouts on the object; they carry no points).")


def fill_dropouts(instances: list[np.ndarray], valid: np.ndarray, *, fill_px: int) -> list[np.ndarray]:
    """Add to each instance the pixels without a depth reading that a closing of radius ``fill_px``
    puts inside it (holes and ragged edges from sensor dropouts). Instances are not modified."""
    if not fill_px:
        return instances
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * fill_px + 1, 2 * fill_px + 1))
    h, w = valid.shape
    out = []
    for mask in instances:
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        y0, y1 = max(rows[0] - fill_px, 0), min(rows[-1] + fill_px + 1, h)
        x0, x1 = max(cols[0] - fill_px, 0), min(cols[-1] + fill_px + 1, w)
        crop = np.pad(mask[y0:y1, x0:x1].astype(np.uint8), fill_px)
        closed = cv2.morphologyEx(crop, cv2.MORPH_CLOSE, kernel)[fill_px:-fill_px, fill_px:-fill_px] > 0
        filled = mask.copy()
        filled[y0:y1, x0:x1] |= closed & ~valid[y0:y1, x0:x1]
        out.append(filled)
    return out


def components(mask: np.ndarray, *, open_px: int, min_area_fraction: float) -> list[np.ndarray]:
    """The connected components (8-connected) of a mask after an opening, largest first.

    Parameters
    ----------
    mask : ndarray of bool, shape (H, W)
    open_px : radius of the square opening (0 = none)
    min_area_fraction : smallest component kept, as a share of H * W

    Returns
    -------
    list of ndarray of bool, shape (H, W)
    """
    m = np.asarray(mask, dtype=np.uint8)
    if open_px:
        kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * open_px + 1, 2 * open_px + 1))
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, kernel)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    min_area = max(1, int(np.ceil(min_area_fraction * m.size)))
    keep = [k for k in range(1, n) if stats[k, cv2.CC_STAT_AREA] >= min_area]
    keep.sort(key=lambda k: (-stats[k, cv2.CC_STAT_AREA], k))
    out = []
    for k in keep:
        x, y, w, h = stats[k, :4]
        full = np.zeros(m.shape, dtype=bool)
        full[y:y + h, x:x + w] = labels[y:y + h, x:x + w] == k
        out.append(full)
    return out


class DepthThresholdSegmenter(InstanceSegmenter):
    """Objects standing out of the support plane and background, chosen by how they move."""

    name = "depth_threshold"
    description = "depth range + background-plane removal + connected components, moving instance chosen"
    Params = DepthThresholdParams

    def candidates(self, frame: Frame, *, sequence: Sequence) -> tuple[np.ndarray, np.ndarray]:
        """Pixels with a depth reading that are not background, and pixels with a reading: bool (H, W)."""
        planes = fit_planes(frame.depth_m, sequence.intrinsics, params=self.params)
        background, valid = background_mask(frame.depth_m, sequence.intrinsics, planes, params=self.params)
        return valid & ~background, valid

    def instances(self, frame: Frame, *, sequence: Sequence) -> list[np.ndarray]:
        p = self.params
        foreground, valid = self.candidates(frame, sequence=sequence)
        found = components(foreground, open_px=p.open_px, min_area_fraction=p.min_area_fraction)
        return fill_dropouts(found, valid, fill_px=p.fill_px)
