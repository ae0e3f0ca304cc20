"""Hands and grippers: the pixels of a frame that handle the object and are not part of it.

Shared by the mask-free segmenters (``depth_threshold``, ``u2net``). A frame's *hand mask* is the
union of:

* **hands by skin colour and shape**: pixels in the explicit skin-colour box of Chai & Ngan (1999)
  in YCrCb (133 <= Cr <= 173, 77 <= Cb <= 127, 8-bit), that depth does not show to be background,
  grouped into connected regions that do not cross a depth step of more than ``hand_touch_m`` (a
  skin-coloured object behind the hand stays apart); a region is a hand when it reaches the image
  border (a hand is held out from an arm that enters the picture; a skin-coloured object in the
  scene seldom reaches it) and its surface, measured with depth, is at least ``hand_min_area_m2``
  (two fingers: specks and patches of skin colour on objects are smaller). A region held above the
  table also reaches the border through pixels without a reading that do, other than projector
  shadows (an arm nearer than the sensor's range). A hand ends where its colour does: the parts
  of its region whose chromaticity (normalised rgb) differs by more than ``hand_chroma`` from the
  skin where the arm holds it, and that rest on the support plane or are larger than a hand
  (``hand_max_area_m2``), are an object held there or carried (a wooden box, a cardboard case
  touched at the hand's own depth), not the hand (:func:`own_colour`);
* **arms and sleeves, whatever their colour**: a region standing out of the background that reaches
  the image border (or the pixels without a reading that do: a sleeve too near the sensor to be
  measured but for its rim), is not resting on the support plane (none of its pixels away from
  depth steps comes down to it: its lowest points stand off the plane by more than
  ``plane_distance_m`` plus the plane's noise and a pixel's size at their depth), and touches a
  hand-sized skin region in 3-D (a sleeve, a glove's cuff, the forearm of a robot arm), is an arm:
  it is removed with the hand, and the hand it holds reaches the border through it. An object that
  reaches the border while it lies on the table is kept;
* **pieces of the arm's surface that colour cut off**: a region standing out of the background, of
  neither colour, not resting on the support plane, whose outline runs next to the arm with no depth
  step (within ``hand_touch_m``) along at least ``arm_outline_share`` of its length, is the same
  surface as the arm (a lit facet of a sleeve whose shaded faces pass for skin) and joins it
  (:func:`arm_pieces`). The hand's pieces of another shade than its own, which may be an object it
  holds (a mug whose body passes for skin), are no arm to continue;
* **forearms by their shape, whatever their colour** (:mod:`.limbs`): a straight cylinder a
  forearm's width that enters the picture at its border, held above the table, traced from the
  border until it meets something wider (the hand, or what it holds or rests on), with the hand's
  reach beyond it;
* **the stretch of an arm that reads nothing** (too near the sensor, or too dark for it): pixels
  without a reading, in solid regions that reach the image border (not the projector's shadow, not
  the speckle of dropouts), of the hand's own colour where they meet it (chromaticity within
  ``hand_chroma``), joined to the hand (:func:`unread_arm`). A window beyond the sensor's range
  beside the arm is of another colour and stays out;
* **a gripper by colour**: the same rule for the pixels inside the HSV box ``gripper_hsv`` (or in
  any of its boxes, for a gripper of several colours), or, when that is not set, the boxes the
  sequence's own settings give as ``gripper_hsv`` (a robot rig knows its gripper: the native
  folder format reads it from ``meta.json``); its regions are found apart from the skin-coloured
  ones, so a wooden object the gripper holds does not join it, and they are
  cut along the projector's shadows too (:func:`projector_shadows`), so a dark object behind a
  finger does not join it through the shadow the finger casts. Its fingers, smaller than
  ``hand_min_area_m2`` and cut off from its body by a depth step or a shadow, join it when they touch
  it in 3-D and do not rest on the support plane;
* **given masks**: one PNG per frame in the folder ``hand_masks`` (a robot knows its own gripper),
  used as they are.

The hand mask is grown by ``hand_margin_px`` (its outline's mixed-colour pixels) and removed from
the objects before the handled one is chosen, so a hand alone is never the object; its pixels are
left out of the change score, so a hand waving in front of a still object does not make the object
move. An object that the hand touches in 3-D (object pixels next to hand pixels, within
``hand_touch_m`` of their depth, along a line of contact at least ``HOLD_LINE_M`` long, not a couple
of stray pixels, within ``HAND_LENGTH_M`` of the hand's tip: a hand holds with its palm and fingers,
and a lit strip of its own sleeve along the forearm is no object it holds) is *held*, and held
objects are preferred (:mod:`.selection`). An object seen on both sides of a hand passing in front
of it is one object (:func:`hidden`).

Notes
-----
The skin model is a fixed published rule, not fitted to any data here: D. Chai and K. N. Ngan,
"Face segmentation using skin-color map in videophone applications", IEEE Trans. Circuits and
Systems for Video Technology 9(4), 551-564, 1999. It ignores luminance, so it holds under most
lighting, and it is known to accept wood, cardboard and some orange and pink surfaces: that is why
only regions that reach the image border and stand out of the background planes count.
Normalised rgb does not change with shading on a matte surface, so the faces of a hand turned
towards or away from the light keep one chromaticity while another material changes it: T. Gevers
and A. W. M. Smeulders, "Color-based object recognition", Pattern Recognition 32(3), 453-464, 1999.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from artclass_core import Frame, InputError, Intrinsics, ParamError, Params, param

from ._compiled import border_reach, shadow_kernel, step_kernel
from .limbs import CONTACT_PX, limbs
from .support import (
    DEPTH_STEP_M,
    Plane,
    as_uint8,
    clean_depth,
    grown_box,
    label_box,
    plane_height_m,
    region_mask,
    rows_for_opencv,
)

__all__ = [
    "HandParams",
    "SKIN_CR",
    "SKIN_CB",
    "skin_mask",
    "hsv_mask",
    "parse_hsv",
    "gripper_boxes",
    "hand_regions",
    "held",
    "hand_tips",
    "hidden",
    "HOLD_LINE_M",
    "load_hand_mask",
    "find_hands",
    "widen",
    "depth_steps",
    "arms",
    "on_plane",
    "rests",
    "stands_on",
    "fingers",
    "arm_pieces",
    "pixels_across",
    "projector_shadows",
    "chromaticity",
    "own_colour",
    "surface_m2",
    "surfaces_m2",
]

# Chai & Ngan (1999): the skin-colour map in YCrCb, 8-bit (OpenCV's YCrCb has the same offsets).
SKIN_CR = (133, 173)
SKIN_CB = (77, 127)


HsvBox = tuple[tuple[int, int, int], tuple[int, int, int]]


def gripper_boxes(
    params: HandParams, rig: Mapping[str, Any], sequence_path: Path | str
) -> list[HsvBox] | None:
    """The gripper's HSV boxes: the parameter ``gripper_hsv`` when set, else the sequence's own
    ``gripper_hsv`` (``rig``: its settings, e.g. ``meta.json``), else None.

    Raises :class:`~artclass_core.InputError` naming the sequence when its value is not boxes.
    """
    if params.gripper_hsv.strip():
        return parse_hsv(params.gripper_hsv)
    return parse_hsv(str(rig.get("gripper_hsv") or ""), where=sequence_path)


def parse_hsv(text: str, *, where: Path | str | None = None) -> list[HsvBox] | None:
    """``"h0,s0,v0,h1,s1,v1"`` (OpenCV units: H 0-180, S and V 0-255), or several such boxes separated
    by ``;`` (a gripper of several colours: a grey body and black fingers), as a list of (low, high);
    None for ``""``.

    Raises :class:`~artclass_core.ParamError` naming ``gripper_hsv`` when a box is not six integers
    in range with low <= high, or :class:`~artclass_core.InputError` naming ``where`` when the text
    is a sequence's setting.
    """
    if not text.strip():
        return None
    boxes, highs = [], (180, 255, 255)
    for part in text.split(";"):
        try:
            v = [int(x) for x in part.replace(" ", "").split(",")]
        except ValueError:
            v = []
        in_range = len(v) == 6 and all(0 <= x <= highs[k % 3] for k, x in enumerate(v))
        if not in_range or any(v[k] > v[k + 3] for k in range(3)):
            message = (
                f"gripper_hsv = {text!r} is not 'h0,s0,v0,h1,s1,v1' (or several such boxes separated "
                "by ';') with 0 <= h <= 180, 0 <= s, v <= 255 and each low <= its high"
            )
            if where is not None:
                raise InputError(f"the sequence's {message}", path=where)
            raise ParamError(f"parameter {message}")
        boxes.append(((v[0], v[1], v[2]), (v[3], v[4], v[5])))
    return boxes


@dataclass(frozen=True)
class HandParams(Params):
    """Which pixels are a hand or gripper, removed from the objects (shared by the mask-free segmenters)."""

    exclude_hands: bool = param(
        True,
        help="Remove hands (skin colour, regions reaching the image border), the arms "
        "or sleeves that hold them (of any colour: entering from the border "
        "above the table), forearms by their shape (a cylinder 3-12 cm across "
        "entering the picture above the table, with the hand's reach beyond it) "
        "and the configured gripper from the objects, and prefer the object a "
        "hand holds; off = every region is an object candidate.",
    )
    hand_min_area_m2: float = param(
        0.003,
        unit="m^2",
        bounds=(0.0, 1.0),
        help="Skin- or gripper-coloured regions whose surface (seen from the camera, "
        "measured with depth) is smaller are not a hand: about two fingers, "
        "30 cm^2; patches of skin colour on objects are smaller.",
    )
    hand_max_area_m2: float = param(
        0.03,
        unit="m^2",
        bounds=(0.0, 1.0),
        help="No hand is larger, seen from the camera (an adult's, fingers spread, is "
        "about 200 cm^2): a part of a skin-coloured region, of another shade than "
        "where the arm holds it, that is larger, is an object the hand carries, "
        "even off the table. 0 = only objects resting on the table are told apart.",
    )
    hand_margin_px: int = param(
        2,
        unit="px",
        bounds=(0, 20),
        help="The hand mask grows by this radius before it is removed: the mixed-colour "
        "pixels of its outline.",
    )
    arm_outline_share: float = param(
        0.5,
        unit="fraction",
        bounds=(0.0, 1.0),
        help="An object candidate that reaches the image border and whose outline runs "
        "beside the hand for at least this share of its length is the rest of the arm "
        "(a fold or shaded strip of a sleeve), not an object; so is a piece of neither skin "
        "nor gripper colour, off the table, whose outline runs next to the arm with no depth "
        "step along this share of its length (a sleeve's lit facet). 0 = off.",
    )
    hand_touch_m: float = param(
        0.02,
        unit="m",
        bounds=(0.0, 0.5),
        help="An object whose pixels next to the hand, within 20 cm of the hand's tip, lie "
        "within this depth of the hand's is held (about a finger's thickness); held "
        "objects are chosen first. An arm joins a hand it comes this close to in 3-D.",
    )
    hand_chroma: float = param(
        0.02,
        unit="rgb/(r+g+b)",
        bounds=(0.0, 1.0),
        help="A hand's skin keeps the chromaticity (normalised rgb) of where its arm "
        "holds it within this distance: a held object of another shade of skin "
        "colour (wood, cardboard) that touches it at its depth keeps its pixels; "
        "shading does not change chromaticity. 0 = off.",
    )
    gripper_hsv: str = param(
        "",
        help="The gripper's colour as an HSV box 'h0,s0,v0,h1,s1,v1' in OpenCV units "
        "(H 0-180, S and V 0-255), e.g. '0,0,0,180,100,100' for a dark grey "
        "gripper, or several boxes separated by ';' for a gripper of several "
        "colours; its regions that reach the image border are removed like "
        "hands. Empty = the sequence's own gripper_hsv (meta.json), if any.",
    )
    hand_masks: str = param(
        "",
        help="Folder of hand or gripper masks, one PNG per frame named like the frame "
        "(non-zero = hand), relative to the sequence folder; added to the hand "
        "mask. Empty = none.",
    )

    def __post_init__(self):
        super().__post_init__()
        parse_hsv(self.gripper_hsv)


def _open(mask: np.ndarray) -> np.ndarray:
    """Opening with a 3x3 square: single-pixel specks and one-pixel bridges removed."""
    return cv2.morphologyEx(as_uint8(mask), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)) > 0


def skin_mask(rgb: np.ndarray) -> np.ndarray:
    """Pixels of skin colour by Chai & Ngan's YCrCb rule.

    Parameters
    ----------
    rgb : ndarray, shape (H, W, 3), uint8, RGB order

    Returns
    -------
    ndarray of bool, shape (H, W)
    """
    ycrcb = cv2.cvtColor(np.ascontiguousarray(rgb, dtype=np.uint8), cv2.COLOR_RGB2YCrCb)
    return cv2.inRange(ycrcb, (0, SKIN_CR[0], SKIN_CB[0]), (255, SKIN_CR[1], SKIN_CB[1])) > 0


def hsv_mask(rgb: np.ndarray, boxes: list[HsvBox]) -> np.ndarray:
    """Pixels whose OpenCV HSV (H 0-180, S and V 0-255) lies in any of the boxes (low, high): bool (H, W)."""
    hsv = cv2.cvtColor(np.ascontiguousarray(rgb, dtype=np.uint8), cv2.COLOR_RGB2HSV)
    return np.logical_or.reduce([cv2.inRange(hsv, low, high) > 0 for low, high in boxes])


def _at_border(stats: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Which regions (rows 1.. of OpenCV's component ``stats``) reach the image border: bool (n - 1,)."""
    x, y, bw, bh = (stats[1:, k] for k in range(4))
    return (x == 0) | (y == 0) | (x + bw == shape[1]) | (y + bh == shape[0])


