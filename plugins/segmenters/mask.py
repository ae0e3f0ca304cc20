"""The ``mask`` segmenter: the sequence's own masks (ground truth or precomputed)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from artclass_core import Frame, InputError, Params, Segmenter, Sequence, param


@dataclass(frozen=True)
class MaskParams(Params):
    erode_px: int = param(
        0,
        unit="px",
        bounds=(0, 20),
        help="Erode the mask by this many pixels to drop mixed depth at the object's edge.",
    )


class MaskSegmenter(Segmenter):
    """Uses the masks stored with the sequence; an empty mask skips the frame."""

    name = "mask"
    description = "the sequence's own object masks (ground truth or precomputed)"
    Params = MaskParams

    def segment(self, frame: Frame, *, sequence: Sequence) -> np.ndarray | None:
        if frame.mask is None:
            raise InputError(
                "the sequence has no masks; choose a segmenter such as depth_threshold", path=sequence.path
            )
        mask = frame.mask
        if self.params.erode_px:
            size = 2 * self.params.erode_px + 1
            mask = cv2.erode(mask.astype(np.uint8), np.ones((size, size), np.uint8)) > 0
        return mask if mask.any() else None
