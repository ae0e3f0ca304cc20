"""A learned hand detector: where the hands in a colour image are, with 21 landmarks and a mask each.

It runs MediaPipe Hands' two models on the CPU, as MediaPipe's own CPU graph does, without MediaPipe:

1. the palm detector looks at the whole image, letterboxed to 192 x 192, and finds palms (a box and
   seven keypoints each, scored);
2. each palm becomes a square region around the whole hand, turned so that the fingers point up;
3. the hand landmark model looks at that region, resized to 224 x 224, and gives 21 landmarks
   (wrist, then four joints per finger from thumb to little finger), a hand-presence score and the
   same landmarks in metres (an estimate of the hand's real size);
4. the hand mask is the filled convex hull of the landmarks, grown by ``margin_m`` metres (the
   fingers' width; converted to pixels by the size of the palm in the image, taken to be an adult's).
   It covers the hand up to the wrist, not the arm.

Use::

    detector = HandDetector(HandDetectorParams(threads=1))
    for hand in detector.detect(rgb):  # rgb: (H, W, 3) uint8
        hand.score, hand.box_px, hand.landmarks_px, hand.mask

The result depends only on the image: there is no random state and no tracking between calls.

Models: ``artclass models fetch palm_detection hand_landmark`` (``make setup`` runs it) puts
palm_detection_full.tflite and hand_landmark_full.tflite (Apache 2.0) into the model cache; they are
taken from the mediapipe wheel on PyPI and run with ai-edge-litert. Nothing is downloaded at run time.

Notes
-----
The pre- and post-processing follow MediaPipe's graphs (mediapipe/modules/palm_detection and
mediapipe/modules/hand_landmark, v0.10.21): SSD anchors, box decoding, weighted non-maximum
suppression, the palm-to-hand region (scale 2.6, shifted half a palm towards the fingers) and the
landmark projection. On photographs the landmarks agree with ``mediapipe.solutions.hands`` to about a
pixel. Hands smaller than about 20 pixels across are missed.

V. Bazarevsky, F. Zhang et al., "MediaPipe Hands: On-device Real-time Hand Tracking", CVPR Workshop
on Computer Vision for AR/VR, 2020.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from artclass_core import InputError, Params, PluginError, param

from . import onnx_models

__all__ = ["Hand", "HandDetector", "HandDetectorParams", "hands_mask", "LANDMARK_NAMES"]

LANDMARK_NAMES = (
    "wrist",
    *("thumb_cmc", "thumb_mcp", "thumb_ip", "thumb_tip"),
    *(
        f"{finger}_{joint}"
        for finger in ("index", "middle", "ring", "little")
        for joint in ("mcp", "pip", "dip", "tip")
    ),
)
PALM_SIZE = 192  # palm detector input, pixels
LANDMARK_SIZE = 224  # landmark model input, pixels
# From palm to hand region (palm_detection_detection_to_roi.pbtxt): 2.6 times the palm box, moved
# half a box towards the fingers.
ROI_SCALE = 2.6
ROI_SHIFT = -0.5
NMS_IOU = 0.3
# Lengths of the rigid palm segments of an adult's hand, metres (wrist to the index, middle and
# little finger's knuckle; index to little knuckle): they set the hand's scale in pixels per metre.
PALM_SEGMENTS_M = {(0, 5): 0.090, (0, 9): 0.095, (0, 17): 0.085, (5, 17): 0.065}


@dataclass(frozen=True)
class HandDetectorParams(Params):
    min_palm_score: float = param(
        0.5, unit="probability", bounds=(0.01, 0.99), help="A palm scoring less is not looked at."
    )
    min_presence: float = param(
        0.5,
        unit="probability",
        bounds=(0.01, 0.99),
        help="A hand region whose hand-presence score is lower is not a hand.",
    )
    max_hands: int = param(2, unit="1", bounds=(1, 10), help="At most this many hands, the best palms first.")
    margin_m: float = param(
        0.015,
        unit="m",
        bounds=(0.0, 0.1),
        help="The hand mask reaches this far beyond the landmarks' convex hull (half a finger's width "
        "and some).",
    )
    threads: int = param(1, unit="1", bounds=(1, 16), help="CPU threads each model may use.")
    palm_model_path: str = param(
        "",
        help="Palm detector .tflite; empty = palm_detection_full.tflite from the model cache "
        "(`artclass models fetch palm_detection`).",
    )
    landmark_model_path: str = param(
        "",
        help="Hand landmark .tflite; empty = hand_landmark_full.tflite from the model cache "
        "(`artclass models fetch hand_landmark`).",
    )


@dataclass(frozen=True, eq=False)
class Hand:
    """One hand found in an image.

    Attributes
    ----------
    score : float, probability
        palm score times hand-presence score.
    palm_score, presence : float, probability
        the palm detector's score and the landmark model's hand-presence score.
    box_px : ndarray, shape (4,), pixels
        ``x0, y0, x1, y1``: the image area the landmark model looked at (the turned square around the
        palm, its axis-aligned bounds, clipped to the image).
    landmarks_px : ndarray, shape (21, 3)
        x, y in pixels (column, row of the image) and z, depth relative to the wrist in pixels of
        the same scale (smaller is nearer the camera), in the order of :data:`LANDMARK_NAMES`.
    landmarks_m : ndarray, shape (21, 3), metres
        the landmarks in the hand's own metric frame (origin near the hand's centre): its shape and
        size, not its place in the scene.
    mask : ndarray, shape (H, W), bool
        the hand's pixels: the landmarks' filled convex hull grown by ``margin_m``.
    """

    score: float
    palm_score: float
    presence: float
    box_px: np.ndarray
    landmarks_px: np.ndarray
    landmarks_m: np.ndarray
    mask: np.ndarray


class HandDetector:
    """Find hands in RGB images with MediaPipe's palm detector and hand landmark model.

    Raises :class:`~artclass_core.PluginError` naming the file when a model is missing (and the
    command that fetches it), fails its checksum or is not the expected model, or when ai-edge-litert
    is not installed.
    """

    def __init__(self, params: HandDetectorParams | None = None):
        self.params = params or HandDetectorParams()
        p = self.params
        self._palm = _Model("palm_detection", p.palm_model_path, PALM_SIZE, n_outputs=2, threads=p.threads)
        self._landmark = _Model(
            "hand_landmark", p.landmark_model_path, LANDMARK_SIZE, n_outputs=4, threads=p.threads
        )

    def detect(self, rgb: np.ndarray) -> list[Hand]:
        """The hands in ``rgb``, best first.

        Parameters
        ----------
        rgb : ndarray, shape (H, W, 3), uint8
            a colour image, RGB channel order.

        Returns
        -------
        list of :class:`Hand`, at most ``max_hands``, by decreasing ``score``.
        """
        rgb = _check_image(rgb)
        p = self.params
        height, width = rgb.shape[:2]
        tensor, pad = _letterbox(rgb, PALM_SIZE)
        raw_boxes, raw_scores = self._palm(tensor)
        palms = _decode_palms(raw_boxes, raw_scores, min_score=p.min_palm_score)
        hands = []
        for box, keypoints, palm_score in _weighted_nms(*palms)[: p.max_hands]:
            box, keypoints = _remove_letterbox(box, keypoints, pad, width, height)
            roi = _palm_to_roi(box, keypoints)
            raw_landmarks, presence, _handedness, world = self._landmark(_crop(rgb, roi, LANDMARK_SIZE))
            presence = float(presence.ravel()[0])
            if presence < p.min_presence:
                continue
            landmarks = _project(raw_landmarks.reshape(21, 3), roi, LANDMARK_SIZE)
            landmarks_m = world.reshape(21, 3).astype(np.float64)
            hands.append(
                Hand(
                    score=palm_score * presence,
                    palm_score=palm_score,
                    presence=presence,
                    box_px=_roi_box(roi, width, height),
                    landmarks_px=landmarks,
                    landmarks_m=landmarks_m,
                    mask=_hull_mask(landmarks, (height, width), margin_m=p.margin_m),
                )
            )
        return sorted(hands, key=lambda h: -h.score)


def hands_mask(hands: list[Hand], shape: tuple[int, int]) -> np.ndarray:
    """The union of the hands' masks, shape ``shape`` (H, W), bool (all False without hands)."""
    mask = np.zeros(shape, bool)
    for hand in hands:
        mask |= hand.mask
    return mask