def hand_regions(
    candidates: np.ndarray,
    depth_m: np.ndarray,
    intrinsics: Intrinsics,
    *,
    min_area_m2: float,
    border: bool = True,
) -> np.ndarray:
    """The connected regions (8-connected, after a 3x3 opening) of ``candidates`` that reach the image
    border (any region when ``border`` is False) and whose surface is at least ``min_area_m2``.

    Parameters
    ----------
    candidates : ndarray of bool, shape (H, W)
    depth_m : ndarray, shape (H, W), metres, 0 = no reading
    intrinsics : pinhole intrinsics of the image
    min_area_m2 : smallest surface, square metres: a pixel at depth z covers (z / fx) (z / fy); pixels
        without a reading count at their region's mean depth

    Returns
    -------
    ndarray of bool, shape (H, W)
    """
    out = np.zeros(candidates.shape, bool)
    for region in _hand_regions(candidates, depth_m, intrinsics, min_area_m2=min_area_m2, border=border):
        out |= region
    return out


def _hand_regions(
    candidates: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics, *, min_area_m2: float, border: bool
) -> list[np.ndarray]:
    """:func:`hand_regions`, each region apart (the connected regions of their union): list of bool
    (H, W)."""
    n, labels, stats, (rows, cols) = label_box(_open(candidates))
    if n < 2:
        return []
    reach = _at_border(stats, candidates.shape)
    kept = np.flatnonzero(reach if border else np.ones(n - 1, bool)) + 1
    if not len(kept):
        return []
    d = clean_depth(depth_m)
    # a region of n pixels covers at most n (z_max / fx) (z_max / fy), with a margin for rounding: the
    # smaller ones (specks of skin colour) need no surface
    least_px = min_area_m2 * intrinsics.fx * intrinsics.fy / (1.001 * max(float(d.max()), 1e-9) ** 2)
    kept = kept[stats[kept, cv2.CC_STAT_AREA] >= least_px]
    out = []
    for k in kept:
        x, y, w, h = stats[k, :4]
        box = np.s_[y : y + h, x : x + w]
        # the labels are those of the mask's bounding box, which starts at (rows.start, cols.start)
        region = labels[y - rows.start : y - rows.start + h, x - cols.start : x - cols.start + w] == k
        if surface_m2(region, d[box], intrinsics) >= min_area_m2:
            full = np.zeros(candidates.shape, bool)
            full[box] = region
            out.append(full)
    return out


