"""Choosing the manipulated instance, shared by every segmenter that finds several instances per frame.

The paper: "we identify the mask instance, between two consecutive frames, that is being
manipulated". :func:`choose_instance` is that choice as a pure function:

1. The instances of frame i are matched to those of a neighbouring frame (i + n, or i - n near the
   end) greedily by mask IoU.
2. Each instance gets a *change score*: the share of the *stable* pixels of the union of its mask
   and its match whose depth changed by more than tau between the two frames. Stable pixels have a
   reading in both frames and are not at a depth edge in either (the depth range of their 3x3
   neighbourhood is below ``change_m``): the pixels that flicker between object and background at
   an edge are left out, so a still object seen by a drifting camera scores about 0, while a moved
   object changes the depth over the area it swept. tau = max(``change_m``, 4 sigma), sigma being
   the robust spread (1.4826 * median |depth change|) of all stable pixels of the image: the
   sensor's noise at the scene's distances. An instance seen in one frame only is scored over its
   own mask: high when the object left, about 0 for a segmentation flicker, which cannot win.
3. Instances scoring more than ``min_change`` are moving. The highest-scoring one is chosen, except
   that a moving instance overlapping the previous frame's choice (IoU >= ``keep_iou``) is
   preferred, so the choice stays on one object while several things move (a hand-held camera).
4. When nothing moves (a static scene), the instance overlapping the previous choice most is kept
   (IoU >= ``keep_iou``); failing that the **fallback** is the instance with the largest
   ``area * (1 - r / R)``, where r is the distance of its centroid from the image centre and R the
   half-diagonal: the largest instance, weighted towards the image centre.

With a hand mask (segmenters that look for hands, see :mod:`.hands`), the hand's pixels in either
frame are left out of the change score (a hand passing in front of a still object does not make it
move), and when the hand holds some of the moving instances, step 3 chooses among those only (an
arm that moves with the object it carries is not chosen over it); when nothing moves and the hand
holds some instances, step 4 chooses among those only (the object in the hand before it moves).

Before the choice, an instance that holds a body which the frames within reach show apart from it,
staying where it is while the rest leaves (a mug lifted off its stand), is split in two
(:mod:`.apart`): two bodies that touch and then separate are two objects.

"The previous choice" is the last choice made by rule 3 or by the fallback: a choice kept by rule 4
does not replace it, so when a still object's segment merges with a neighbour's for a frame (two
boxes touching in the image) the choice does not drift to the neighbour afterwards.

Two other scores were tried and dropped, on the synthetic sequences and the YCB-Video excerpts
(static objects, the camera drifting 0.5 mm per frame): the changed share over all pixels plus
1 - IoU (edge flicker alone gave still objects 0.05-0.38, overlapping the 0.1-0.5 of carried
objects), and the displacement of each instance's median 3-D point (segments that merge or split
between frames gave still objects 3-160 mm). The default comparison is with frame i + 3, not
i + 1: the synthetic objects are carried at 3-5 mm per frame, about one pixel of lateral motion,
which no edge-robust score separates from noise; over 3 frames carried objects score 0.15-0.8 and
still ones at most 0.05.

:class:`InstanceSegmenter` implements ``segment`` once on top of a subclass's ``instances``: each
frame's instances are computed once and kept (bit-packed) per sequence, the choices are made in
frame order (the choice of frame i depends on that of frame i - 1, so the masks are the same
whatever order the frames are asked in), and chosen masks are cached in memory and, with
``cache_dir``, as PNG files outside the input folder.
"""

from __future__ import annotations

import dataclasses
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from artclass_core import Frame, Params, Segmenter, Sequence, param

from ._compiled import steady_kernel
from .apart import REACH_FRAMES, BodiesApart, FrameView, frame_view, reach
from .cache import DiskMaskCache, PackedMask
from .hands import HOLD_LINE_M, HandParams, held, widen
from .support import as_numpy_compares, clean_depth

__all__ = [
    "Choice",
    "SelectionParams",
    "InstanceSegmenter",
    "mask_iou",
    "match_instances",
    "change_scores",
    "steady_pixels",
    "depth_edges",
    "fallback_index",
    "choose_instance",
]


