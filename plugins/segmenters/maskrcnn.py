"""The ``maskrcnn`` segmenter: Mask R-CNN with the ONNX Model Zoo's MaskRCNN-10/12 signature.

The paper localises the object with Mask R-CNN (COCO weights, no fine-tuning) and keeps the instance
that is being manipulated. The zoo's files cannot be downloaded here, so a user who has one points
``model_path`` at it; its signature is checked when it is loaded:

* input ``image``: float32 [3, H, W] (no batch), BGR 0..255, resized so the short side is 800
  (the long side at most 1333), minus the BGR mean (102.9801, 115.9465, 122.7717), zero-padded at the
  bottom/right to multiples of 32;
* outputs ``6568`` float32 [nbox, 4] boxes (x0, y0, x1, y1) in resized pixels, ``6570`` int64 [nbox]
  COCO labels (1..80), ``6572`` float32 [nbox] scores, ``6887`` float32 [nbox, 1, 28, 28] masks.

Post-processing (the zoo's): boxes divided by the resize ratio; each 28 x 28 mask resized to its box
(x1 - x0 + 1, y1 - y0 + 1), thresholded at 0.5 and pasted with clipping at the image border.
Detections scoring at least ``score_threshold`` and passing the class filters are the instances;
the shared selection (:mod:`.selection`) picks the one being manipulated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from artclass_core import Frame, ParamError, PluginError, Sequence, param

from . import onnx_models
from .onnx_models import TensorSpec
from .selection import InstanceSegmenter, SelectionParams

__all__ = [
    "MaskrcnnParams",
    "MaskrcnnSegmenter",
    "COCO_CLASSES",
    "preprocess",
    "postprocess",
    "load_maskrcnn",
    "parse_classes",
]

MEAN_BGR = np.array([102.9801, 115.9465, 122.7717], np.float32)
SHORT_SIDE, LONG_SIDE_MAX, PAD = 800, 1333, 32
MASK_THRESHOLD = 0.5
INPUTS = [TensorSpec("image", "tensor(float)", 3, (3, None, None))]
OUTPUTS = [
    TensorSpec("6568", "tensor(float)", 2, (None, 4)),
    TensorSpec("6570", "tensor(int64)", 1),
    TensorSpec("6572", "tensor(float)", 1),
    TensorSpec("6887", "tensor(float)", 4, (None, 1, 28, 28)),
]
SIGNATURE = "ONNX Model Zoo MaskRCNN-10/12 (image -> 6568 boxes, 6570 labels, 6572 scores, 6887 masks)"

#: COCO class names by the zoo model's label id (1..80; 0 is the background).
COCO_CLASSES: tuple[str, ...] = (
    "__background__",
    "person",
    "bicycle",
    "car",
    "motorcycle",
    "airplane",
    "bus",
    "train",
    "truck",
    "boat",
    "traffic light",
    "fire hydrant",
    "stop sign",
    "parking meter",
    "bench",
    "bird",
    "cat",
    "dog",
    "horse",
    "sheep",
    "cow",
    "elephant",
    "bear",
    "zebra",
    "giraffe",
    "backpack",
    "umbrella",
    "handbag",
    "tie",
    "suitcase",
    "frisbee",
    "skis",
    "snowboard",
    "sports ball",
    "kite",
    "baseball bat",
    "baseball glove",
    "skateboard",
    "surfboard",
    "tennis racket",
    "bottle",
    "wine glass",
    "cup",
    "fork",
    "knife",
    "spoon",
    "bowl",
    "banana",
    "apple",
    "sandwich",
    "orange",
    "broccoli",
    "carrot",
    "hot dog",
    "pizza",
    "donut",
    "cake",
    "chair",
    "couch",
    "potted plant",
    "bed",
    "dining table",
    "toilet",
    "tv",
    "laptop",
    "mouse",
    "remote",
    "keyboard",
    "cell phone",
    "microwave",
    "oven",
    "toaster",
    "sink",
    "refrigerator",
    "book",
    "clock",
    "vase",
    "scissors",
    "teddy bear",
    "hair drier",
    "toothbrush",
)


def parse_classes(text: str, *, name: str) -> frozenset[int]:
    """COCO label ids from ``"laptop, cup, 77"`` (names or ids, comma-separated; empty = none).

    Raises :class:`ParamError` naming the parameter and the unknown entry.
    """
    ids = set()
    for item in (s.strip() for s in text.split(",")):
        if not item:
            continue
        if item.isdigit():
            k = int(item)
            if not 1 <= k < len(COCO_CLASSES):
                raise ParamError(
                    f"parameter {name}: COCO label id {k} is out of range 1..{len(COCO_CLASSES) - 1}"
                )
            ids.add(k)
        elif item.lower() in COCO_CLASSES[1:]:
            ids.add(COCO_CLASSES.index(item.lower()))
        else:
            raise ParamError(
                f"parameter {name}: {item!r} is not a COCO class name or id (e.g. laptop, cup, 64)"
            )
    return frozenset(ids)


@dataclass(frozen=True)
class MaskrcnnParams(SelectionParams):
    model_path: str = param(
        "",
        help="ONNX file of a Mask R-CNN with the ONNX Model Zoo MaskRCNN-10/12 signature "
        "(required; the zoo's files are not downloadable here).",
    )
    score_threshold: float = param(
        0.7,
        unit="probability",
        bounds=(0.0, 1.0),
        help="Detections scoring below this are ignored (the zoo example uses 0.7).",
    )
    classes: str = param(
        "",
        help="Only these COCO classes (comma-separated names or ids, e.g. 'laptop,cup'); "
        "empty = every class.",
    )
    exclude_classes: str = param(
        "person",
        help="Never these COCO classes: by default the person, whose hand and "
        "arm would otherwise be the manipulated instance.",
    )

    def __post_init__(self):
        super().__post_init__()
        parse_classes(self.classes, name="classes")
        parse_classes(self.exclude_classes, name="exclude_classes")


def preprocess(rgb: np.ndarray) -> tuple[np.ndarray, float]:
    """The zoo's input for an image.

    Parameters
    ----------
    rgb : ndarray, shape (H, W, 3), uint8, RGB order

    Returns
    -------
    image : ndarray, shape (3, H', W'), float32 -- BGR minus the mean, H' and W' multiples of 32
    ratio : float -- resized size / original size
    """
    h, w = rgb.shape[:2]
    ratio = SHORT_SIDE / min(h, w)
    if max(h, w) * ratio > LONG_SIDE_MAX:
        ratio = LONG_SIDE_MAX / max(h, w)
    size = (int(ratio * w), int(ratio * h))
    bgr = cv2.resize(rgb[:, :, ::-1], size, interpolation=cv2.INTER_LINEAR).astype(np.float32)
    chw = (bgr - MEAN_BGR).transpose(2, 0, 1)
    padded = np.zeros((3, math.ceil(size[1] / PAD) * PAD, math.ceil(size[0] / PAD) * PAD), np.float32)
    padded[:, : size[1], : size[0]] = chw
    return padded, ratio


def postprocess(
    boxes: np.ndarray,
    labels: np.ndarray,
    scores: np.ndarray,
    masks: np.ndarray,
    *,
    ratio: float,
    shape: tuple[int, int],
    score_threshold: float,
    keep_labels: frozenset[int] = frozenset(),
    drop_labels: frozenset[int] = frozenset(),
) -> list[tuple[np.ndarray, int, float]]:
    """Full-image masks of the detections (the zoo's post-processing).

    Parameters
    ----------
    boxes : ndarray, shape (nbox, 4), resized pixels (x0, y0, x1, y1)
    labels : ndarray, shape (nbox,), int -- COCO label ids
    scores : ndarray, shape (nbox,)
    masks : ndarray, shape (nbox, 1, 28, 28) -- mask probabilities within each box
    ratio : resize ratio of :func:`preprocess`
    shape : (H, W) of the original image
    score_threshold : keep detections scoring at least this
    keep_labels : if not empty, keep only these labels
    drop_labels : never keep these labels

    Returns
    -------
    list of (mask (H, W) bool, label, score), in the model's order, non-empty masks only
    """
    h, w = shape
    out = []
    for box, label, score, prob in zip(np.asarray(boxes, float) / ratio, labels, scores, masks):
        label = int(label)
        if score < score_threshold or (keep_labels and label not in keep_labels) or label in drop_labels:
            continue
        x0, y0, x1, y1 = (int(round(v, 3)) for v in box)  # the zoo's int(), robust to float error (49.9999)
        bw, bh = x1 - x0 + 1, y1 - y0 + 1
        if bw <= 0 or bh <= 0:
            continue
        patch = (
            cv2.resize(np.asarray(prob[0], np.float32), (bw, bh), interpolation=cv2.INTER_LINEAR)
            > MASK_THRESHOLD
        )
        full = np.zeros((h, w), bool)
        cx0, cy0, cx1, cy1 = max(x0, 0), max(y0, 0), min(x1 + 1, w), min(y1 + 1, h)
        if cx1 > cx0 and cy1 > cy0:
            full[cy0:cy1, cx0:cx1] = patch[cy0 - y0 : cy1 - y0, cx0 - x0 : cx1 - x0]
        if full.any():
            out.append((full, label, float(score)))
    return out


def load_maskrcnn(model_path: str):
    """The (cached) onnxruntime session of a zoo Mask R-CNN, its signature checked.

    Raises :class:`PluginError` when ``model_path`` is unset or missing, or the model's inputs and
    outputs differ from the zoo's (every difference is named).
    """
    if not model_path:
        raise PluginError(
            "the maskrcnn segmenter needs a model: set model_path to an ONNX Model Zoo "
            "MaskRCNN-10/12 file (e.g. --param model_path=/path/MaskRCNN-12.onnx)"
        )
    path = Path(model_path).expanduser()
    if not path.is_file():
        raise PluginError(
            "model_path: no such model file (an ONNX Model Zoo MaskRCNN-10/12 file is needed)", path=path
        )
    sess = onnx_models.session(str(path))
    onnx_models.check_signature(sess, inputs=INPUTS, outputs=OUTPUTS, what=SIGNATURE, path=path)
    return sess


class MaskrcnnSegmenter(InstanceSegmenter):
    """Mask R-CNN (COCO) detections above a score, the manipulated one chosen, as in the paper."""

    name = "maskrcnn"
    description = (
        "Mask R-CNN (ONNX Model Zoo MaskRCNN-10/12 file given by model_path), moving instance chosen"
    )
    Params = MaskrcnnParams

    def detections(self, frame: Frame) -> list[tuple[np.ndarray, int, float]]:
        """(mask, COCO label, score) of every detection kept by the score and class filters."""
        p = self.params
        sess = load_maskrcnn(p.model_path)
        image, ratio = preprocess(frame.rgb)
        boxes, labels, scores, masks = sess.run(["6568", "6570", "6572", "6887"], {"image": image})
        return postprocess(
            boxes,
            labels,
            scores,
            masks,
            ratio=ratio,
            shape=frame.rgb.shape[:2],
            score_threshold=p.score_threshold,
            keep_labels=parse_classes(p.classes, name="classes"),
            drop_labels=parse_classes(p.exclude_classes, name="exclude_classes"),
        )

    def instances(self, frame: Frame, *, sequence: Sequence) -> list[np.ndarray]:
        return [mask for mask, _, _ in self.detections(frame)]