def surface_m2(region: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics) -> float:
    """The surface (m^2) that the pixels ``region`` (bool (H, W)) cover seen from the camera: a pixel at
    depth z covers (z / fx) (z / fy); pixels without a reading count at the region's mean depth (0 when
    none has one)."""
    z = depth_m[region]
    z = z[z > 0]
    if not len(z):
        return 0.0
    return (float(np.sum(z * z)) + (np.count_nonzero(region) - len(z)) * float(z.mean()) ** 2) / (
        intrinsics.fx * intrinsics.fy
    )


def surfaces_m2(
    labels: np.ndarray, where: np.ndarray, n: int, depth_m: np.ndarray, intrinsics: Intrinsics
) -> np.ndarray:
    """:func:`surface_m2` of each region 0 .. n - 1 of ``labels`` (int (H, W)) among the pixels
    ``where`` (bool (H, W)), all in one pass: float (n,)."""
    z = depth_m[where].astype(np.float64)
    of, seen = labels[where], z > 0
    n_seen = np.bincount(of[seen], minlength=n)
    mean = np.bincount(of[seen], weights=z[seen], minlength=n) / np.maximum(n_seen, 1)
    total = (
        np.bincount(of[seen], weights=z[seen] ** 2, minlength=n)
        + (np.bincount(of, minlength=n) - n_seen) * mean**2
    )
    return total / (intrinsics.fx * intrinsics.fy)


def load_hand_mask(folder: Path, frame: Frame) -> np.ndarray:
    """The given hand mask of ``frame``: ``folder/<frame name>.png``, non-zero = hand. bool (H, W).

    Raises :class:`~artclass_core.InputError` naming the file when it is missing, unreadable or of
    another size than the frame.
    """
    path = folder / f"{frame.name}.png"
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_file() else None
    if image is None:
        raise InputError("hand mask missing or unreadable (hand_masks needs one PNG per frame)", path=path)
    if image.shape[:2] != frame.depth_m.shape[:2]:
        raise InputError(
            f"hand mask is {image.shape[1]}x{image.shape[0]}, the frame "
            f"{frame.depth_m.shape[1]}x{frame.depth_m.shape[0]}",
            path=path,
        )
    return (image.max(axis=2) if image.ndim == 3 else image) > 0