# -- the models ------------------------------------------------------------------------------------


class _Model:
    """One TensorFlow Lite model under ai-edge-litert: NHWC float32 in [0, 1] in, outputs in order."""

    def __init__(self, name: str, model_path: str, size: int, *, n_outputs: int, threads: int):
        path = onnx_models.resolve(name, model_path)
        try:
            from ai_edge_litert.interpreter import Interpreter
        except ImportError:
            raise PluginError(
                "the hand detector needs ai-edge-litert (pip install ai-edge-litert==2.3.0)", path=path
            ) from None
        try:
            self._interpreter = Interpreter(model_path=str(path), num_threads=threads)
            self._interpreter.allocate_tensors()
        except (ValueError, RuntimeError) as exc:
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            raise PluginError(
                f"not a TensorFlow Lite model ai-edge-litert can load: {first}", path=path
            ) from None
        inputs = self._interpreter.get_input_details()
        # tflite names outputs Identity, Identity_1, ...: sort them into that order
        outputs = sorted(self._interpreter.get_output_details(), key=lambda d: (len(d["name"]), d["name"]))
        if [list(d["shape"]) for d in inputs] != [[1, size, size, 3]] or len(outputs) != n_outputs:
            raise PluginError(
                f"not the {name} model: expected one input of shape [1, {size}, {size}, 3] and "
                f"{n_outputs} outputs, found inputs {[list(map(int, d['shape'])) for d in inputs]} and "
                f"{len(outputs)} outputs",
                path=path,
            )
        self._input = inputs[0]["index"]
        self._outputs = [d["index"] for d in outputs]

    def __call__(self, tensor: np.ndarray) -> list[np.ndarray]:
        self._interpreter.set_tensor(self._input, np.ascontiguousarray(tensor, np.float32))
        self._interpreter.invoke()
        return [self._interpreter.get_tensor(i).copy() for i in self._outputs]