@dataclass(frozen=True)
class SelectionParams(Params):
    """How the manipulated instance is chosen, and where masks are cached."""

    neighbour_frames: int = param(
        3,
        unit="frames",
        bounds=(1, 100),
        help="Frame i's instances are compared with those of frame i + n (i - n "
        "near the end) to find the one being manipulated.",
    )
    change_m: float = param(
        0.01,
        unit="m",
        bounds=(0.0005, 1.0),
        help="Smallest depth change (metres) that counts as a change; raised to 4 times "
        "the measured depth noise when that is larger. Also the depth-edge step.",
    )
    min_change: float = param(
        0.1,
        unit="fraction",
        bounds=(0.0, 1.0),
        help="An instance whose share of changed stable pixels exceeds this is moving; "
        "when none does, the scene counts as static.",
    )
    keep_iou: float = param(
        0.3,
        unit="fraction",
        bounds=(0.0, 1.0),
        help="An instance overlapping the previous frame's choice by at least this IoU "
        "is preferred, keeping the choice on one object.",
    )
    cache_dir: str = param(
        "", help="Folder for a PNG cache of the masks, outside the input folder; empty = memory only."
    )


@dataclass(frozen=True)
class Choice:
    """Which instance was chosen in a frame, and why (JSON-ready via ``to_dict``)."""

    index: int | None  # into the frame's instances; None when there is none
    rule: str  # "moving", "moving, kept", "still, kept", "still, fallback", "none"
    scores: tuple[float, ...] = ()  # change score of each instance
    tau_m: float | None = None  # depth change threshold used
    matches: tuple[int | None, ...] = ()  # matched instance in the neighbouring frame
    neighbour: int | None = None  # the neighbouring frame's index
    held: tuple[bool, ...] = ()  # which instances a hand holds (empty: no hand mask)

    def to_dict(self) -> dict[str, Any]:
        return dict(
            index=self.index,
            rule=self.rule,
            scores=[round(s, 4) for s in self.scores],
            tau_m=self.tau_m,
            matches=list(self.matches),
            neighbour=self.neighbour,
            held=list(self.held),
        )


