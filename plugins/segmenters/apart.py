"""Two bodies that touch and then separate are two bodies, in every frame.

A mug on its stand, a kettle on its base: while they touch, a segmenter sees one instance. Once the
hand lifts the mug, it sees two, and the stand stays where it was. The stand is no part moving about
a joint (a joint keeps its parts in contact), yet a pair of frames that holds it in the mug's mask
shows two motions. So a body that a frame within reach shows as an instance of its own is cut out
of an instance of this frame that holds most of it, when:

- it stays where it is over the frames within reach: in none of them do more than ``min_change`` of
  its pixels (the share of changed pixels that makes an instance move in the choice) show a farther
  depth, as they would once it left. What comes in front of it, the hand or the mug lifted above it,
  hides it but does not move it;
- the rest of the instance leaves its place between this frame and that one: its pixels that show
  a farther depth there are more than ``min_change`` of the instance's;
- that frame shows the rest apart: a body at least half its size that moves, farther than a
  joint's contact (``CONTACT_M``, the video's test of separated parts) from it in 3-D, with what
  lies between them in the picture seen: where that is mostly a hand or has no readings, the two
  may meet out of sight. A frame's bodies are its instances cut where their depth steps by more
  than a contact, read across the pixel that a sensor mixes at a step (:func:`split_at_steps`): a
  kettle held above its base, seen against it, is one instance with it, and that step is all that
  shows them apart. A laptop whose lid lies
  closed is one instance that stays, with no body beside it; a monitor whose neck the picture
  misses has its screen within a contact of its foot; a dark lid seen edge-on shows its far edge
  beyond a face without readings.

A depth change counts when it exceeds ``change_m`` and four robust sigmas of the change over all the
pixels both frames read (most of a scene stays), on the pixels away from a depth edge in both
frames: an edge's readings flicker between its two sides when anything moves, the camera too. Each
frame is compared with the frames a multiple of the choice's ``neighbour_frames`` from the first
within :data:`REACH_FRAMES` (:func:`reach`), at half the resolution.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np
from scipy.spatial import cKDTree

from artclass_core import Intrinsics
from artclass_core.video import CONTACT_M

from .hands import widen
from .support import clean_depth, grown_box, label_box, region_mask

__all__ = ["MIXED_PX", "REACH_FRAMES", "BodiesApart", "FrameView", "frame_view", "reach", "split_at_steps"]

#: How far (frames each way) a body is sought apart: an object is carried clear of what it stood on
#: within a second at 30 frames a second.
REACH_FRAMES = 30
#: A body lies in an instance when this share of its pixels does.
INSIDE_SHARE = 0.5
#: Where most of what lies between two bodies in the picture (within a contact of both) has no
#: reading or is a hand, where they meet may be hidden.
HIDDEN_SHARE = 0.5
#: A step in depth reads through a mixed pixel: a sensor's window (a time-of-flight pixel, a stereo
#: or structured-light match) that straddles it reads between the two depths. So readings this many
#: pixels apart, and one more, show the step.
MIXED_PX = 1
#: The tests read every second pixel each way.
_STEP = 2
#: A depth farther than any reading, for the pixels without one.
_NO_READING_M = 1e6


def reach(j: int, n: int, stride: int, *, ahead: int = REACH_FRAMES) -> list[int]:
    """The frames that frame ``j`` of ``n`` is compared with: the multiples of ``stride`` from
    :data:`REACH_FRAMES` before it to ``ahead`` after it (a live stream is not waited for longer than
    the choice waits)."""
    first = -(-max(j - REACH_FRAMES, 0) // stride) * stride
    return [u for u in range(first, min(j + ahead, n - 1) + 1, stride) if u != j]


class FrameView(NamedTuple):
    """What the tests read of a frame, at half the resolution but for the outlines."""

    depth: np.ndarray  # depth, metres, 0 = no reading
    span: np.ndarray  # the depth each pixel's 3x3 neighbourhood spans (much next to no reading)
    bodies: list[np.ndarray]  # the instances
    boxes: list[tuple[int, int, int, int]]  # their bounding boxes (x, y, w, h)
    pieces: list[np.ndarray]  # the instances cut where the depth steps by more than a contact
    piece_boxes: list[tuple[int, int, int, int]]
    rims: list[np.ndarray]  # the 3-D points (N, 3) of the pieces' outlines, at full resolution
    unseen: np.ndarray  # the pixels with no reading, or a hand's
    stepped: np.ndarray  # the instances' pixels beyond a step, which no piece holds


def frame_view(
    instances: list[np.ndarray], depth_m: np.ndarray, hand: np.ndarray | None, intrinsics: Intrinsics
) -> FrameView:
    """The :class:`FrameView` of a frame's instances (bool (H, W) each), depth and hand pixels (None:
    not sought)."""
    depth = clean_depth(depth_m)
    span = cv2.morphologyEx(depth, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8))  # max - min over 3x3
    unseen = depth <= 0 if hand is None else (depth <= 0) | hand
    bodies = [m[::_STEP, ::_STEP] for m in instances]
    whole, stepped = split_at_steps(instances, depth, step_m=CONTACT_M)
    pieces = [m[::_STEP, ::_STEP] for m in whole]
    return FrameView(
        depth[::_STEP, ::_STEP],
        span[::_STEP, ::_STEP],
        bodies,
        [cv2.boundingRect(m.view(np.uint8)) for m in bodies],
        pieces,
        [cv2.boundingRect(m.view(np.uint8)) for m in pieces],
        [_rim_points(m, depth, intrinsics) for m in whole],
        unseen[::_STEP, ::_STEP],
        stepped[::_STEP, ::_STEP],
    )


def split_at_steps(
    instances: list[np.ndarray], depth_m: np.ndarray, *, step_m: float
) -> tuple[list[np.ndarray], np.ndarray]:
    """The instances cut where they step in depth by more than ``step_m``: a reading whose instance
    reads a nearer depth by more than that within ``MIXED_PX + 1`` pixels is on the far side of a
    step, or one of the mixed readings across it, and goes; each instance falls into the pieces that
    connect through one surface. Pieces smaller than a tenth of their instance go too (a rim of mixed
    readings). One step does not tell two bodies from one body's cliff seen from above; the tests of
    :class:`BodiesApart` do, over time.

    Returns the pieces and the pixels that went (bool (H, W))."""
    out, gone = [], np.zeros(depth_m.shape, bool)
    window = np.ones((2 * MIXED_PX + 3,) * 2, np.uint8)
    for mask in instances:
        box = grown_box(mask, MIXED_PX + 1)
        read = mask[box] & (depth_m[box] > 0)
        z = np.where(read, depth_m[box], _NO_READING_M).astype(np.float32)
        far = read & (z - cv2.erode(z, window) > step_m)
        if not far.any():
            out.append(mask)
            continue
        gone[box] |= far
        kept = mask.copy()
        kept[box] &= ~far
        count, labels, stats, within = label_box(kept)
        least = 0.1 * np.count_nonzero(mask)
        out += [
            region_mask(k, labels, stats, within, mask.shape)
            for k in range(1, count)
            if stats[k, cv2.CC_STAT_AREA] >= least
        ]
    return out, gone


class BodiesApart:
    """The cuts of one sequence (see the module docstring). Frames are added as their instances are
    known, and forgotten once out of reach."""

    def __init__(self, intrinsics: Intrinsics, *, change_m: float, min_change: float):
        self.intrinsics = intrinsics
        self.change_m, self.min_change = change_m, min_change
        self.views: dict[int, FrameView] = {}  # the frames within reach
        self._taus: dict[tuple[int, int], float] = {}
        self._left: dict[tuple[int, int, int], bool] = {}  # (frame, instance, other frame): it left
        self._apart: dict[tuple[int, int, int], bool] = {}  # (frame, instance, instance): apart in 3-D

    def add(self, u: int, view: FrameView) -> None:
        """Frame ``u``'s :class:`FrameView`."""
        self.views.setdefault(u, view)

    def forget_before(self, j: int) -> None:
        """Forget the frames out of reach of frame ``j`` and those before it."""
        old = {u for u in self.views if u < j - REACH_FRAMES}
        for u in old:
            del self.views[u]
        self._taus = {k: t for k, t in self._taus.items() if not old & set(k)}
        self._left = {k: t for k, t in self._left.items() if k[0] not in old and k[2] not in old}
        self._apart = {k: t for k, t in self._apart.items() if k[0] not in old}

    def split(self, j: int, instances: list[np.ndarray], others: list[int]) -> list[np.ndarray]:
        """``instances`` of frame ``j`` (added) with the bodies cut out that the frames ``others``
        (added) show apart from them, each cut an instance of its own after them; the same list when
        nothing is cut."""
        if not instances:
            return instances
        out, cuts = list(instances), []
        frames = others + [j]
        still = [
            (u, b)
            for u in others
            for b in range(len(self.views[u].pieces))
            if not any(self._left_by(u, b, v) for v in frames if v != u)
        ]
        for k, mine in enumerate(self.views[j].bodies):
            for u, b in still:
                if self._separates(mine, j, k, u, b, frames):
                    cut = self._cut(self.views[u].pieces[b], mine, j, u, out[k].shape) & out[k]
                    if cut.any():
                        out[k] = out[k] & ~cut
                        cuts.append(cut)
        return [m for m in out if m.any()] + cuts if cuts else instances

    def _separates(self, mine: np.ndarray, j: int, k: int, u: int, b: int, frames: list[int]) -> bool:
        """Whether body ``b`` of frame ``u`` (a piece: :func:`split_at_steps`), which stays where it is,
        is a body that instance ``k`` of frame ``j`` (``mine``) holds and separates from (the module
        docstring's last two tests)."""
        body, bodies = self.views[u].pieces[b], self.views[u].pieces
        if not _overlap(self.views[j].boxes[k], self.views[u].piece_boxes[b]) or np.count_nonzero(
            body & mine
        ) < INSIDE_SHARE * np.count_nonzero(body):
            return False
        rest = mine & ~body
        if not self._leaves(rest, j, u, box=self.views[j].boxes[k], of=mine):
            return False
        least = INSIDE_SHARE * np.count_nonzero(rest)  # the rest, seen apart
        return any(
            np.count_nonzero(bodies[r]) >= least
            and self._apart_from(u, b, r)
            and any(self._left_by(u, r, v) for v in frames if v != u)
            for r in range(len(bodies))
            if r != b
        )

    # -- internals --------------------------------------------------------------------------------
    def _tau(self, u: int, v: int) -> float:
        """The depth change that counts between frames ``u`` and ``v``."""
        key = (min(u, v), max(u, v))
        if key not in self._taus:
            a, b = self.views[u].depth[::4, ::4], self.views[v].depth[::4, ::4]  # plenty for a median
            change = np.abs(a - b)[(a > 0) & (b > 0)]
            sigma = 1.4826 * float(np.median(change)) if change.size else 0.0
            self._taus[key] = max(self.change_m, 4.0 * sigma)
        return self._taus[key]

    def _leaves(self, mask: np.ndarray, u: int, v: int, *, box: tuple, of: np.ndarray | None = None) -> bool:
        """Whether ``mask``'s pixels (half resolution, frame ``u``, within ``box``: x, y, w, h) that
        show a farther depth in frame ``v`` (what was there left) are more than ``min_change`` of
        those of ``of`` (default ``mask``) away from a depth edge in both frames: whose 3x3
        neighbourhood spans no more than the change that counts (an edge's readings flicker between
        its two sides when anything moves, the camera too)."""
        x, y, w, h = box
        crop = np.s_[y : y + h, x : x + w]
        a, b, tau = self.views[u].depth[crop], self.views[v].depth[crop], self._tau(u, v)
        read = (self.views[u].span[crop] <= tau) & (self.views[v].span[crop] <= tau)
        left = np.count_nonzero(mask[crop] & read & (b > a + tau))
        whole = mask if of is None else of
        return left > self.min_change * np.count_nonzero(whole[crop] & read)

    def _left_by(self, u: int, b: int, v: int) -> bool:
        """Whether body ``b`` of frame ``u`` left its place by frame ``v``."""
        key = (u, b, v)
        if key not in self._left:
            self._left[key] = self._leaves(self.views[u].pieces[b], u, v, box=self.views[u].piece_boxes[b])
        return self._left[key]

    def _apart_from(self, u: int, b: int, r: int) -> bool:
        """Whether bodies ``b`` and ``r`` of frame ``u`` are farther than :data:`CONTACT_M` apart in
        3-D (their outlines' points), and the picture shows what lies between them: two bodies, not
        two sides of a part whose joint the hand, or a surface without readings, hides."""
        key = (u, b, r)
        if key not in self._apart:
            rims = [self.views[u].rims[k] for k in (b, r)]
            apart = (
                all(len(p) for p in rims)
                and not np.isfinite(cKDTree(rims[0]).query(rims[1], distance_upper_bound=CONTACT_M)[0]).any()
            )
            if apart:
                # a contact's width in half-resolution pixels, at the outlines' median depth
                z = float(np.median(np.concatenate([p[:, 2] for p in rims])))
                disc = cv2.getStructuringElement(
                    cv2.MORPH_ELLIPSE, (2 * int(CONTACT_M * self.intrinsics.fx / z / _STEP) + 1,) * 2
                )
                near = [cv2.dilate(self.views[u].pieces[k].view(np.uint8), disc) > 0 for k in (b, r)]
                between = near[0] & near[1] & ~self.views[u].pieces[b] & ~self.views[u].pieces[r]
                hidden = np.count_nonzero(between & self.views[u].unseen)
                apart = hidden <= HIDDEN_SHARE * np.count_nonzero(between)
            self._apart[key] = bool(apart)
        return self._apart[key]

    def _cut(self, body: np.ndarray, mine: np.ndarray, j: int, u: int, shape: tuple[int, int]) -> np.ndarray:
        """The pixels of frame ``j`` (full resolution, ``shape``) where the body (of frame ``u``,
        half resolution) shows itself in ``mine`` at the depth it has in frame ``u``; the pieces of
        frame ``j`` that lie mostly there and hold none of what left ``mine`` (a farther depth in
        frame ``u``): what frame ``u`` did not see of the body, uncovered since; the readings beyond a
        step beside them (the body's own, and mixed ones, next to what lies in front of it); and a
        pixel around them."""
        view, tau = self.views[j], self._tau(j, u)
        a, b = view.depth, self.views[u].depth
        same = body & mine & (a > 0) & (np.abs(a - b) <= tau)
        left = mine & (a > 0) & (b > a + tau)
        for piece in view.pieces:
            if (
                np.count_nonzero(piece & same) >= INSIDE_SHARE * np.count_nonzero(piece)
                and not (piece & left).any()
            ):
                same |= piece
        reach = -(-(MIXED_PX + 1) // _STEP)  # at half resolution, rounded up
        same |= view.stepped & widen(same, reach)
        h, w = shape
        full = cv2.resize(same.view(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
        return widen(full, 1)


def _overlap(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    """Whether two (x, y, w, h) boxes share a pixel."""
    return a[0] < b[0] + b[2] and b[0] < a[0] + a[2] and a[1] < b[1] + b[3] and b[1] < a[1] + a[3]


def _rim_points(mask: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """The 3-D points (N, 3) of the outline of ``mask`` (bool (H, W)) where it has a reading."""
    box = grown_box(mask, 1)  # the erosion gives there what it gives on the whole image
    m = mask[box]
    rim = m & ~(cv2.erode(m.view(np.uint8), np.ones((3, 3), np.uint8)) > 0) & (depth_m[box] > 0)
    v, x = np.nonzero(rim)
    v, x = v + box[0].start, x + box[1].start
    return intrinsics.points(x, v, depth_m[v, x].astype(np.float64))