def find_hands(
    frame: Frame,
    background: np.ndarray,
    intrinsics: Intrinsics,
    *,
    params: HandParams,
    sequence_path: Path | str,
    support: Plane | None = None,
    plane_distance_m: float = 0.0,
    rig: Mapping[str, Any] | None = None,
    support_height_m: np.ndarray | None = None,
) -> np.ndarray:
    """The hand (and gripper) mask of a frame, with the arms that hold them (see the module
    docstring), not yet grown by its margin.

    Parameters
    ----------
    frame : the frame (``rgb`` (H, W, 3) uint8)
    background : ndarray of bool, shape (H, W) -- pixels depth shows to be background
    intrinsics : pinhole intrinsics of the frame
    params : the hand settings
    sequence_path : the sequence folder (``hand_masks`` is relative to it)
    support : the support plane (see :func:`.support.fit_planes`); None = no arm search
    plane_distance_m : metres -- the pixels nearer than this to a plane are background
    rig : the sequence's settings (``Sequence.meta``); its ``gripper_hsv`` is the gripper's colour
        when the parameter is not set
    support_height_m : ndarray, shape (H, W), metres, optional -- the support plane's
        :func:`.support.plane_height_m`, when already computed

    Returns
    -------
    ndarray of bool, shape (H, W); all False when ``exclude_hands`` is off
    """
    if not params.exclude_hands:
        return np.zeros(background.shape, bool)
    # skin and the gripper's colour are two kinds of evidence: their regions are found apart, so that a
    # skin-coloured object a gripper holds does not join it (a pixel of both colours is skin)
    kinds = [skin_mask(frame.rgb)]
    gripper = gripper_boxes(params, rig or {}, sequence_path)
    if gripper is not None:
        kinds.append(hsv_mask(frame.rgb, gripper) & ~kinds[0])
    candidates = np.logical_or.reduce(kinds) & ~background
    d, touch = clean_depth(frame.depth_m), params.hand_touch_m
    step = depth_steps(d, step_m=touch)
    if support is None:
        contact, limb = None, np.zeros(d.shape, bool)
    else:
        contact = on_plane(
            d, intrinsics, support, step=step, plane_distance_m=plane_distance_m, height_m=support_height_m
        )
        limb = limbs(~background & (d > 0), d, intrinsics, contact=contact)
    if not candidates.any():  # nothing skin- or gripper-coloured stands out of the background
        return _with_given(limb, frame, params=params, sequence_path=sequence_path)
    # cut along depth steps, so that a skin-coloured object behind the hand does not join it; then
    # give the hand back its side of the step (its outline). The gripper is cut along the projector's
    # shadows too (a dark object behind its finger does not join it through the shadow the finger
    # casts on it): the pieces of the gripper this cuts off rejoin it as its fingers; a hand's
    # pieces would not (a small skin-coloured object in the hand looks the same), so its shadows
    # stay joined
    shadow = projector_shadows(d, step_m=touch, fx=intrinsics.fx)
    apart = candidates & ~step
    found = [  # each kind's regions
        _hand_regions(
            kind & (apart & ~shadow if k else apart),
            d,
            intrinsics,
            min_area_m2=params.hand_min_area_m2,
            border=support is None,
        )
        for k, kind in enumerate(kinds)
    ]
    edge = None  # the pixels without a reading that reach the image border, once found
    if support is None:
        hand = np.zeros(d.shape, bool)
        for region in (r for regions in found for r in regions):
            hand |= region
    else:
        regions = [(k, r) for k, kind in enumerate(found) for r in kind]  # k: 0 skin, 1 gripper
        hand = np.zeros(d.shape, bool)
        # a skin-coloured object stands on the table; a hand that grasps something there only touches
        # it with its fingertips. A gripper is held out from above: a gripper-coloured region that
        # touches the table at all is an object lying there
        held_out = [r for k, r in regions if not (stands_on(r, contact, d) if k == 0 else rests(r, contact))]
        for _, r in regions:
            if r[0].any() or r[-1].any() or r[:, 0].any() or r[:, -1].any():
                hand |= r
        # an arm too near the sensor to be measured reaches the border through pixels without a
        # reading; so does a sleeve of which only the rim is measured
        edge = _edge_gaps(d, shadow) if held_out else None
        for r in held_out:
            if not hand[r].any() and _touches(r, edge):
                hand |= r
        arm = (
            arms(
                ~background & ~candidates & ~step & (d > 0),
                np.logical_or.reduce(held_out),
                d,
                intrinsics,
                contact=contact,
                touch_m=touch,
                edge=edge,
                skin=(hand & kinds[0], np.logical_or.reduce(held_out) & kinds[0]),
            )
            if held_out
            else hand
        )
        if arm.any():
            hand |= arm
            for r, on_arm in zip(held_out, _touching(held_out, arm, d, intrinsics, touch_m=touch)):
                if on_arm:  # held out by an arm
                    hand |= r
        if len(kinds) > 1 and hand.any():
            hand |= fingers(
                kinds[1] & candidates & ~step & ~shadow & ~hand,
                hand,
                d,
                intrinsics,
                contact=contact,
                touch_m=touch,
                max_area_m2=params.hand_min_area_m2,
            )
        skin = hand & kinds[0]
        doubtful = None  # pieces of the hand of another shade than its own: maybe an object it holds
        if params.hand_chroma > 0 and skin.any():
            carriers = hand & ~kinds[0]
            own, doubtful = own_colour(
                skin,
                carriers,
                frame.rgb,
                tolerance=params.hand_chroma,
                contact=contact,
                larger=(d, intrinsics, params.hand_max_area_m2),
            )
            hand = (hand & ~skin) | own
        if params.arm_outline_share > 0 and hand.any() and contact is not None:
            hand |= arm_pieces(
                ~background & ~candidates & ~step & (d > 0) & ~hand,
                hand if doubtful is None else hand & ~doubtful,
                d,
                contact=contact,
                touch_m=touch,
                share=params.arm_outline_share,
            )
    hand |= limb
    seen = hand & (d > 0)
    if seen.any():
        # the hand's side of the depth steps around its readings (on their box: none is farther)
        box = grown_box(seen, 1)
        near, far = _depth_range(d[box], hand[box], 1)
        hand[box] |= (
            ~background[box]
            & step[box]
            & (far > 0)
            & ((d[box] == 0) | ((d[box] >= near - touch) & (d[box] <= far + touch)))
        )
    if hand.any():
        # pixels without a reading are the hand's where a closing of the margin's radius puts them
        # inside it (dropouts on skin), not a band along its side (the sensor's shadow on the table)
        hand &= (d > 0) | close_gaps(hand & (d > 0), params.hand_margin_px)
        gaps = _edge_gaps(d, shadow) if edge is None else edge
        hand |= unread_arm(hand, gaps, frame.rgb, tolerance=params.hand_chroma)
    return _with_given(hand, frame, params=params, sequence_path=sequence_path)


def _with_given(
    hand: np.ndarray, frame: Frame, *, params: HandParams, sequence_path: Path | str
) -> np.ndarray:
    """``hand`` with the frame's given mask (``hand_masks``) added, when there is one."""
    if params.hand_masks:
        hand |= load_hand_mask(Path(sequence_path) / Path(params.hand_masks).expanduser(), frame)
    return hand


# An instance is held when the hand touches it along at least this length (a fingertip's touch): a
# couple of pixels where the hand passes close to a still object are no grasp.
HOLD_LINE_M = 0.005
# A hand holds with its palm and fingers: within this distance of its tip (an adult hand, wrist to
# fingertip, is 17-19 cm long). A hand's tip is read from its pixels within TIP_WINDOW_PX.
HAND_LENGTH_M = 0.2
TIP_WINDOW_PX = 5
# The lowest pixels of an object lying on the plane stand off it by the background cut, plus this many
# of the plane's noise sigmas and of the pixel's size at their depth (the object's next row up).
CONTACT_SIGMAS = 3.0
CONTACT_PIXELS = 2.0


def on_plane(
    depth_m: np.ndarray,
    intrinsics: Intrinsics,
    support: Plane,
    *,
    step: np.ndarray,
    plane_distance_m: float,
    height_m: np.ndarray | None = None,
) -> np.ndarray:
    """The pixels where what stands on the support plane comes down to it: within
    ``plane_distance_m + CONTACT_SIGMAS * noise + CONTACT_PIXELS * z / fx`` of the plane (the
    background cut, the plane's measured noise and a pixel's size at depth z), with a reading, off
    depth steps (``step``: the flying pixels between an arm and the table behind it are no contact).
    ``height_m``: the support plane's :func:`.support.plane_height_m`, when already computed.
    bool (H, W)."""
    height = plane_height_m(depth_m, intrinsics, support) if height_m is None else height_m
    return (
        (
            height
            < plane_distance_m
            + CONTACT_SIGMAS * max(support.noise_m, DEPTH_STEP_M)
            + CONTACT_PIXELS * depth_m / intrinsics.fx
        )
        & ~step
        & (depth_m > 0)
    )


def rests(region: np.ndarray, contact: np.ndarray) -> bool:
    """Whether ``region`` rests on the support plane: at least CONTACT_PX of its pixels on it
    (``contact``, from :func:`on_plane`): an object lying on the table shows its lower rows just above
    the background cut; an arm held over it does not."""
    return np.count_nonzero(region & contact) >= CONTACT_PX


# A region stands on the support plane when at least this share of its lower outline comes down to it.
STANDING_SHARE = 0.5


def stands_on(region: np.ndarray, contact: np.ndarray, depth_m: np.ndarray) -> bool:
    """Whether ``region`` (bool (H, W)) stands on the support plane: it :func:`rests` on it, and in at
    least STANDING_SHARE of its columns its lowest pixel with a reading (``depth_m`` > 0) is on it
    (``contact``). An object standing on a table meets it along the bottom of its outline; a hand
    held over the table that grasps something lying there touches it with its fingertips only."""
    seen = region & (depth_m > 0)
    columns = np.flatnonzero(seen.any(axis=0))
    if not rests(region, contact) or not len(columns):
        return False
    bottom = seen.shape[0] - 1 - np.argmax(seen[::-1, columns], axis=0)
    return float(np.mean(contact[bottom, columns])) >= STANDING_SHARE