def _check_image(rgb) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8 or min(rgb.shape[:2]) < 1:
        raise InputError(
            f"the hand detector needs an (H, W, 3) uint8 RGB image, got shape {rgb.shape} {rgb.dtype}"
        )
    return rgb


# -- palm detection --------------------------------------------------------------------------------


def _ssd_anchors(size: int = PALM_SIZE, strides: tuple[int, ...] = (8, 16, 16, 16)) -> np.ndarray:
    """Anchor centres, shape (2016, 2), in [0, 1]: two per cell and layer, layers of equal stride
    merged (SsdAnchorsCalculator with fixed_anchor_size, aspect ratio 1, interpolated scale)."""
    centres = []
    for stride in sorted(set(strides)):
        per_cell = 2 * strides.count(stride)
        cells = math.ceil(size / stride)
        grid = (np.arange(cells) + 0.5) / cells
        xs, ys = np.meshgrid(grid, grid)
        centres.append(np.repeat(np.stack([xs.ravel(), ys.ravel()], 1), per_cell, axis=0))
    return np.concatenate(centres).astype(np.float32)


ANCHORS = _ssd_anchors()


def _letterbox(rgb: np.ndarray, size: int) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """The image scaled into a size x size square, centred, black borders; (1, size, size, 3) in
    [0, 1], and the borders (left, top, right, bottom) as fractions of the square."""
    height, width = rgb.shape[:2]
    scale = size / max(height, width)
    new_w, new_h = max(1, round(width * scale)), max(1, round(height * scale))
    resized = cv2.resize(rgb, (new_w, new_h), interpolation=cv2.INTER_LINEAR)
    out = np.zeros((size, size, 3), np.float32)
    left, top = (size - new_w) // 2, (size - new_h) // 2
    out[top : top + new_h, left : left + new_w] = resized / np.float32(255)
    pad = (left / size, top / size, (size - new_w - left) / size, (size - new_h - top) / size)
    return out[None], pad


def _decode_palms(raw_boxes: np.ndarray, raw_scores: np.ndarray, *, min_score: float):
    """Boxes (N, 4) x0, y0, x1, y1 and keypoints (N, 7, 2) in [0, 1] of the letterboxed square, and
    scores (N,), of the anchors scoring at least ``min_score``."""
    scores = 1.0 / (1.0 + np.exp(-np.clip(raw_scores[0, :, 0].astype(np.float64), -100, 100)))
    keep = np.flatnonzero(scores >= min_score)
    raw = raw_boxes[0, keep].astype(np.float64) / PALM_SIZE
    anchors = ANCHORS[keep].astype(np.float64)
    centre = raw[:, 0:2] + anchors
    half = raw[:, 2:4] / 2
    boxes = np.concatenate([centre - half, centre + half], 1)
    keypoints = raw[:, 4:18].reshape(-1, 7, 2) + anchors[:, None, :]
    return boxes, keypoints, scores[keep]


def _weighted_nms(boxes: np.ndarray, keypoints: np.ndarray, scores: np.ndarray):
    """Weighted non-maximum suppression: each group of boxes overlapping the best remaining one by
    more than ``NMS_IOU`` becomes one palm, their score-weighted mean. [(box, keypoints, score)]."""
    palms = []
    remaining = np.argsort(-scores, kind="stable")
    while remaining.size:
        best = boxes[remaining[0]]
        others = boxes[remaining]
        inter_w = np.clip(np.minimum(best[2], others[:, 2]) - np.maximum(best[0], others[:, 0]), 0, None)
        inter_h = np.clip(np.minimum(best[3], others[:, 3]) - np.maximum(best[1], others[:, 1]), 0, None)
        inter = inter_w * inter_h
        area = (others[:, 2] - others[:, 0]) * (others[:, 3] - others[:, 1])
        iou = inter / np.maximum(area[0] + area - inter, 1e-12)
        group = remaining[iou > NMS_IOU]
        weights = scores[group] / scores[group].sum()
        palms.append(
            (
                weights @ boxes[group],
                np.einsum("n,nkd->kd", weights, keypoints[group]),
                float(scores[remaining[0]]),
            )
        )
        remaining = remaining[iou <= NMS_IOU]
    return palms


