"""The ``u2net`` segmenter: U^2-Net (u2netp) salient-object masks combined with depth.

Per frame: the u2netp foreground probability (class-agnostic; onnxruntime on the CPU), thresholded;
pixels that depth shows to be background (out of ``[near_m, far_m]``, on or behind a large plane: the
support plane, the floor beyond it, a wall; see :mod:`.support`) and hands (:mod:`.hands`) are
removed; the connected components of at least ``min_area_fraction`` of the image are the instances
(those that a hand passing in front of an object cuts apart joined again:
:func:`.depth_threshold.join_hidden`), and the shared selection (:mod:`.selection`) picks the one
being manipulated. Pixels without a depth reading inside a salient region are kept: they carry no
points, and dropping them would split objects along sensor shadows.

Pre/post-processing (the model's own): RGB resized to 320 x 320, / 255, ImageNet mean
(0.485, 0.456, 0.406) and std (0.229, 0.224, 0.225), NCHW float32 into ``input.1``; the output
``1959`` (1 x 1 x 320 x 320) is already a sigmoid probability, resized back to the frame and
thresholded as is (no min-max normalisation, which would turn an empty scene into a full mask).

Weights: ``artclass models fetch u2netp`` puts them in the model cache (:mod:`.onnx_models`);
``model_path`` points at another file with the same signature (e.g. the larger u2net.onnx).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from artclass_core import Frame, Sequence, param

from . import onnx_models
from .depth_threshold import MaskFreeSegmenter, components, join_hidden
from .hands import HandParams
from .onnx_models import TensorSpec
from .selection import SelectionParams
from .support import BackgroundParams

__all__ = ["U2netParams", "U2netSegmenter", "saliency", "load_u2net", "INPUT_SIZE"]

INPUT_SIZE = 320
MEAN = np.array([0.485, 0.456, 0.406], np.float32)
STD = np.array([0.229, 0.224, 0.225], np.float32)
INPUTS = [TensorSpec("input.1", "tensor(float)", 4, (1, 3, INPUT_SIZE, INPUT_SIZE))]
OUTPUTS = [TensorSpec("1959", "tensor(float)", 4, (1, 1, INPUT_SIZE, INPUT_SIZE))]


@dataclass(frozen=True)
class U2netParams(SelectionParams, BackgroundParams, HandParams):
    model_path: str = param(
        "",
        help="U^2-Net ONNX file; empty = the u2netp fetched into the model cache by "
        "`artclass models fetch u2netp`.",
    )
    threshold: float = param(
        0.5,
        unit="probability",
        bounds=(0.01, 0.99),
        help="Pixels whose foreground probability exceeds this are salient.",
    )
    min_area_fraction: float = param(
        0.002,
        unit="fraction",
        bounds=(0.0, 0.5),
        help="Salient regions smaller than this share of the image are not instances.",
    )


def load_u2net(model_path: str = ""):
    """The (cached) onnxruntime session of the U^2-Net model, its signature checked.

    Raises :class:`~artclass_core.PluginError` when the model is missing (naming the fetch command),
    fails its checksum, or does not have U^2-Net's signature.
    """
    path = onnx_models.resolve("u2netp", model_path)
    sess = onnx_models.session(str(path))
    onnx_models.check_signature(
        sess, inputs=INPUTS, outputs=OUTPUTS, what="U^2-Net (input.1 -> 1959)", path=path
    )
    return sess


def saliency(rgb: np.ndarray, *, session) -> np.ndarray:
    """U^2-Net foreground probability of an image.

    Parameters
    ----------
    rgb : ndarray, shape (H, W, 3), uint8, RGB order
    session : onnxruntime session of a U^2-Net model (see :func:`load_u2net`)

    Returns
    -------
    probability : ndarray, shape (H, W), float32 in [0, 1]
    """
    h, w = rgb.shape[:2]
    small = cv2.resize(rgb, (INPUT_SIZE, INPUT_SIZE), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
    x = ((small - MEAN) / STD).transpose(2, 0, 1)[None].astype(np.float32)
    prob = session.run(["1959"], {"input.1": x})[0][0, 0]
    return cv2.resize(prob, (w, h), interpolation=cv2.INTER_LINEAR)


class U2netSegmenter(MaskFreeSegmenter):
    """Salient objects (U^2-Net) that depth does not show to be background, chosen by how they move."""

    name = "u2net"
    description = "U^2-Net (u2netp) salient objects minus depth background and hands, moving instance chosen"
    Params = U2netParams

    def instances(self, frame: Frame, *, sequence: Sequence) -> list[np.ndarray]:
        p = self.params
        prob = saliency(frame.rgb, session=load_u2net(p.model_path))
        scene = self.scene(frame, sequence=sequence)
        objects = (prob > p.threshold) & ~scene.background
        allowed = self.not_hand(frame, sequence=sequence)
        found = components(
            objects if allowed is None else objects & allowed,
            open_px=0,
            min_area_fraction=p.min_area_fraction,
        )
        if allowed is None:
            return found
        hand = self.hand_mask(frame, sequence=sequence)
        return join_hidden(found, hand, scene.depth_m, sequence.intrinsics, touch_m=p.hand_touch_m)
