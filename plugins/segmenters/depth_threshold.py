"""The ``depth_threshold`` segmenter: what stands out of the scene's large planes, by depth alone.

Per frame: keep the depth readings inside ``[near_m, far_m]``; remove the large background planes
(the support plane, the points behind it such as the floor beyond a table's edge, and a second large
plane such as a wall; see :mod:`.support`); open the remaining mask by ``open_px``; its connected
components of at least ``min_area_fraction`` of the image are the instances. Each then takes back,
by hysteresis, the pixels within ``plane_distance_m`` of a plane that still stand out of it by more
than ``grow_sigmas`` times its measured noise and connect to the instance (the lower centimetre of
an object lying on a table; instances they connect become one: the two levers of pliers lying flat,
whose pivot is too low to survive the plane removal). Such pixels that form a region of their own,
whose colour differs from the surface around it by ``thin_contrast``, are an instance too: an
object a few millimetres thick lying flat (scissors); so is a patch of the table whose colour differs
from the table around it by ``thin_contrast`` and whose height stands out of the table around it
(:func:`colour_patches`: a ruler whose single readings are lost in a far sensor's noise).
Instances whose 3-D points still come within ``join_m`` of each other are one object: the parts of
an articulated object touch at their joint. Each instance takes back the holes it encloses whose
rim meets it within ``plane_distance_m`` in 3-D (a tray's floor lying on the table; not the table
seen through a handle). Last, it takes the dropouts (pixels without a reading) that a closing of
radius ``fill_px`` puts inside it. Hands and the gripper (:mod:`.hands`) are left out from the
start, so a hand neither becomes an object nor joins two; the instances a hand hides in part, seen
farther than ``hand_touch_m`` behind it, are one object (a hand passing in front of an object cuts
it in two). The shared selection (:mod:`.selection`) picks the one being manipulated.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from artclass_core import Frame, Intrinsics, Sequence, param

from ._compiled import colour_distance_kernel, share_mean_kernel
from .hands import HOLD_LINE_M, HandParams, find_hands, held, hidden, pixels_across, widen
from .selection import InstanceSegmenter, SelectionParams
from .support import (
    BORDER_PX,
    DEPTH_STEP_M,
    BackgroundParams,
    Plane,
    above_planes,
    as_uint8,
    background_mask,
    border_band,
    clean_depth,
    fit_planes,
    grown_box,
    label_box,
    label_regions,
    plane_height_m,
    range_mask,
    region_mask,
    rows_for_opencv,
)

__all__ = [
    "DepthThresholdParams",
    "DepthThresholdSegmenter",
    "MaskFreeSegmenter",
    "components",
    "fill_dropouts",
    "fill_floors",
    "grow",
    "join_touching",
    "join_hidden",
    "thin_objects",
    "colour_patches",
]


@dataclass(frozen=True)
class DepthThresholdParams(SelectionParams, BackgroundParams, HandParams):
    open_px: int = param(
        0,
        unit="px",
        bounds=(0, 10),
        help="Morphological opening radius: removes speckle and thin bridges (flying "
        "pixels) between objects and the background.",
    )
    min_area_fraction: float = param(
        0.002,
        unit="fraction",
        bounds=(0.0, 0.5),
        help="Connected regions smaller than this share of the image are not "
        "instances (about 600 px at 640x480).",
    )
    fill_px: int = param(
        2,
        unit="px",
        bounds=(0, 20),
        help="Pixels without a depth reading that a closing of this radius puts inside an "
        "instance join it (sensor dropouts on the object; they carry no points).",
    )
    grow_sigmas: float = param(
        4.0,
        unit="sigma",
        bounds=(0.0, 100.0),
        help="Hysteresis: pixels nearer than plane_distance_m to a background plane that "
        "stand out of it by more than this many times its measured depth noise join "
        "the instances they connect to (an object's lower centimetre on a table). "
        "0 = off.",
    )
    thin_contrast: float = param(
        10.0,
        unit="ΔE",
        bounds=(0.0, 100.0),
        help="Thin objects lying flat: a region standing out of the support plane by more "
        "than grow_sigmas times its noise, though nearer than plane_distance_m, is an "
        "object of its own when its colour differs from the surface around it by at "
        "least this CIE76 colour difference (2.3 is just noticeable). 0 = off.",
    )
    join_m: float = param(
        0.01,
        unit="m",
        bounds=(0.0, 0.5),
        help="Instances whose 3-D points come this close are one object: the parts of an "
        "articulated object touch at the joint (the levers of pliers lying flat are cut "
        "apart 3-4 mm at a pivot too low to stand out of the table). 0 = never join.",
    )


def fill_dropouts(instances: list[np.ndarray], valid: np.ndarray, *, fill_px: int) -> list[np.ndarray]:
    """Add to each instance the pixels without a depth reading that a closing of radius ``fill_px``
    puts inside it (holes and ragged edges from sensor dropouts). Instances are not modified."""
    if not fill_px:
        return instances
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * fill_px + 1, 2 * fill_px + 1))
    out = []
    for mask in instances:
        box = grown_box(mask, fill_px)
        crop = np.pad(mask[box].astype(np.uint8), fill_px)
        closed = cv2.morphologyEx(crop, cv2.MORPH_CLOSE, kernel)[fill_px:-fill_px, fill_px:-fill_px] > 0
        filled = mask.copy()
        filled[box] |= closed & ~valid[box]
        out.append(filled)
    return out


def grow(instances: list[np.ndarray], low: np.ndarray) -> list[np.ndarray]:
    """Hysteresis: each instance with the ``low`` pixels connected (8-connected) to it; instances the low
    pixels connect become one. Largest first; low pixels that touch no instance are dropped."""
    seeds = np.logical_or.reduce(instances)
    _, labels, stats, box = label_box(seeds | low)
    keep = sorted(
        np.flatnonzero(np.bincount(labels[seeds[box]])), key=lambda k: (-stats[k, cv2.CC_STAT_AREA], k)
    )
    return [region_mask(k, labels, stats, box, seeds.shape) for k in keep]


def join_touching(
    instances: list[np.ndarray], depth_m: np.ndarray, intrinsics: Intrinsics, *, join_m: float
) -> list[np.ndarray]:
    """Instances whose 3-D points (those on the mask's boundary, where two instances meet) come within
    ``join_m`` of each other, directly or through others, made one. Largest first."""
    if len(instances) < 2 or join_m <= 0:
        return instances
    rims = [_rim_points(m, depth_m, intrinsics) for m in instances]
    group = list(range(len(instances)))
    for a in range(len(instances)):
        if not len(rims[a]):
            continue
        tree = _tree(rims[a])
        for b in range(a + 1, len(instances)):
            if len(rims[b]) and np.isfinite(tree.query(rims[b], distance_upper_bound=join_m)[0]).any():
                old, new = group[b], group[a]
                group = [new if g == old else g for g in group]
    joined = [
        np.logical_or.reduce([m for m, g in zip(instances, group) if g == k]) for k in sorted(set(group))
    ]
    return sorted(joined, key=lambda m: -int(m.sum()))


def _rim_points(mask: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """The 3-D points (N, 3), metres, of the pixels of ``mask`` (bool (H, W), not empty) with a reading
    (``depth_m`` > 0, no NaN) that a 3x3 erosion removes: its boundary. Worked out on the mask's
    bounding box grown by a pixel, where the erosion gives what it gives on the whole image."""
    box = grown_box(mask, 1)
    m = mask[box]
    rim = m & ~(cv2.erode(m.view(np.uint8), np.ones((3, 3), np.uint8)) > 0) & (depth_m[box] > 0)
    return _points(depth_m, rim, (box[0].start, box[1].start), intrinsics)


def join_hidden(
    instances: list[np.ndarray],
    hand: np.ndarray | None,
    depth_m: np.ndarray,
    intrinsics: Intrinsics,
    *,
    touch_m: float,
) -> list[np.ndarray]:
    """Instances that the hand hides in part (:func:`.hands.hidden`: seen beside it, farther than
    ``touch_m`` behind it, along a line of at least ``HOLD_LINE_M``) made one, when the hand holds none
    of them (:func:`.hands.held`): a hand or arm passing in front of an object cuts it in two, and
    both sides are the same object. A hand that holds an object may hide others behind it, which stay
    apart. Largest first."""
    if len(instances) < 2 or hand is None:
        return instances
    reach_px = pixels_across(touch_m, intrinsics.fx, depth_m[hand & (depth_m > 0)]) if hand.any() else 1
    if any(
        held(
            instances,
            hand,
            depth_m,
            touch_m=touch_m,
            reach_px=reach_px,
            line_m=HOLD_LINE_M,
            fx=intrinsics.fx,
            intrinsics=intrinsics,
        )
    ):
        return instances
    behind = hidden(instances, hand, depth_m, touch_m=touch_m, line_m=HOLD_LINE_M, fx=intrinsics.fx)
    if sum(behind) < 2:
        return instances
    joined = [np.logical_or.reduce([m for m, b in zip(instances, behind) if b])]
    return sorted(joined + [m for m, b in zip(instances, behind) if not b], key=lambda m: -int(m.sum()))


def _table_depth(depth_m: np.ndarray, table: np.ndarray) -> float:
    """The median depth of the ``table`` pixels (not empty), from every fourth row and column when
    that sample holds any: a typical distance, to size a window by."""
    sample = depth_m[::4, ::4][table[::4, ::4]]
    return float(np.median(sample if sample.size else depth_m[table]))


def fill_floors(
    instances: list[np.ndarray], depth_m: np.ndarray, intrinsics: Intrinsics, *, gap_m: float
) -> list[np.ndarray]:
    """Add to each instance the holes it encloses whose rim mostly (the median of its pixels) comes within
    ``gap_m`` in 3-D of the instance's own pixels around the hole: a surface of the object that the plane
    removal took (a tray's floor lying on the table, its walls' lower centimetre gone with it), not the
    background seen through the object (the table through a mug's handle, centimetres behind the
    handle). Instances are not modified."""
    kernel = np.ones((3, 3), np.uint8)
    out = []
    for mask in instances:
        box = grown_box(mask, 0)
        m = mask[box]
        holes = _holes(m)
        n, labels = cv2.connectedComponents(as_uint8(holes), connectivity=8)
        if n < 2:
            out.append(mask)
            continue
        seen = depth_m[box] > 0
        around = m & (cv2.dilate(as_uint8(holes), kernel) > 0) & seen
        rim = holes & (cv2.dilate(as_uint8(m), kernel) > 0) & seen
        if not rim.any() or not around.any():
            out.append(mask)
            continue
        corner = (box[0].start, box[1].start)
        gaps = _tree(_points(depth_m, around, corner, intrinsics)).query(
            _points(depth_m, rim, corner, intrinsics)
        )[0]
        which, holes_k = labels[rim], np.arange(1, n)  # _points' order is row-major, as this
        has_rim = np.bincount(which, minlength=n)[1:] > 0
        good = holes_k[has_rim & (np.asarray(ndimage.median(gaps, which, holes_k)) <= gap_m)]
        filled = mask.copy()
        chosen = np.zeros(n, bool)
        chosen[good] = True
        filled[box] |= chosen[labels]
        out.append(filled)
    return out


def _tree(points: np.ndarray) -> cKDTree:
    """A k-d tree of ``points`` (N, 3) for nearest-neighbour distances, built without balancing or
    compacting its nodes: a query finds the same nearest distances, and the tree of a few thousand
    points is built in half the time."""
    return cKDTree(points, balanced_tree=False, compact_nodes=False)


def _holes(mask: np.ndarray) -> np.ndarray:
    """The pixels outside ``mask`` (bool (H, W)) that it encloses: not connected (4-connected) to the
    image border through pixels outside it (:func:`scipy.ndimage.binary_fill_holes`, by a flood fill
    from the border). bool (H, W)."""
    outside = np.pad(mask.astype(np.uint8), 1)
    cv2.floodFill(outside, None, (0, 0), 2, flags=4)
    return outside[1:-1, 1:-1] == 0


def _points(
    depth_m: np.ndarray, where: np.ndarray, corner: tuple[int, int], intrinsics: Intrinsics
) -> np.ndarray:
    """The 3-D points (N, 3), metres, of the pixels ``where`` (bool, a crop of the image whose first row
    and column are ``corner``), in row-major order: :meth:`Intrinsics.backproject` of the crop alone."""
    v, u = np.nonzero(where)
    v, u = v + corner[0], u + corner[1]
    return intrinsics.points(u, v, depth_m[v, u].astype(np.float64))


def thin_objects(
    low: np.ndarray, rgb: np.ndarray, *, min_area_fraction: float, contrast: float, ring_px: int = 3
) -> list[np.ndarray]:
    """Regions of ``low`` (pixels a little above the support plane) that are objects lying flat: the
    connected components of ``low`` after a 3x3 opening (the plane's noise leaves single pixels), of at
    least ``min_area_fraction`` of the image, whose mean CIE Lab colour differs by at least
    ``contrast`` (CIE76 delta E) from that of a ring ``ring_px`` wide around them. Largest first.

    Parameters
    ----------
    low : ndarray of bool, shape (H, W)
    rgb : ndarray, shape (H, W, 3), uint8, RGB order

    Returns
    -------
    list of ndarray of bool, shape (H, W)
    """
    found = components(low, open_px=1, min_area_fraction=min_area_fraction)
    if not found:
        return found
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * ring_px + 1, 2 * ring_px + 1))
    out = []
    for m in found:  # each in its bounding box, grown by the ring
        box = grown_box(m, ring_px)
        lab = cv2.cvtColor(rows_for_opencv(rgb[box]), cv2.COLOR_RGB2Lab).astype(np.float32)
        lab[..., 0] *= 100.0 / 255.0  # OpenCV's 8-bit Lab: L scaled by 255/100, a and b offset by 128
        inside = m[box]
        ring = (cv2.dilate(as_uint8(inside), disc) > 0) & ~low[box]
        if ring.any() and np.linalg.norm(lab[inside].mean(axis=0) - lab[ring].mean(axis=0)) >= contrast:
            out.append(m)
    return out


def colour_patches(
    plane: np.ndarray,
    rgb: np.ndarray,
    height_m: np.ndarray,
    *,
    noise_m: float,
    sigmas: float,
    contrast: float,
    min_area_fraction: float,
    window_px: int,
    surface: np.ndarray | None = None,
    ring_px: int = 3,
) -> list[np.ndarray]:
    """Objects lying flat, found by colour first: the pixels of ``plane`` whose CIE Lab colour differs
    by at least ``contrast`` (CIE76 delta E, their colour averaged over ``THIN_WINDOW_PX`` squared
    pixels) from the mean colour of the ``window_px`` square around them, left out the pixels that
    themselves differ from it (:class:`SampledColours`: first on a sample of the pixels, then pixel
    by pixel near what it finds), grouped into connected components of at least
    ``min_area_fraction`` of the image. A component is an object when its median height stands out
    of the table around it (the median height of the plane's pixels between ``2 * ring_px`` and
    half a window from it) by more than the plane's noise ``noise_m`` and more than ``sigmas`` times
    the noise of a mean (``noise_m / sqrt(n)`` over n readings). A pattern on the table is at its
    height; an object a few millimetres thick stands out of it on average though none of its single
    readings does. The table around it, not the plane, is the reference: where the plane fits the
    table poorly, or the readings beside a tall object stand off it, a patch there is no higher than
    its surroundings. The patch must lie on the table: ``ON_TABLE_SHARE`` of a ring ``ring_px`` wide
    around it on ``surface`` (not the border between the table and the wall behind it, whose mixed
    readings stand off the table). Largest first.

    Parameters
    ----------
    plane : ndarray of bool, shape (H, W) -- pixels on the support plane, with a reading
    rgb : ndarray, shape (H, W, 3), uint8, RGB order
    height_m : ndarray, shape (H, W), metres -- height above the plane (:func:`.support.plane_height_m`)
    noise_m : metres -- a single reading's noise on the plane
    window_px : odd side of the square whose mean colour is the surface around a pixel
    surface : ndarray of bool, shape (H, W), optional -- what may surround an object lying flat (the
        support plane, the hand that holds it); default ``plane``

    Returns
    -------
    list of ndarray of bool, shape (H, W)
    """
    if not plane.any():
        return []
    surface = plane if surface is None else surface
    # the colours are needed on the plane's bounding box and the half window around it only
    box = grown_box(plane, window_px // 2 + COLOUR_STRIDE_PX)
    colours = SampledColours(rgb[box], window_px=window_px, least_sq=np.float32(contrast * contrast))
    least_px = min_area_fraction * plane.size
    distinct = np.zeros(plane.shape, bool)
    for within, own in colours.candidates(plane[box], least_px=least_px):
        # pixel by pixel, on the box of the candidate's pixels (in the image: ``near``)
        near = tuple(slice(b.start + w.start, b.start + w.stop) for b, w in zip(box, within))
        distinct[near] |= colours.pixels_distinct(rgb[near], within) & own & plane[near]
    found = components(distinct, open_px=0, min_area_fraction=min_area_fraction)
    out = []
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * ring_px + 1, 2 * ring_px + 1))
    reach = max(window_px // 2, 3 * ring_px)
    for m in found:
        near = grown_box(m, reach)  # each in its bounding box, grown by the table around it
        inside = m[near]
        ring = (cv2.dilate(inside.view(np.uint8), disc) > 0) & ~inside
        if np.count_nonzero(ring & surface[near]) < ON_TABLE_SHARE * np.count_nonzero(ring):
            continue
        h = height_m[near][inside]
        # the table's own level around it, beyond the readings its outline mixes with the table's
        away = cv2.distanceTransform((~inside).view(np.uint8), cv2.DIST_L2, 3)
        level = height_m[near][plane[near] & (away > 2 * ring_px) & (away <= reach)]
        lift = float(np.median(h)) - (float(np.median(level)) if len(level) else 0.0)
        if lift > noise_m and lift > sigmas * noise_m / np.sqrt(len(h)):
            out.append(m)
    return out


class SampledColours:
    """The colour test of objects lying flat (see :func:`colour_patches`) on an 8-bit RGB image
    (H, W, 3), first on every ``COLOUR_STRIDE_PX``-th pixel in x and y: the CIE Lab colour of each
    sample (the mean of its THIN_WINDOW_PX squared pixels) and the mean of the samples in the
    ``window_px`` square around it that do not differ from that window's mean by ``least_sq`` (the
    surface around it: an object's own colour does not pull the mean of the table beside it, so a
    large, vivid handle leaves no halo of table around it); then pixel by pixel where the samples
    find something. The window's mean is smooth on the scale of the stride, and the samples cost a
    fraction of the pixels' conversion to CIE Lab.
    """

    def __init__(self, rgb: np.ndarray, *, window_px: int, least_sq: np.float32):
        s = COLOUR_STRIDE_PX
        mean = cv2.blur(rows_for_opencv(rgb), (THIN_WINDOW_PX, THIN_WINDOW_PX))
        # OpenCV's 8-bit CIE Lab: its steps (0.4 in L, 1 in a and b) lie far below the contrasts sought;
        # it costs a tenth of the float conversion, and the window's means are integer sums (float
        # output), in 8-bit units until the difference is scaled to CIE units
        lab = cv2.cvtColor(np.ascontiguousarray(mean[::s, ::s]), cv2.COLOR_RGB2Lab)
        self.lab = lab.astype(np.float32)
        # as many samples a side as span the window with their own means' reach
        samples = (_odd((window_px - THIN_WINDOW_PX) / s + 1),) * 2
        self.least_sq = least_sq
        plain = cv2.boxFilter(lab, cv2.CV_32F, samples)
        differs = self._distance(self.lab, plain) >= least_sq
        # The window's mean again without the samples that differ from it (where the whole window
        # differs, inside a large object, the plain mean).
        kept = lab.copy()
        kept[differs] = 0
        share = cv2.boxFilter((~differs).view(np.uint8), cv2.CV_32F, samples)
        self.around = np.empty_like(plain)
        share_mean_kernel(cv2.boxFilter(kept, cv2.CV_32F, samples), share, plain, self.around)
        self.found = self._distance(self.lab, self.around) >= least_sq
        self.shape = rgb.shape[:2]

    @staticmethod
    def _distance(lab: np.ndarray, around: np.ndarray) -> np.ndarray:
        """Squared CIE76 distance (H, W) between ``lab`` and ``around`` (8-bit Lab units, float32 (H, W, 3))."""
        out = np.empty(lab.shape[:2], np.float32)
        colour_distance_kernel(lab, around, _LAB8_UNITS, out)
        return out

    def candidates(
        self, where: np.ndarray, *, least_px: float
    ) -> list[tuple[tuple[slice, slice], np.ndarray]]:
        """Where to test pixel by pixel: the samples whose colour differs from the surface around them
        by a squared CIE76 distance of at least ``least_sq``, with their neighbours (a thin object is
        found whole, though some of its samples fall on its outline and miss), on ``where`` (bool
        (H, W)), in connected regions (8-connected) of at least ``least_px`` pixels (a sample stands
        for ``COLOUR_STRIDE_PX`` squared). Each as the box of its pixels and of those their means
        reach (rows, columns) and which pixels of the box are its own (their nearest sample is):
        bool (H', W')."""
        s = COLOUR_STRIDE_PX
        grown = (cv2.dilate(self.found.view(np.uint8), np.ones((3, 3), np.uint8)) > 0) & where[::s, ::s]
        n, labels, stats = label_regions(grown)
        out = []
        for k in np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] * s * s >= least_px) + 1:
            x, y, w, h = stats[k, :4]
            # pixel p's nearest sample is (p + s // 2) // s: the samples first .. last are nearest to
            # the pixels s * first - s // 2 .. s * (last + 1) - s // 2 - 1; and the box holds the
            # pixels their means reach
            reach = THIN_WINDOW_PX // 2
            box = tuple(
                slice(max(s * start - s // 2 - reach, 0), min(s * (start + size) - s // 2 + reach, limit))
                for start, size, limit in ((y, h, self.shape[0]), (x, w, self.shape[1]))
            )
            rows, cols = (
                np.minimum((np.arange(b.start, b.stop) + s // 2) // s, n_samples - 1)
                for b, n_samples in zip(box, labels.shape)
            )
            # labels[rows[:, None], cols[None, :]] == k, each sample's row and column repeated as
            # often as it is the nearest (rows and cols do not decrease)
            mine = labels[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1] == k
            out.append(
                (
                    box,
                    np.repeat(
                        np.repeat(mine, np.bincount(rows - rows[0]), axis=0),
                        np.bincount(cols - cols[0]),
                        axis=1,
                    ),
                )
            )
        return out

    def pixels_distinct(self, rgb: np.ndarray, within: tuple[slice, slice]) -> np.ndarray:
        """The test for each pixel of ``rgb``, the crop ``within`` of the image (H', W', 3): its own
        colour, averaged over THIN_WINDOW_PX squared pixels (the crop's edge repeated), against the
        surface around it, interpolated between the samples; and, on the outline of what differs,
        at least half as far from it as its neighbours' farthest (a window astride an object's
        outline takes a part of its colour: the object ends where its colour is half-way).
        bool (H', W')."""
        lab = cv2.cvtColor(rows_for_opencv(rgb), cv2.COLOR_RGB2Lab)
        lab = cv2.boxFilter(lab, cv2.CV_32F, (THIN_WINDOW_PX, THIN_WINDOW_PX))
        # sample i lies at pixel COLOUR_STRIDE_PX * i: the crop's pixel (x, y) at sample
        # ((x + first column) / stride, (y + first row) / stride), linearly interpolated
        s = COLOUR_STRIDE_PX
        to_samples = np.array([[1 / s, 0, within[1].start / s], [0, 1 / s, within[0].start / s]])
        around = cv2.warpAffine(
            self.around,
            to_samples,
            (lab.shape[1], lab.shape[0]),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REPLICATE,
        )
        d2 = self._distance(lab, around)
        found = d2 >= self.least_sq
        square = np.ones((3, 3), np.uint8)
        outline = cv2.erode(found.view(np.uint8), square) == 0
        return found & ~(outline & (4 * d2 < cv2.dilate(d2, square)))


# CIE units per unit of OpenCV's 8-bit Lab (L scaled by 255 / 100; a and b offset by 128, which
# differences cancel)
_LAB8_UNITS = np.array([100.0 / 255.0, 1.0, 1.0], np.float32)


def _odd(px: float) -> int:
    """``px`` rounded up to an odd whole number of pixels, at least 1."""
    return max(int(np.ceil(px)) // 2 * 2 + 1, 1)


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
    m = as_uint8(mask)
    if open_px:
        kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * open_px + 1, 2 * open_px + 1))
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, kernel)
    _, labels, stats, box = label_box(m)
    min_area = max(1, int(np.ceil(min_area_fraction * m.size)))
    keep = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= min_area) + 1
    keep = keep[np.argsort(-stats[keep, cv2.CC_STAT_AREA], kind="stable")]  # ties: the lower label first
    return [region_mask(k, labels, stats, box, m.shape) for k in keep]


# Thin objects lying flat are sought in the height above the plane averaged over squares of this many
# pixels a side (a third of a single reading's noise): an object is a region, not a pixel.
THIN_WINDOW_PX = 3
# Objects lying flat are sought by colour on every this-many-th pixel in x and y first, then pixel by
# pixel near what these samples find.
COLOUR_STRIDE_PX = 2
# The surface around an object lying flat, whose colour it is told from: a square this wide at the
# table's depth (wider than a ruler or a blade of scissors).
THIN_CONTEXT_M = 0.05
# An object lying flat is surrounded by the table (or the hand holding it): at least this share of a
# ring around it.
ON_TABLE_SHARE = 0.75


class Scene(NamedTuple):
    """What depth alone tells of a frame (see :meth:`MaskFreeSegmenter.scene`)."""

    planes: list[Plane]  # the background planes, the support plane first
    background: np.ndarray  # bool (H, W): see :func:`.support.background_mask`
    valid: np.ndarray  # bool (H, W): pixels with a depth reading
    depth_m: np.ndarray  # float32 (H, W), metres, 0 = no reading (:func:`.support.clean_depth`)
    heights_m: list[np.ndarray]  # float32 (H, W) per plane, metres: :func:`.support.plane_height_m`


class MaskFreeSegmenter(InstanceSegmenter):
    """Base of the segmenters that find objects without given masks: the scene's background planes
    from depth, and the hands (:mod:`.hands`) to leave out. ``Params`` include BackgroundParams and
    HandParams."""

    def __init__(self, params: SelectionParams | None = None):
        super().__init__(params)
        self._last = threading.local()  # each thread's last scene

    def scene(self, frame: Frame, *, sequence: Sequence) -> Scene:
        """The background planes of ``frame``, its background mask, its pixels with a reading (see
        :func:`.support.background_mask`), its clean depth and each plane's height above it; each
        thread keeps its last frame's, as hands and instances both need them. The planes are sought
        first where they lie in the sequence's first frame (see ``hints`` in
        :func:`.support.fit_planes`), so the result of a frame does not depend on which frames were
        segmented before it, nor on which thread segments it."""
        key = (str(sequence.path), sequence.name, frame.index)
        last = getattr(self._last, "scene", None)
        if last is None or last[0] != key:
            with self._lock:
                hints = self._first_planes(frame, sequence) if frame.index else None
            planes = fit_planes(frame.depth_m, sequence.intrinsics, params=self.params, hints=hints)
            depth = clean_depth(frame.depth_m)
            heights = [plane_height_m(depth, sequence.intrinsics, plane) for plane in planes]
            background, valid = background_mask(
                depth, sequence.intrinsics, planes, params=self.params, heights=heights
            )
            last = self._last.scene = (key, Scene(planes, background, valid, depth, heights))
        return last[1]

    def _first_planes(self, frame: Frame, sequence: Sequence) -> list[Plane]:
        """The background planes of the sequence's first frame (kept for the last sequence; call it
        with the lock held)."""
        key = (str(sequence.path), sequence.name)
        first = getattr(self, "_first_scene", None)
        if first is None or first[0] != key:
            first = self._first_scene = (
                key,
                fit_planes(sequence[0].depth_m, sequence.intrinsics, params=self.params),
            )
        return first[1]

    def hands(self, frame: Frame, *, sequence: Sequence) -> np.ndarray | None:
        if not self.params.exclude_hands:
            return None
        scene = self.scene(frame, sequence=sequence)
        return find_hands(
            frame,
            scene.background,
            sequence.intrinsics,
            params=self.params,
            sequence_path=sequence.path,
            support=scene.planes[0] if scene.planes else None,
            plane_distance_m=self.params.plane_distance_m,
            rig=sequence.meta,
            support_height_m=scene.heights_m[0] if scene.planes else None,
        )

    def covered(self, frame: Frame, *, sequence: Sequence) -> np.ndarray | None:
        """The hand's pixels, its margin included (None when hands are not looked for)."""
        hand = self.hand_mask(frame, sequence=sequence)
        return None if hand is None else widen(hand, self.params.hand_margin_px)