def _remove_letterbox(box, keypoints, pad, width: int, height: int):
    """Box and keypoints from the letterboxed square to image pixels."""
    left, top, right, bottom = pad
    scale = np.array([width / (1 - left - right), height / (1 - top - bottom)])
    offset = np.array([left, top])
    box_px = np.concatenate([(box[:2] - offset) * scale, (box[2:] - offset) * scale])
    return box_px, (keypoints - offset) * scale


# -- from palm to landmarks ------------------------------------------------------------------------


def _palm_to_roi(box_px: np.ndarray, keypoints_px: np.ndarray) -> tuple[float, float, float, float]:
    """The hand region of a palm: centre x, y, side in pixels and rotation in radians (the angle
    that turns the wrist -> middle-finger knuckle direction to point up)."""
    wrist, middle = keypoints_px[0], keypoints_px[2]
    rotation = math.pi / 2 - math.atan2(-(middle[1] - wrist[1]), middle[0] - wrist[0])
    rotation = rotation - 2 * math.pi * math.floor((rotation + math.pi) / (2 * math.pi))
    width, height = box_px[2] - box_px[0], box_px[3] - box_px[1]
    cx, cy = (box_px[0] + box_px[2]) / 2, (box_px[1] + box_px[3]) / 2
    cx -= height * ROI_SHIFT * math.sin(rotation)
    cy += height * ROI_SHIFT * math.cos(rotation)
    return cx, cy, max(width, height) * ROI_SCALE, rotation


def _roi_to_image(roi, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (u, v) of the region, each in [-0.5, 0.5], to image pixels."""
    cx, cy, side, rotation = roi
    c, s = math.cos(rotation), math.sin(rotation)
    return cx + (c * u - s * v) * side, cy + (s * u + c * v) * side


def _crop(rgb: np.ndarray, roi, size: int) -> np.ndarray:
    """The turned square region, resampled to (1, size, size, 3) in [0, 1]; edges repeated outside."""
    xs, ys = _roi_to_image(roi, np.array([-0.5, 0.5, -0.5]), np.array([-0.5, -0.5, 0.5]))
    src = np.stack([xs, ys], 1).astype(np.float32)
    dst = np.float32([[0, 0], [size, 0], [0, size]])
    crop = cv2.warpAffine(
        rgb,
        cv2.getAffineTransform(src, dst),
        (size, size),
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return (crop / np.float32(255))[None]


def _project(raw: np.ndarray, roi, size: int) -> np.ndarray:
    """Landmarks (21, 3) from region pixels to image pixels (z scaled like x and y, times 0.4 as
    MediaPipe normalises it)."""
    x, y = _roi_to_image(roi, raw[:, 0] / size - 0.5, raw[:, 1] / size - 0.5)
    z = raw[:, 2] / size * roi[2] * 0.4
    return np.stack([x, y, z], 1).astype(np.float64)


def _roi_box(roi, width: int, height: int) -> np.ndarray:
    xs, ys = _roi_to_image(roi, np.array([-0.5, 0.5, 0.5, -0.5]), np.array([-0.5, -0.5, 0.5, 0.5]))
    return np.array(
        [max(xs.min(), 0.0), max(ys.min(), 0.0), min(xs.max(), float(width)), min(ys.max(), float(height))]
    )


# -- the mask --------------------------------------------------------------------------------------


def _pixels_per_metre(landmarks_px: np.ndarray) -> float:
    """The hand's scale from an adult's palm: the largest ratio of a palm segment's length in the
    image to its typical length (a segment seen at an angle only looks shorter)."""
    return max(
        float(np.linalg.norm(landmarks_px[i, :2] - landmarks_px[j, :2])) / length_m
        for (i, j), length_m in PALM_SEGMENTS_M.items()
    )


def _hull_mask(landmarks_px, shape: tuple[int, int], *, margin_m: float) -> np.ndarray:
    """The landmarks' filled convex hull, grown by ``margin_m`` metres, as an (H, W) bool mask."""
    mask = np.zeros(shape, np.uint8)
    hull = cv2.convexHull(np.round(landmarks_px[:, :2]).astype(np.int32))
    cv2.fillConvexPoly(mask, hull, 1)
    radius = round(margin_m * _pixels_per_metre(landmarks_px))
    if radius > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
        mask = cv2.dilate(mask, kernel)
    return mask.astype(bool)