def arms(
    foreground: np.ndarray,
    hands: np.ndarray,
    depth_m: np.ndarray,
    intrinsics: Intrinsics,
    *,
    contact: np.ndarray,
    touch_m: float,
    edge: np.ndarray | None = None,
    skin: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """The arms (sleeves) among the regions of ``foreground``: those that do not rest on the support
    plane, touch ``hands`` in 3-D, and reach the image border (or ``edge``, the pixels without a
    reading that do: an arm nearer than the sensor's range, of which only a rim farther away is
    measured). With ``skin``, also the sleeves between bare skin: a region that touches the arm found
    so far and skin held out beyond it (a hand) continues the arm to that hand when it is a stretch
    of forearm (:func:`forearm_between`), one region after another.

    Parameters
    ----------
    foreground : ndarray of bool, shape (H, W) -- pixels standing out of the background, not hand
        coloured, away from depth steps
    hands : ndarray of bool, shape (H, W) -- hand-sized skin (or gripper) regions held above the table
    depth_m : ndarray, shape (H, W), metres, 0 = no reading
    intrinsics : pinhole intrinsics of the image
    contact : ndarray of bool, shape (H, W) -- the pixels on the support plane (:func:`on_plane`)
    touch_m : metres -- how far an arm may be from the hand it joins, in depth and across the image
        (at the hand's median depth)
    edge : ndarray of bool, shape (H, W), optional -- the pixels without a reading connected to the
        image border (:func:`_edge_gaps`)
    skin : (ndarray of bool, ndarray of bool), shapes (H, W), optional -- the skin that reaches the
        border, and all the skin held out above the table

    Returns
    -------
    ndarray of bool, shape (H, W)
    """
    out = np.zeros(foreground.shape, bool)
    if not hands.any():
        return out
    n, labels, stats, box = label_box(_open(foreground))
    reach = np.concatenate([[False], _at_border(stats, foreground.shape)])
    if edge is not None:
        reach |= np.bincount(labels[widen(edge, 1)[box]], minlength=n) > 0
    free = np.bincount(labels[contact[box]], minlength=n) < CONTACT_PX  # as rests()
    free[0] = False

    def regions(which: np.ndarray) -> list[np.ndarray]:
        return [region_mask(k, labels, stats, box, foreground.shape) for k in np.flatnonzero(which)]

    reaching = regions(free & reach)
    for region, touches in zip(reaching, _touching(reaching, hands, depth_m, intrinsics, touch_m=touch_m)):
        if touches:
            out |= region
    if skin is None:
        return out
    # a sleeve between bare skin: a stretch of forearm from the arm found so far to a hand beyond it
    limb, bare = skin[0] | out, skin[1]
    between = regions(free & ~reach)
    while between:
        beyond = bare & ~limb
        on_limb = _touching(between, limb, depth_m, intrinsics, touch_m=touch_m)
        on_hand = _touching(between, beyond, depth_m, intrinsics, touch_m=touch_m)
        taken = [
            a and b and forearm_between(r, limb, beyond, depth_m, intrinsics)
            for r, a, b in zip(between, on_limb, on_hand)
        ]
        if not any(taken):
            break
        for region in (r for r, t in zip(between, taken) if t):
            out |= region
            limb |= region
        between = [r for r, t in zip(between, taken) if not t]
    return out


#: A forearm, bare or sleeved, is this wide (metres): from a slim wrist to a loose sleeve.
FOREARM_WIDTH_M = (0.04, 0.12)


def forearm_between(
    region: np.ndarray, limb: np.ndarray, hand: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics
) -> bool:
    """Whether ``region`` is a stretch of forearm from ``limb`` to ``hand`` (bool (H, W) each): as wide
    as a forearm across its length (:data:`FOREARM_WIDTH_M`: the spread of its 3-D points along their
    second axis; a band of width w spreads w / sqrt(12)), and touching the limb and the hand at its
    two ends (their contacts at least half its length apart along its first axis). A held object
    touching the fingers is wider than an arm, or touches the hand along its side."""
    ys, xs = np.nonzero(region & (depth_m > 0))
    if len(ys) < 10:
        return False
    z = depth_m[ys, xs]
    points = np.column_stack(
        [(xs - intrinsics.cx) * z / intrinsics.fx, (ys - intrinsics.cy) * z / intrinsics.fy, z]
    )
    spread, axes = np.linalg.eigh(np.cov(points.T))
    width = float(np.sqrt(12 * max(spread[1], 0.0)))
    if not FOREARM_WIDTH_M[0] <= width <= FOREARM_WIDTH_M[1]:
        return False
    along = (points - points.mean(axis=0)) @ axes[:, 2]
    near, far = widen(limb, 2)[ys, xs], widen(hand, 2)[ys, xs]
    if not near.any() or not far.any():
        return False
    return abs(float(along[far].mean() - along[near].mean())) >= 0.5 * float(np.ptp(along))


def arm_pieces(
    pieces: np.ndarray,
    arm: np.ndarray,
    depth_m: np.ndarray,
    *,
    contact: np.ndarray,
    touch_m: float,
    share: float,
) -> np.ndarray:
    """The pieces of the arm's surface that the colour rules cut off from it (a lit facet of a sleeve
    whose colour is neither the sleeve's nor skin): the regions of ``pieces`` (8-connected, after a
    3x3 opening) that do not rest on the support plane and whose outline is continuous with ``arm``
    along at least ``share`` of its length: an outline pixel next to (8-connected) a pixel of the
    arm, within ``touch_m`` in depth of the arm's readings there (no depth step between them: one
    surface). The pieces taken are arm too, for the pieces beside them (until none is added).

    Parameters
    ----------
    pieces : ndarray of bool, shape (H, W) -- pixels standing out of the background, away from depth
        steps, not hand or gripper coloured, not yet in the hand mask
    arm : ndarray of bool, shape (H, W) -- the hand mask found so far, without its pieces of another
        shade than the hand's own (:func:`own_colour`: they may be an object the hand holds)
    depth_m : ndarray, shape (H, W), metres, 0 = no reading
    contact : ndarray of bool, shape (H, W) -- the pixels on the support plane (:func:`on_plane`)
    touch_m : metres -- the largest depth difference across the shared outline
    share : fraction of a piece's outline that must be continuous with the arm

    Returns
    -------
    ndarray of bool, shape (H, W)

    Notes
    -----
    An arm is one connected surface; a held object is another body, seen beside the hand across a
    depth step (the fingers lie on it) or meeting it along a line of contact, not along most of its
    outline. Only the pixels next to the arm count, not those a couple of pixels away: an object's
    outline runs that close to the hand where the fingers hold it.
    """
    out = np.zeros(pieces.shape, bool)
    opened = _open(pieces)
    if not opened.any() or not arm.any():
        return out
    box = grown_box(opened, 1)  # every outline pixel's neighbours lie inside it
    n, labels = cv2.connectedComponents(opened[box].view(np.uint8), connectivity=8)
    inside = labels > 0
    # 8-connected regions never touch each other: the union's outline is each region's outline
    outline = inside & ~(cv2.erode(inside.view(np.uint8), np.ones((3, 3), np.uint8)) > 0)
    d, grown = depth_m[box], arm[box].copy()
    length = np.bincount(labels[outline], minlength=n)
    free = np.bincount(labels[inside & contact[box]], minlength=n) < CONTACT_PX  # as rests()
    free[0] = False
    taken = np.zeros(n, bool)
    while True:  # the pieces taken are arm too: a facet may continue one taken before
        near, far = _depth_range(d, grown, 1)
        joined = outline & (far > 0) & (d >= near - touch_m) & (d <= far + touch_m)
        along = np.bincount(labels[joined], minlength=n)
        new = free & ~taken & (along > 0) & (along >= share * length)
        if not new.any():
            break
        taken |= new
        grown |= new[labels]
    out[box] = taken[labels]
    return out


def fingers(
    pieces: np.ndarray,
    gripper: np.ndarray,
    depth_m: np.ndarray,
    intrinsics: Intrinsics,
    *,
    contact: np.ndarray,
    touch_m: float,
    max_area_m2: float,
) -> np.ndarray:
    """The gripper's fingers among the regions of ``pieces`` (8-connected, after a 3x3 opening): those
    smaller than ``max_area_m2`` (a hand-sized region has been judged on its own) that touch
    ``gripper`` in 3-D and do not rest on the support plane. A finger seen below the gripper's body
    is cut from it by a depth step, and it is too small to count as a gripper by itself.

    Parameters
    ----------
    pieces : ndarray of bool, shape (H, W) -- gripper-coloured pixels standing out of the background,
        away from depth steps, not yet in the hand mask
    gripper : ndarray of bool, shape (H, W) -- the gripper (and arm) found so far
    depth_m : ndarray, shape (H, W), metres, 0 = no reading
    intrinsics : pinhole intrinsics of the image
    contact : ndarray of bool, shape (H, W) -- the pixels on the support plane (:func:`on_plane`)
    touch_m : metres -- how far a finger may be from the gripper, in depth and across the image
    max_area_m2 : square metres -- the largest surface of a finger

    Returns
    -------
    ndarray of bool, shape (H, W)
    """
    regions = [r for r in _regions(_open(pieces)) if surface_m2(r, depth_m, intrinsics) < max_area_m2]
    out = np.zeros(pieces.shape, bool)
    for region, touches in zip(regions, _touching(regions, gripper, depth_m, intrinsics, touch_m=touch_m)):
        if touches and not rests(region, contact):
            out |= region
    return out


def _regions(mask: np.ndarray) -> list[np.ndarray]:
    """The connected regions (8-connected) of ``mask``: list of bool (H, W)."""
    n, labels, stats, box = label_box(mask)
    return [region_mask(k, labels, stats, box, mask.shape) for k in range(1, n)]


def _touching(
    regions: list[np.ndarray],
    other: np.ndarray,
    depth_m: np.ndarray,
    intrinsics: Intrinsics,
    *,
    touch_m: float,
) -> list[bool]:
    """Which ``regions`` come within ``touch_m`` of ``other`` in 3-D: in depth, and across the image at
    ``other``'s median depth, so across a gap of dropouts (sensors lose the rim of a sleeve's end and
    of a forearm seen edge-on)."""
    seen = other & (depth_m > 0)
    if not seen.any():
        return [False] * len(regions)
    reach_px = pixels_across(touch_m, intrinsics.fx, depth_m[seen])
    return held(regions, other, depth_m, touch_m=touch_m, reach_px=reach_px)


def pixels_across(distance_m: float, fx: float, depths_m: np.ndarray) -> int:
    """``distance_m`` across the image, in pixels (at least 1), at the median of ``depths_m`` (metres)."""
    return max(int(np.ceil(distance_m * fx / float(np.median(depths_m)))), 1)


#: The widest baseline between a structured-light or active-stereo sensor's camera and its projector
#: (or second camera), metres: 7.5 cm on a Kinect v1, 5 cm on a RealSense D400.
BASELINE_M = 0.1


def projector_shadows(depth_m: np.ndarray, *, step_m: float, fx: float) -> np.ndarray:
    """The pixels without a reading whose nearest readings to the left and to the right in their row
    differ by more than ``step_m``: the projector's shadow of a structured-light sensor (its projector
    sits beside the camera along x), which lies beside a depth edge on whatever is behind it and must
    not join the two sides. A shadow is as wide as the disparity its two sides differ by, at most
    :data:`BASELINE_M` ``fx`` (1 / z_near - 1 / z_far) pixels: a wider gap holds something the sensor
    does not read (a sleeve too near or too dark for it). bool (H, W)."""
    out = np.zeros(depth_m.shape, bool)
    depth = np.ascontiguousarray(depth_m, dtype=np.float32)
    shadow_kernel(depth, np.float32(step_m), np.float32(BASELINE_M * fx), out)
    return out


def chromaticity(rgb: np.ndarray, where: np.ndarray) -> np.ndarray:
    """Normalised rgb, (r, g, b) / (r + g + b), of the pixels ``where`` (bool (H, W)) of an 8-bit RGB
    image (H, W, 3), each averaged over its 3x3 neighbourhood first (the camera's noise divided by
    3): float32 (N, 3), in row-major order. Shading scales r, g and b alike and leaves it unchanged;
    a change of material does not."""
    c = cv2.blur(rows_for_opencv(rgb), (3, 3))[where].astype(np.float32)
    total = c[:, 0] + c[:, 1] + c[:, 2]  # whole numbers: exact
    return c / np.maximum(total, np.float32(1.0))[:, None]


# A hand's own colour is read from its pixels within SEED_PX of where its arm holds it, past the
# MIXED_PX of its outline whose colour is mixed with the arm's or the background's (the camera's blur,
# the 3x3 average, and the thin strips of mixed pixels along a sleeve's outline that look like skin).
SEED_PX = 8
MIXED_PX = 3


def own_colour(
    skin: np.ndarray,
    carriers: np.ndarray,
    rgb: np.ndarray,
    *,
    tolerance: float,
    contact: np.ndarray,
    larger: tuple[np.ndarray, Intrinsics, float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``skin`` without what a hand holds on the table or carries: in each connected region
    (8-connected) of ``skin``, the pixels whose :func:`chromaticity` lies farther than ``tolerance``
    from the median of its *seeds* (its pixels near the image border or near ``carriers``: where the
    arm holds it; more than MIXED_PX inside the region's outline) or that connect to the seeds only
    through those, form pieces; a piece that rests on the support plane (:func:`rests`) is an object
    the hand holds there, not the hand, and is removed; so is a piece whose :func:`surface_m2` is
    larger than a hand can be (``larger``: the depth, the intrinsics and that surface), a box the
    hand carries. A piece that is neither is kept (the hand, when the sleeve is skin-coloured too);
    so is a region without seeds.

    Parameters
    ----------
    skin : ndarray of bool, shape (H, W) -- the skin-coloured pixels of the hand mask
    carriers : ndarray of bool, shape (H, W) -- what holds the hand out: its arm and sleeve, as read
        (a band without a reading is not one: it is as often the shadow beside a box the hand holds)
    rgb : ndarray, shape (H, W, 3), uint8, RGB order
    tolerance : distance in normalised rgb; 0 = ``skin`` unchanged
    contact : ndarray of bool, shape (H, W) -- the pixels on the support plane (:func:`on_plane`)
    larger : (depth_m (H, W), intrinsics, max_area_m2), optional -- a piece whose surface exceeds
        ``max_area_m2`` (> 0) is removed off the table too

    Returns
    -------
    kept, other : ndarray of bool, shape (H, W) each -- the hand, and the pieces of another shade than
        their seeds that it keeps (the hand of a skin-coloured sleeve, or an object the hand carries:
        which, colour cannot tell)
    """
    kept_other = np.zeros(skin.shape, bool)
    if tolerance <= 0 or not skin.any():
        return skin, kept_other
    # the work is done on the skin's bounding box grown by SEED_PX
    box = rows, cols = grown_box(skin, SEED_PX)
    sk, held_by = skin[box], carriers[box]
    border = np.zeros(sk.shape, bool)  # the box's sides that are the image's
    border[0], border[-1] = rows.start == 0, rows.stop == skin.shape[0]
    border[:, 0] |= cols.start == 0
    border[:, -1] |= cols.stop == skin.shape[1]
    seeds = ~widen(~sk, MIXED_PX) & widen(held_by | border, SEED_PX) & ~widen(held_by, MIXED_PX)
    n, labels = cv2.connectedComponents(sk.view(np.uint8), connectivity=8)
    chroma, of, seed = chromaticity(rgb[box], sk), labels[sk], seeds[sk]  # of the skin pixels only
    out = skin.copy()
    for k in np.unique(labels[seeds]):
        region = labels == k
        mine = of == k
        ref = np.median(chroma[mine & seed], axis=0)
        own = np.zeros(sk.shape, bool)
        own[sk] = mine & (_squared_norms(chroma - ref) <= tolerance * tolerance)
        count, parts = cv2.connectedComponents(own.view(np.uint8), connectivity=8)
        seeded = np.zeros(count, bool)  # the parts of its own colour that hold seeds
        seeded[parts[own & seeds]] = True
        other = region & ~seeded[parts]
        m, pieces = cv2.connectedComponents(other.view(np.uint8), connectivity=8)
        gone = np.bincount(pieces[other & contact[box]], minlength=m) >= CONTACT_PX  # as rests()
        if larger is not None and larger[2] > 0:
            depth, intrinsics, most = larger
            gone |= surfaces_m2(pieces, other, m, depth[box], intrinsics) > most
        gone[0] = False
        out[box] &= ~gone[pieces]
        kept_other[box] |= other & ~gone[pieces]
    return out, kept_other


def _squared_norms(v: np.ndarray) -> np.ndarray:
    """``np.sum(v ** 2, axis=1)`` of ``v`` (N, 3), the same sums ((x + y) + z) from its columns, a
    fraction of the time of a reduction over a short axis."""
    sq = v * v
    return sq[:, 0] + sq[:, 1] + sq[:, 2]


def unread_arm(hand: np.ndarray, gaps: np.ndarray, rgb: np.ndarray, *, tolerance: float) -> np.ndarray:
    """The stretch of the arm that reads nothing (too near the sensor, or too dark for it), bool (H, W):
    in each solid region of ``gaps`` (the pixels without a reading that reach the image border, other
    than the projector's shadow: :func:`_edge_gaps`; opened by a disc of ``MIXED_PX``, so not the
    speckle of dropouts) that touches ``hand``, the pixels whose :func:`chromaticity` lies within
    ``tolerance`` of the median of the hand's where they meet (past its mixed outline when it has
    pixels there), connected to the hand."""
    out = np.zeros(hand.shape, bool)
    gaps, beside = gaps & ~hand, widen(hand, 1)
    if tolerance <= 0 or not (gaps & beside).any():
        return out
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * MIXED_PX + 1,) * 2)
    _, parts = cv2.connectedComponents(cv2.morphologyEx(as_uint8(gaps), cv2.MORPH_OPEN, disc), connectivity=8)
    inner = hand & ~widen(~hand, MIXED_PX)
    for k in np.unique(parts[beside & (parts > 0)]):
        gap = parts == k
        box = grown_box(gap, 2 * MIXED_PX + 1)  # all that follows looks at, with its 3x3 colour average
        gap, near = gap[box], widen(gap[box], 2 * MIXED_PX)
        meet = inner[box] & near if (inner[box] & near).any() else hand[box] & near
        alike = np.zeros(gap.shape, bool)
        alike[gap] = (
            _squared_norms(chromaticity(rgb[box], gap) - np.median(chromaticity(rgb[box], meet), axis=0))
            <= tolerance**2
        )
        n, pieces = cv2.connectedComponents(as_uint8(alike), connectivity=8)
        joined = np.zeros(n, bool)
        joined[pieces[beside[box] & alike]] = True  # never the background: alike is False there
        out[box] |= joined[pieces]
    return out


def _edge_gaps(depth_m: np.ndarray, shadow: np.ndarray) -> np.ndarray:
    """The pixels without a reading, other than ``shadow``, connected (8-connected) to the image
    border: where an arm nearer than the sensor's range leaves the picture. bool (H, W)."""
    out = np.zeros(depth_m.shape, bool)
    border_reach((depth_m == 0) & ~shadow, out)
    return out


def _touches(region: np.ndarray, other: np.ndarray | None) -> bool:
    """Whether ``region`` has a pixel next to (8-connected) one of ``other``."""
    return other is not None and bool(np.any(other & widen(region, 1)))


def _depth_range(d: np.ndarray, where: np.ndarray, reach_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Nearest and farthest reading of ``d`` (0 = none) among the pixels ``where``, in the square of
    half-width ``reach_px`` around each pixel; +inf and 0 where there is none. float32 (H, W) each.
    The minimum and maximum filters run on the bounding box of those readings grown by ``reach_px``
    only: outside it there is none within reach."""
    d = d.astype(np.float32, copy=False)
    seen = where & (d > 0)
    near = np.full(d.shape, np.inf, np.float32)
    far = np.zeros(d.shape, np.float32)
    if not seen.any():
        return near, far
    box = grown_box(seen, reach_px)
    kernel = np.ones((2 * reach_px + 1, 2 * reach_px + 1), np.uint8)
    crop, dc = seen[box], d[box]
    near[box] = cv2.erode(np.where(crop, dc, np.float32(np.inf)), kernel, borderValue=np.inf)
    far[box] = cv2.dilate(np.where(crop, dc, np.float32(0)), kernel, borderValue=0)
    return near, far


def depth_steps(depth_m: np.ndarray, *, step_m: float) -> np.ndarray:
    """The pixels whose 3x3 neighbourhood holds readings (``depth_m`` > 0, float32 (H, W)) more than
    ``step_m`` apart: bool (H, W). Pixels without a reading count when their neighbours' do."""
    out = np.zeros(depth_m.shape, bool)
    step_kernel(np.ascontiguousarray(depth_m, dtype=np.float32), np.float32(step_m), out)
    return out


def close_gaps(mask: np.ndarray, radius_px: int) -> np.ndarray:
    """``mask`` closed by a disc of ``radius_px`` (its gaps narrower than the disc filled): bool (H, W)."""
    if not radius_px or not mask.any():
        return mask
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))
    return cv2.morphologyEx(as_uint8(mask), cv2.MORPH_CLOSE, disc) > 0


def widen(mask: np.ndarray, radius_px: int) -> np.ndarray:
    """``mask`` dilated by a disc of ``radius_px`` (no copy when 0 or empty): bool (H, W)."""
    if not radius_px or not mask.any():
        return mask
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))
    return cv2.dilate(as_uint8(mask), disc) > 0