def _box(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    x, y, w, h = cv2.boundingRect(np.ascontiguousarray(mask, dtype=bool).view(np.uint8))
    return (y, x, y + h, x + w) if w else None


def _iou_boxed(a, box_a, b, box_b) -> float:
    if box_a is None or box_b is None:
        return 0.0
    y0, x0 = max(box_a[0], box_b[0]), max(box_a[1], box_b[1])
    y1, x1 = min(box_a[2], box_b[2]), min(box_a[3], box_b[3])
    if y1 <= y0 or x1 <= x0:
        return 0.0
    inter = np.count_nonzero(a[y0:y1, x0:x1] & b[y0:y1, x0:x1])
    union = np.count_nonzero(a) + np.count_nonzero(b) - inter
    return inter / union if union else 0.0


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks of the same shape (0 when both are empty)."""
    return _iou_boxed(a, _box(a), b, _box(b))


def match_instances(instances: list[np.ndarray], others: list[np.ndarray]) -> list[tuple[int | None, float]]:
    """Greedy one-to-one matching by IoU (highest first; only overlapping pairs match).

    Returns
    -------
    For each of ``instances``: (index into ``others`` or None, IoU of the match or 0).
    """
    boxes_a, boxes_b = [_box(m) for m in instances], [_box(m) for m in others]
    pairs = [
        (_iou_boxed(a, ba, b, bb), i, j)
        for i, (a, ba) in enumerate(zip(instances, boxes_a))
        for j, (b, bb) in enumerate(zip(others, boxes_b))
    ]
    out: list[tuple[int | None, float]] = [(None, 0.0)] * len(instances)
    used_a, used_b = set(), set()
    for iou, i, j in sorted(pairs, key=lambda p: (-p[0], p[1], p[2])):
        if iou <= 0:
            break
        if i in used_a or j in used_b:
            continue
        used_a.add(i)
        used_b.add(j)
        out[i] = (j, iou)
    return out


def depth_edges(depth_m: np.ndarray, step_m: float) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood spans more than ``step_m`` of depth, or touches a missing reading."""
    # max - min over 3x3 (a missing reading is 0, so every pixel next to one is an edge)
    return cv2.morphologyEx(depth_m, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > step_m


def steady_pixels(depth_m: np.ndarray, *, change_m: float) -> np.ndarray:
    """The pixels of a depth image with a reading, away from depth edges (their 3x3 neighbourhood
    spans at most ``change_m`` of depth and has no missing reading): bool (H, W)."""
    d = clean_depth(depth_m)
    out = np.empty(d.shape, bool)
    # (d > 0) & ~depth_edges(d, change_m) in one compiled pass
    steady_kernel(np.ascontiguousarray(d), as_numpy_compares(d, change_m), out)
    return out


def change_scores(
    instances: list[np.ndarray],
    depth_m: np.ndarray,
    others: list[np.ndarray],
    other_depth_m: np.ndarray,
    *,
    change_m: float,
    ignore: np.ndarray | None = None,
    steady: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[list[float], list[tuple[int | None, float]], float]:
    """How much each instance changes between this frame and the neighbouring one.

    Parameters
    ----------
    instances : list of ndarray of bool, shape (H, W) -- this frame's instances
    depth_m : ndarray, shape (H, W), metres, 0 = no reading -- this frame's depth
    others, other_depth_m : the same for the neighbouring frame
    change_m : smallest depth change that counts (metres), and the depth-edge step
    ignore : ndarray of bool, shape (H, W), optional -- pixels left out (a hand in either frame)
    steady : (ndarray of bool, shape (H, W)) x 2, optional -- :func:`steady_pixels` of this and the
        neighbouring frame, when already computed

    Returns
    -------
    scores : list of float in [0, 1], one per instance
        share of the stable pixels of the union of the instance and its match (its own mask when
        unmatched) whose depth changed by more than tau
    matches : list of (index into ``others`` or None, IoU), from :func:`match_instances`
    tau_m : the change threshold used, max(change_m, 4 * robust sigma of the stable pixels' change)
    """
    matches = match_instances(instances, others)
    d, od = clean_depth(depth_m), clean_depth(other_depth_m)
    if steady is None:
        steady = steady_pixels(d, change_m=change_m), steady_pixels(od, change_m=change_m)
    stable = steady[0] & steady[1]
    if ignore is not None:
        stable &= ~ignore
    quarter = np.s_[::2, ::2]  # a quarter of the pixels is plenty for a median
    sample = np.abs(d[quarter] - od[quarter])[stable[quarter]]
    sigma = 1.4826 * float(np.median(sample)) if sample.size else 0.0
    tau = max(change_m, 4.0 * sigma)
    scores = []
    for mask, (j, _) in zip(instances, matches):
        boxes = [b for b in (_box(mask), None if j is None else _box(others[j])) if b is not None]
        if not boxes:
            scores.append(0.0)
            continue
        y0, x0 = min(b[0] for b in boxes), min(b[1] for b in boxes)
        y1, x1 = max(b[2] for b in boxes), max(b[3] for b in boxes)
        region = mask[y0:y1, x0:x1] if j is None else mask[y0:y1, x0:x1] | others[j][y0:y1, x0:x1]
        region = region & stable[y0:y1, x0:x1]  # a new array: the instances are not modified
        n = np.count_nonzero(region)
        changed = np.abs(d[y0:y1, x0:x1] - od[y0:y1, x0:x1]) > tau
        scores.append(np.count_nonzero(region & changed) / n if n else 0.0)
    return scores, matches, tau


def fallback_index(instances: list[np.ndarray]) -> int | None:
    """The static-scene choice: the largest ``area * (1 - r / R)`` (r: centroid to image centre,
    R: half-diagonal), ties to the lower index. None when there are no instances."""
    best, best_value = None, -1.0
    for k, mask in enumerate(instances):
        h, w = mask.shape
        v, u = np.nonzero(mask)
        if len(v) == 0:
            continue
        r = np.hypot(u.mean() - (w - 1) / 2, v.mean() - (h - 1) / 2)
        value = len(v) * (1.0 - r / np.hypot(w / 2, h / 2))
        if value > best_value:
            best, best_value = k, value
    return best


def choose_instance(
    instances: list[np.ndarray],
    depth_m: np.ndarray,
    others: list[np.ndarray] | None,
    other_depth_m: np.ndarray | None,
    *,
    previous: np.ndarray | None = None,
    change_m: float,
    min_change: float,
    keep_iou: float,
    ignore: np.ndarray | None = None,
    held: list[bool] | None = None,
    steady: tuple[np.ndarray, np.ndarray] | None = None,
) -> Choice:
    """Choose the manipulated instance of a frame (see the module docstring for the rule).

    Parameters
    ----------
    instances : list of ndarray of bool, shape (H, W) -- this frame's instances
    depth_m : ndarray, shape (H, W), metres -- this frame's depth
    others, other_depth_m : the neighbouring frame's instances and depth, or None when there is no
        neighbouring frame (the scene is then treated as static)
    previous : ndarray of bool, shape (H, W), optional -- the mask chosen in the previous frame
    change_m : smallest depth change that counts (metres)
    min_change : change score above which an instance is moving
    keep_iou : IoU with ``previous`` from which an instance keeps the choice
    ignore : ndarray of bool, shape (H, W), optional -- pixels left out of the change score (hands)
    held : list of bool, optional -- which instances a hand holds; held instances come first, moving
        or still
    steady : the two frames' :func:`steady_pixels`, when already computed

    Returns
    -------
    Choice
    """
    if not instances:
        return Choice(None, "none")
    tau = None
    if others is None or other_depth_m is None:
        scores, matches = [0.0] * len(instances), [(None, 0.0)] * len(instances)
    else:
        scores, matches, tau = change_scores(
            instances, depth_m, others, other_depth_m, change_m=change_m, ignore=ignore, steady=steady
        )
    kept = [mask_iou(m, previous) for m in instances] if previous is not None and previous.any() else None
    moving = [k for k, s in enumerate(scores) if s > min_change]
    if held is not None and any(held[k] for k in moving):
        moving = [k for k in moving if held[k]]
    common = dict(
        scores=tuple(float(s) for s in scores),
        matches=tuple(j for j, _ in matches),
        tau_m=tau,
        held=tuple(bool(h) for h in held or ()),
    )
    if moving:
        if kept is not None:
            staying = [k for k in moving if kept[k] >= keep_iou]
            if staying:
                return Choice(max(staying, key=lambda k: (scores[k], -k)), "moving, kept", **common)
        return Choice(max(moving, key=lambda k: (scores[k], -k)), "moving", **common)
    still = (
        [k for k in range(len(instances)) if held[k]]
        if held is not None and any(held)
        else range(len(instances))
    )
    if kept is not None:
        best = max(still, key=lambda k: (kept[k], -k))
        if kept[best] >= keep_iou:
            return Choice(best, "still, kept", **common)
    chosen = fallback_index([instances[k] for k in still])
    return Choice(None if chosen is None else still[chosen], "still, fallback", **common)


@dataclass
class _SequenceState:
    instances: dict[int, list[PackedMask]] = field(default_factory=dict)
    hands: dict[int, PackedMask | None] = field(default_factory=dict)
    chosen: list[PackedMask] = field(default_factory=list)  # frames 0 .. len - 1, in order
    choices: list[Choice | None] = field(default_factory=list)  # None: the mask came from the disk cache
    reference: PackedMask | None = None  # the choice that "previous" refers to (see _append)
    apart: BodiesApart | None = None  # the bodies that touch and separate, made on first use
    views: dict[int, FrameView] = field(default_factory=dict)  # what ``apart`` reads, until it takes it


class InstanceSegmenter(Segmenter):
    """Base of the segmenters that find several instances per frame.

    A subclass sets ``Params`` (a subclass of :class:`SelectionParams`) and implements
    :meth:`instances`; ``segment`` chooses the manipulated instance and caches the result.
    Thread-safe (the app shares one object between sessions).
    """

    Params = SelectionParams
    max_sequences = 64  # per-sequence states kept (least recently used dropped)

    def __init__(self, params: Params | None = None):
        super().__init__(params)
        self._lock = threading.RLock()
        self._states: OrderedDict[tuple, _SequenceState] = OrderedDict()
        self._steady: OrderedDict[tuple, np.ndarray] = OrderedDict()  # steady_pixels of recent frames
        cache_dir = getattr(self.params, "cache_dir", "")
        self._disk = DiskMaskCache(cache_dir, segmenter=self.name, params=self.params) if cache_dir else None

    # -- to implement ---------------------------------------------------------------------------
    def instances(self, frame: Frame, *, sequence: Sequence) -> list[np.ndarray]:
        """The object instances of ``frame``: list of ndarray of bool, shape (H, W), non-empty."""
        raise NotImplementedError

    def hands(self, frame: Frame, *, sequence: Sequence) -> np.ndarray | None:
        """The hand or gripper pixels of ``frame`` (bool (H, W)), or None when this segmenter does not
        look for hands (the default). ``instances`` should leave them out (see :meth:`hand_mask`)."""
        return None

    # -- the segmenter API ----------------------------------------------------------------------
    def segment(self, frame: Frame, *, sequence: Sequence) -> np.ndarray | None:
        """The mask of the manipulated instance in ``frame`` (None when the frame has no instance)."""
        self._prepare(frame, sequence)
        with self._lock:
            mask = self._chosen(frame, sequence)
        return None if mask.empty else mask.unpack()

    def choice(self, frame: Frame, *, sequence: Sequence) -> Choice | None:
        """Why ``frame``'s mask was chosen (None when it came from the disk cache)."""
        with self._lock:
            self._chosen(frame, sequence)
            return self._state(sequence).choices[frame.index]

    def frame_instances(self, frame: Frame, *, sequence: Sequence) -> list[np.ndarray]:
        """``instances`` of a frame, computed once per frame and sequence."""
        with self._lock:
            return [m.unpack() for m in self._instances(sequence, frame.index, frame)]

    def hand_mask(self, frame: Frame, *, sequence: Sequence) -> np.ndarray | None:
        """``hands`` of a frame, computed once per frame and sequence (None: no hand search)."""
        with self._lock:
            state = self._state(sequence)
            known = frame.index in state.hands
        if not known:  # worked out outside the lock: a pure function of the frame
            hand = self.hands(frame, sequence=sequence)
            with self._lock:
                state.hands.setdefault(frame.index, None if hand is None else PackedMask.pack(hand))
        packed = state.hands[frame.index]
        return None if packed is None else packed.unpack()

    # -- internals -------------------------------------------------------------------------------
    def _state(self, sequence: Sequence) -> _SequenceState:
        key = (str(sequence.path), sequence.name, len(sequence))
        state = self._states.get(key)
        if state is None:
            state = self._states[key] = _SequenceState()
            while len(self._states) > self.max_sequences:
                self._states.popitem(last=False)
        self._states.move_to_end(key)
        return state

    def _instances(self, sequence: Sequence, i: int, frame: Frame | None = None) -> list[PackedMask]:
        with self._lock:
            state = self._state(sequence)
            found = state.instances.get(i)
        if found is None:  # worked out outside the lock (unless the caller holds it): a pure function
            frame = frame if frame is not None and frame.index == i else sequence[i]
            masks = [m for m in self.instances(frame, sequence=sequence) if np.any(m)]
            found = [PackedMask.pack(m) for m in masks]
            view = frame_view(
                masks, frame.depth_m, self.hand_mask(frame, sequence=sequence), sequence.intrinsics
            )
            with self._lock:
                state.views.setdefault(i, view)
                found = state.instances.setdefault(i, found)
        return found

    def _prepare(self, frame: Frame, sequence: Sequence) -> None:
        """The instances of ``frame`` and of the frame it is compared with, worked out before the lock
        is taken, so that threads segmenting other frames work at the same time; the choice, which
        follows the frames in order, is made under the lock from them. Not with a disk cache (the
        chosen mask may be on the disk)."""
        if self._disk is not None:
            return
        n = len(sequence)
        for i in (frame.index, self._neighbour(frame.index, n), *self._reach(sequence, frame.index)):
            if 0 <= i < n:
                self._instances(sequence, i, frame)

    def _neighbour(self, j: int, n: int) -> int:
        """The frame that frame ``j`` of ``n`` is compared with: ``neighbour_frames`` after it, or
        before it near the end (outside 0 .. n - 1 when the sequence is too short)."""
        k = self.params.neighbour_frames
        return j + k if j + k < n else j - k

    def _chosen(self, frame: Frame, sequence: Sequence) -> PackedMask:
        state = self._state(sequence)
        if self._disk is not None and not state.chosen:
            self._disk.check_outside(sequence.path)
        while len(state.chosen) <= frame.index:
            self._decide_next(state, sequence, frame)
        return state.chosen[frame.index]

    def _decide_next(self, state: _SequenceState, sequence: Sequence, asked: Frame) -> None:
        j = len(state.chosen)
        frame = asked if asked.index == j else None
        name = frame.name if frame is not None else None
        if self._disk is not None:
            name = name or sequence[j].name
            cached = self._disk.load(sequence.path, sequence.name, name)
            if cached is not None:
                self._append(state, PackedMask.pack(cached), None)
                return
        p = self.params
        n = len(sequence)
        nb = self._neighbour(j, n)
        mine = [m.unpack() for m in self._instances(sequence, j, frame)]
        depth = (frame if frame is not None else sequence[j]).depth_m
        mine = self._apart(state, sequence, j, mine)
        if 0 <= nb < n and nb != j:
            others = [m.unpack() for m in self._instances(sequence, nb)]
            other_depth = sequence[nb].depth_m
            steady = self._steady_pixels(sequence, j, depth), self._steady_pixels(sequence, nb, other_depth)
        else:
            nb, others, other_depth, steady = None, None, None, None
        ignore, holding = self._hand_evidence(
            sequence, frame if frame is not None else sequence[j], nb, mine, depth
        )
        choice = choose_instance(
            mine,
            depth,
            others,
            other_depth,
            previous=None if state.reference is None else state.reference.unpack(),
            change_m=p.change_m,
            min_change=p.min_change,
            keep_iou=p.keep_iou,
            ignore=ignore,
            held=holding,
            steady=steady,
        )
        choice = dataclasses.replace(choice, neighbour=nb)
        shape = depth.shape
        packed = (
            PackedMask.pack(mine[choice.index])
            if choice.index is not None
            else PackedMask(shape, (0, 0, 0, 0), b"")
        )
        if self._disk is not None:
            self._disk.store(sequence.path, sequence.name, name or sequence[j].name, packed.unpack())
        self._append(state, packed, choice)

    def _apart(
        self, state: _SequenceState, sequence: Sequence, j: int, instances: list[np.ndarray]
    ) -> list[np.ndarray]:
        """Frame ``j``'s instances with the bodies cut out that separate from them in the frames within
        reach (:mod:`.apart`: a mug lifted off its stand and the stand are two instances while they
        touch too)."""
        p = self.params
        if state.apart is None:
            state.apart = BodiesApart(sequence.intrinsics, change_m=p.change_m, min_change=p.min_change)
        apart, others = state.apart, self._reach(sequence, j)
        for u in (j, *others):
            if u not in apart.views:
                self._instances(sequence, u)  # and its view
                apart.add(u, state.views.pop(u))
        apart.forget_before(j)
        for u in [u for u in state.views if u < j]:  # frames left behind (asked out of order)
            del state.views[u]
        return apart.split(j, instances, others)

    def _reach(self, sequence: Sequence, j: int) -> list[int]:
        """The frames :meth:`_apart` compares frame ``j`` with; of a live stream, none later than the
        neighbouring frame, which the choice waits for."""
        k = self.params.neighbour_frames
        return reach(j, len(sequence), k, ahead=k if sequence.meta.get("live") else REACH_FRAMES)

    def _steady_pixels(self, sequence: Sequence, i: int, depth_m: np.ndarray) -> np.ndarray:
        """:func:`steady_pixels` of frame ``i``, kept for the last few frames: each frame is compared
        with the frame ``neighbour_frames`` before it and the one after it."""
        key = (str(sequence.path), sequence.name, i)
        if key not in self._steady:
            self._steady[key] = steady_pixels(depth_m, change_m=self.params.change_m)
            while len(self._steady) > 2 * self.params.neighbour_frames + 2:
                self._steady.popitem(last=False)
        return self._steady[key]

    def _hand_evidence(
        self,
        sequence: Sequence,
        frame: Frame,
        nb: int | None,
        instances: list[np.ndarray],
        depth_m: np.ndarray,
    ) -> tuple[np.ndarray | None, list[bool] | None]:
        """The pixels to leave out of the change score (the hands of this and the neighbouring frame,
        with their margin) and which instances the hand holds; (None, None) without a hand search."""
        p = self.params
        hand = self.hand_mask(frame, sequence=sequence)
        if hand is None or not isinstance(p, HandParams):
            return None, None
        other = self.hand_mask(sequence[nb], sequence=sequence) if nb is not None else None
        ignore = widen(hand if other is None else hand | other, p.hand_margin_px)
        return ignore, held(
            instances,
            hand,
            clean_depth(depth_m),
            touch_m=p.hand_touch_m,
            reach_px=p.hand_margin_px + 1,
            line_m=HOLD_LINE_M,
            fx=sequence.intrinsics.fx,
            intrinsics=sequence.intrinsics,
        )

    @staticmethod
    def _append(state: _SequenceState, packed: PackedMask, choice: Choice | None) -> None:
        state.chosen.append(packed)
        state.choices.append(choice)
        # A choice kept only because it overlaps the reference does not become the reference: a
        # still object whose segment merges with a neighbour for a frame would otherwise hand the
        # choice on to that neighbour.
        if not packed.empty and (choice is None or choice.rule != "still, kept"):
            state.reference = packed