def without_arm(instances: list[np.ndarray], hand: np.ndarray, *, share: float) -> list[np.ndarray]:
    """``instances`` without the pieces of arm the hand mask missed (a fold or a shaded strip of a
    sleeve): an arm enters the picture at its border, so an instance that reaches the border and
    whose outline (away from the border) runs within ``BORDER_PX`` of ``hand`` for at least
    ``share`` of its length is arm. A held object touches the hand along a part of its outline."""
    if not share or not hand.any():
        return instances
    border = border_band(hand.shape)
    beside = widen(hand, BORDER_PX)
    out = []
    for mask in instances:
        outline = mask & ~(cv2.erode(as_uint8(mask), np.ones((3, 3), np.uint8)) > 0) & ~border
        if not (mask & border).any() or (outline & beside).sum() < share * max(outline.sum(), 1):
            out.append(mask)
    return out


def keep_within(
    instances: list[np.ndarray], allowed: np.ndarray | None, *, min_area_fraction: float
) -> list[np.ndarray]:
    """Each instance restricted to ``allowed`` (None = all); those left smaller than
    ``min_area_fraction`` of the image dropped, largest first."""
    if allowed is None:
        return instances
    least = max(1, int(np.ceil(min_area_fraction * allowed.size)))
    out = [m for m in (m & allowed for m in instances) if np.count_nonzero(m) >= least]
    return sorted(out, key=lambda m: -int(np.count_nonzero(m)))