def held(
    instances: list[np.ndarray],
    hand: np.ndarray,
    depth_m: np.ndarray,
    *,
    touch_m: float,
    reach_px: int = 1,
    line_m: float = 0.0,
    fx: float = 0.0,
    intrinsics: Intrinsics | None = None,
) -> list[bool]:
    """Which instances the hand touches in 3-D: instance pixels within ``reach_px`` (a square) of
    hand pixels, whose depth lies within ``touch_m`` of the range of their depths, along a line of
    contact at least ``line_m`` long. With ``intrinsics``, only the touching pixels within
    ``HAND_LENGTH_M`` in 3-D of the hand's tip count (:func:`hand_tips`): a hand holds with its
    palm and fingers, and a piece of its own sleeve along the forearm is not held.

    Parameters
    ----------
    instances : list of ndarray of bool, shape (H, W)
    hand : ndarray of bool, shape (H, W) -- before any margin is added (its own depths)
    depth_m : ndarray, shape (H, W), metres, 0 = no reading
    touch_m : depth tolerance, metres
    reach_px : how far from the hand an object pixel may be (the margin removed with the hand, + 1)
    line_m : metres -- the shortest line of contact: the touching pixels, a band ``reach_px`` wide
        along the hand, must cover at least ``reach_px * line_m * fx / z`` pixels (z: their median
        depth); 0 = any touching pixel
    fx : focal length, pixels (needed when ``line_m`` > 0)
    intrinsics : pinhole intrinsics, optional -- to measure the distance to the hand's tip

    Returns
    -------
    list of bool, one per instance
    """
    return _along_hand(
        instances,
        hand,
        depth_m,
        touch_m=touch_m,
        reach_px=reach_px,
        line_m=line_m,
        fx=fx,
        behind=False,
        intrinsics=intrinsics,
    )