class DepthThresholdSegmenter(MaskFreeSegmenter):
    """Objects standing out of the support plane and background, chosen by how they move."""

    name = "depth_threshold"
    description = (
        "depth range + background-plane removal + connected components, hands removed, moving instance chosen"
    )
    Params = DepthThresholdParams

    def instances(self, frame: Frame, *, sequence: Sequence) -> list[np.ndarray]:
        p, K = self.params, sequence.intrinsics
        planes, background, valid, depth, heights = self.scene(frame, sequence=sequence)
        covered = self.covered(frame, sequence=sequence)
        allowed = None if covered is None else ~covered
        objects = valid & ~background if allowed is None else valid & ~background & allowed
        found = components(objects, open_px=p.open_px, min_area_fraction=p.min_area_fraction)
        if p.grow_sigmas > 0:
            inside = range_mask(depth, near_m=p.near_m, far_m=p.far_m)  # shared by both calls
            low = background & above_planes(
                depth, K, planes, params=p, sigmas=p.grow_sigmas, heights=heights, inside=inside
            )
            low = low if allowed is None else low & allowed
            if p.thin_contrast > 0:
                flat = background & above_planes(
                    depth,
                    K,
                    planes,
                    params=p,
                    sigmas=p.grow_sigmas,
                    window_px=THIN_WINDOW_PX,
                    heights=heights,
                    inside=inside,
                )
                found += thin_objects(
                    flat if allowed is None else flat & allowed,
                    frame.rgb,
                    min_area_fraction=p.min_area_fraction,
                    contrast=p.thin_contrast,
                )
                if planes:
                    table = background & valid & (np.abs(heights[0]) < p.plane_distance_m)
                    found += colour_patches(
                        table if allowed is None else table & allowed,
                        frame.rgb,
                        heights[0],
                        surface=table if allowed is None else table | ~allowed,
                        noise_m=max(planes[0].noise_m, DEPTH_STEP_M),
                        sigmas=p.grow_sigmas,
                        contrast=p.thin_contrast,
                        min_area_fraction=p.min_area_fraction,
                        window_px=_odd(THIN_CONTEXT_M * K.fx / _table_depth(depth, table))
                        if table.any()
                        else 1,
                    )
            if found:
                found = grow(found, low)
        found = join_touching(found, depth, K, join_m=p.join_m)
        if allowed is not None:
            hand = self.hand_mask(frame, sequence=sequence)
            found = join_hidden(found, hand, depth, K, touch_m=p.hand_touch_m)
        found = fill_floors(found, depth, K, gap_m=p.plane_distance_m)
        found = fill_dropouts(found, valid, fill_px=p.fill_px)
        found = keep_within(found, allowed, min_area_fraction=p.min_area_fraction)
        return found if allowed is None else without_arm(found, ~allowed, share=p.arm_outline_share)