def hand_tips(hand: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """The tips of the hand mask's connected regions (8-connected) that reach the image border: for
    each, its pixel farthest across the image from the mean of its pixels on the border (where the
    arm enters the picture), in 3-D at the median depth of the region's readings within
    ``TIP_WINDOW_PX`` of it. Returns the tips (N, 3), metres, and the regions that do not reach the
    border or have no reading near their tip (bool (H, W)): an arm that enters through pixels
    without a reading, whose tip is unknown.
    """
    tipless = hand.copy()
    if not hand.any():
        return np.zeros((0, 3)), tipless
    rows, cols = grown_box(hand, 0)  # the work is done on the hand's bounding box
    _, labels = cv2.connectedComponents(as_uint8(hand[rows, cols]), connectivity=8)
    depth = depth_m[rows, cols]
    h, w = hand.shape
    # the box's sides that are the image's
    sides = [labels[0]] * (rows.start == 0) + [labels[-1]] * (rows.stop == h)
    sides += [labels[:, 0]] * (cols.start == 0) + [labels[:, -1]] * (cols.stop == w)
    on_border = np.concatenate(sides) if sides else np.zeros(0, labels.dtype)
    tips = []
    for k in np.unique(on_border[on_border > 0]):
        mine = labels == k
        v, u = np.nonzero(mine)
        iv, iu = v + rows.start, u + cols.start  # in the image
        entry = (iv == 0) | (iv == h - 1) | (iu == 0) | (iu == w - 1)
        far = int(np.argmax((v - v[entry].mean()) ** 2 + (u - u[entry].mean()) ** 2))
        r = TIP_WINDOW_PX
        win = slice(max(v[far] - r, 0), v[far] + r + 1), slice(max(u[far] - r, 0), u[far] + r + 1)
        z = depth[win][mine[win] & (depth[win] > 0)]
        if len(z):
            tips.append(intrinsics.points(iu[far : far + 1], iv[far : far + 1], np.array([np.median(z)]))[0])
            tipless[rows, cols] &= ~mine
    return np.array(tips, dtype=np.float64).reshape(-1, 3), tipless


def hidden(
    instances: list[np.ndarray],
    hand: np.ndarray,
    depth_m: np.ndarray,
    *,
    touch_m: float,
    line_m: float,
    fx: float,
) -> list[bool]:
    """Which instances the hand hides in part: at least ``line_m * fx / z`` of their pixels (a line
    ``line_m`` long at their median depth z) lie within ``touch_m`` of the hand across the image (at
    the hand's median depth: across the projector's shadow the hand casts on them) and farther than
    ``touch_m`` behind its nearest reading there. The parameters are those of :func:`held`.
    list of bool."""
    seen = hand & (depth_m > 0)
    if not seen.any():
        return [False] * len(instances)
    reach_px = pixels_across(touch_m, fx, depth_m[seen])
    return _along_hand(
        instances,
        hand,
        depth_m,
        touch_m=touch_m,
        reach_px=reach_px,
        line_m=line_m / reach_px,
        fx=fx,
        behind=True,
    )


def _along_hand(
    instances: list[np.ndarray],
    hand: np.ndarray,
    depth_m: np.ndarray,
    *,
    touch_m: float,
    reach_px: int,
    line_m: float,
    fx: float,
    behind: bool,
    intrinsics: Intrinsics | None = None,
) -> list[bool]:
    """:func:`held` (``behind`` False) or :func:`hidden` (True)."""
    if not hand.any() or not instances:
        return [False] * len(instances)
    d = clean_depth(depth_m)
    seen = hand & (d > 0)
    if not seen.any():
        return [False] * len(instances)
    # no pixel farther than reach_px from the hand's readings is along it: the work is done on their
    # bounding box grown by reach_px
    box = grown_box(seen, reach_px)
    whole_d, whole_hand = d, hand
    d, hand = d[box], hand[box]
    near, far = _depth_range(d, hand, reach_px)  # of the hand's readings around each pixel
    if behind:
        along = (d > 0) & ~hand & (d > near + touch_m) & (far > 0)
    else:
        along = (d > 0) & ~hand & (d >= near - touch_m) & (d <= far + touch_m)
    if intrinsics is not None:  # the instances' pixels near the hand's tip, or beside a tipless region
        along &= np.logical_or.reduce([m[box] for m in instances])
    if intrinsics is not None and along.any():  # the tips are found only when something touches
        tips, tipless = hand_tips(whole_hand, whole_d, intrinsics)
        v, u = np.nonzero(along)
        v, u = v + box[0].start, u + box[1].start
        points = intrinsics.points(u, v, d[along].astype(np.float64))
        ok = np.zeros(len(points), bool)
        for tip in tips:
            ok |= _squared_norms(points - tip) <= HAND_LENGTH_M**2
        ok |= widen(tipless, reach_px)[v, u]
        along[along] = ok
    out = []
    for m in instances:
        line = m[box] & along
        n = np.count_nonzero(line)
        least = reach_px * line_m * fx / float(np.median(d[line])) if n and line_m > 0 else 1
        out.append(bool(n) and n >= least)
    return out
