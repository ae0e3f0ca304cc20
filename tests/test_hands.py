"""Hands and grippers in the mask-free segmenters: the skin-colour model, hand regions, given hand
masks, the gripper colour, the held object, and whole sequences of a drawn scene (a table, a box on
it, a hand with its forearm entering from the image border) with known hand and object masks.

The scenes are drawn here, not taken from the synthetic generator: a table seen from 0.5 m above
by a camera pitched 40 degrees down, a wall behind it, a blue box 5 cm proud of the table, and a
skin-coloured hand (palm, four fingers, thumb, forearm) at its own depth, with colour and 1 mm depth
noise. The skin colours are typical light and dark skin tones, chosen before the model was applied.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from test_onnx_segmenters import u2netp_path  # noqa: F401 (the real u2netp weights, a fixture)

from artclass_core import Config, Frame, InputError, Intrinsics, ParamError, Pipeline, Sequence, load_registry
from artclass_plugins.segmenters.depth_threshold import (
    DepthThresholdParams,
    DepthThresholdSegmenter,
    join_hidden,
)
from artclass_plugins.segmenters.hands import (
    HandParams,
    _depth_range,
    _squared_norms,
    arm_pieces,
    arms,
    chromaticity,
    depth_steps,
    find_hands,
    forearm_between,
    hand_regions,
    hand_tips,
    held,
    hsv_mask,
    on_plane,
    own_colour,
    parse_hsv,
    projector_shadows,
    skin_mask,
    surface_m2,
    surfaces_m2,
)
from artclass_plugins.segmenters.selection import mask_iou
from artclass_plugins.segmenters.support import Plane, background_mask, fit_planes
from artclass_plugins.segmenters.u2net import U2netParams, U2netSegmenter

W, H = 320, 240
INTR = Intrinsics(fx=300.0, fy=300.0, cx=159.5, cy=119.5, width=W, height=H)
PITCH = np.radians(40.0)
UP = np.array([0.0, -np.cos(PITCH), -np.sin(PITCH)])  # the table's normal, towards the camera
LIGHT_SKIN, DARK_SKIN = (224, 172, 140), (141, 85, 36)
FINGER_M, FOREARM_M = 0.015, 0.06  # thickness of fingers lying flat, of a forearm
TABLE, WALL, BOX, GRIPPER = (160, 165, 170), (225, 228, 230), (50, 70, 150), (60, 62, 66)
SLEEVE = (45, 110, 60)  # a green sleeve: not skin, not the box


def table_depth(height_m: np.ndarray | float = 0.0) -> np.ndarray:
    """A table 0.5 m below the camera, cut off by a wall at 1.2 m: depth (H, W), metres, of the points
    ``height_m`` (scalar or (H, W)) above the table along each pixel's ray."""
    v = np.mgrid[0:H, 0:W][0].astype(np.float64)
    denom = -(UP[1] * (v - INTR.cy) / INTR.fy + UP[2])
    with np.errstate(divide="ignore"):
        z = np.where(denom > 1e-6, (0.5 - np.asarray(height_m)) / denom, np.inf)
    return np.minimum(z, 1.2)


def hand_shape(x: int, y: int, *, scale: float = 1.0, side: str = "right") -> np.ndarray:
    """A hand seen from above, palm centre (x, y), fingers pointing away from ``side`` of the image,
    forearm reaching that side's border: bool (H, W)."""
    m = np.zeros((H, W), np.uint8)
    s = scale
    sign = -1 if side == "right" else 1  # fingers point left for a right-side arm
    cv2.ellipse(m, (x, y), (int(22 * s), int(18 * s)), 0, 0, 360, 1, -1)
    for k, dy in enumerate((-13, -4, 5, 13)):  # four fingers
        length = int((30 - 4 * abs(k - 1.5)) * s)
        cv2.line(
            m,
            (x + sign * int(18 * s), y + int(dy * s)),
            (x + sign * (int(18 * s) + length), y + int(dy * s)),
            1,
            max(2, int(7 * s)),
        )
    cv2.line(
        m, (x, y - int(15 * s)), (x + sign * int(14 * s), y - int(38 * s)), 1, max(2, int(8 * s))
    )  # thumb
    edge = W - 1 if side == "right" else 0
    cv2.line(m, (x, y), (edge, y + int(25 * s)), 1, int(30 * s))  # forearm
    return m > 0


def box_mask(x: int, y: int, w: int = 60, h: int = 45) -> np.ndarray:
    m = np.zeros((H, W), bool)
    m[y : y + h, x : x + w] = True
    return m


def render(
    box: np.ndarray,
    hand: np.ndarray | None,
    *,
    hand_depth_m: float | None,
    skin=LIGHT_SKIN,
    hand_colour=None,
    seed: int = 0,
    sleeve: np.ndarray | None = None,
    depth: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Colour and depth of the scene. ``hand_depth_m`` None: the hand lies on what is under it (holding it).
    ``sleeve``: the part of the hand coloured SLEEVE. ``depth``: the scene's depth with the box in it
    (default: the table, with the box 5 cm nearer along the rays)."""
    rng = np.random.default_rng(seed)
    if depth is None:
        depth = table_depth()
        depth[box] -= 0.05
    else:
        depth = depth.copy()
    rgb = np.empty((H, W, 3), np.float64)
    rgb[:] = TABLE
    rgb[depth >= 1.2] = WALL
    rgb[box] = BOX
    if hand is not None:
        if hand_depth_m is None:  # fingers lying on the box, the wrist and forearm raised off the table
            depth[hand] -= np.where(box[hand], FINGER_M, FOREARM_M)
        else:
            depth[hand] = hand_depth_m
        rgb[hand] = hand_colour or skin
        if sleeve is not None:
            rgb[sleeve] = SLEEVE
        shade = 0.85 + 0.15 * np.linspace(0, 1, W)[None, :]  # light falls off across the hand
        rgb[hand] *= np.broadcast_to(shade, (H, W))[hand][:, None]
    rgb += rng.normal(0, 4, rgb.shape)
    depth = np.round(depth + rng.normal(0, 0.001, depth.shape), 3)  # millimetre steps, as sensors store
    return np.clip(rgb, 0, 255).astype(np.uint8), depth.astype(np.float32)


def paint(rgb: np.ndarray, where: np.ndarray, colour, *, seed: int) -> None:
    """Colour the pixels ``where`` of ``rgb`` (uint8 (H, W, 3)) ``colour`` with the camera's noise."""
    noisy = np.array(colour) + np.random.default_rng(seed).normal(0, 4, (np.count_nonzero(where), 3))
    rgb[where] = np.clip(noisy, 0, 255)


class Scene(Sequence):
    def __init__(self, frames: list[Frame], *, name: str, path: str | Path = "/in-memory/hands"):
        super().__init__(name=name, path=path, intrinsics=INTR, n_frames=len(frames))
        self._frames = frames

    def load(self, i: int) -> Frame:
        return self._frames[i]


def waving_scene(n: int = 10, **kw) -> tuple[Scene, np.ndarray, list[np.ndarray]]:
    """A still box with a hand waving 5-10 cm in front of it (not touching): the box, the hands."""
    box = box_mask(130, 130)
    frames, hands = [], []
    for i in range(n):
        hand = hand_shape(200 - 6 * i, 110 + 4 * (i % 3))
        rgb, depth = render(box, hand, hand_depth_m=0.55, seed=i, **kw)
        frames.append(Frame(i, f"{i:06d}", rgb, depth))
        hands.append(hand)
    return Scene(frames, name=f"waving-{n}"), box, hands


def carrying_scene(n: int = 10) -> tuple[Scene, list[np.ndarray], list[np.ndarray]]:
    """The hand lies on the box and slides it 4 px a frame across the table: the boxes, the hands."""
    frames, boxes, hands = [], [], []
    for i in range(n):
        box = box_mask(100 + 4 * i, 130)
        hand = hand_shape(150 + 4 * i, 145, scale=0.8)
        rgb, depth = render(box, hand, hand_depth_m=None, seed=i)
        frames.append(Frame(i, f"{i:06d}", rgb, depth))
        boxes.append(box & ~hand)
        hands.append(hand)
    return Scene(frames, name="carrying"), boxes, hands


# -- the colour models ------------------------------------------------------------------------------


def test_skin_colour_model_accepts_skin_tones_and_rejects_the_scene():
    patches = np.array(
        [
            [
                LIGHT_SKIN,
                DARK_SKIN,
                (255, 200, 170),
                TABLE,
                WALL,
                BOX,
                GRIPPER,
                (40, 160, 60),
                (240, 240, 40),
                (20, 20, 20),
            ]
        ],
        np.uint8,
    )
    assert skin_mask(patches)[0].tolist() == [True, True, True] + [False] * 7


def test_gripper_colour_box_is_parsed_and_applied():
    assert parse_hsv("") is None
    assert parse_hsv("0, 0, 0, 180, 100, 100") == [((0, 0, 0), (180, 100, 100))]
    two = "0,0,0,180,100,100; 100,150,100,130,255,255"  # a dark grey body and blue fingers
    assert parse_hsv(two) == [((0, 0, 0), (180, 100, 100)), ((100, 150, 100), (130, 255, 255))]
    for bad in ("1,2,3", "0,0,0,181,10,10", "10,0,0,5,10,10", "a,b,c,d,e,f", "0,0,0,180,100,100;"):
        with pytest.raises(ParamError, match="gripper_hsv"):
            HandParams(gripper_hsv=bad)
    patches = np.array([[GRIPPER, TABLE, BOX]], np.uint8)
    assert hsv_mask(patches, parse_hsv("0,0,0,180,100,100"))[0].tolist() == [True, False, False]
    assert hsv_mask(patches, parse_hsv(two))[0].tolist() == [True, False, True]  # the blue box too


# -- hand regions -----------------------------------------------------------------------------------


def test_hand_regions_reach_the_border_and_have_a_hand_sized_surface():
    depth = np.full((H, W), 0.6, np.float32)  # a pixel is 2 mm across: 30 cm^2 is 750 pixels
    arm, lone, speck = hand_shape(220, 100), np.zeros((H, W), bool), np.zeros((H, W), bool)
    lone[150:200, 30:90] = True  # skin-coloured, large, but not reaching the border
    speck[0:20, 100:120] = True  # at the border, 400 px = 16 cm^2
    found = hand_regions(arm | lone | speck, depth, INTR, min_area_m2=0.003)
    assert mask_iou(found, arm) > 0.97 and not found[lone].any() and not found[speck].any()
    depth[arm] = 0.0  # no reading on the hand: counted at the region's depth
    depth[arm & (np.arange(W)[None, :] > 300)] = 0.6
    assert mask_iou(hand_regions(arm, depth, INTR, min_area_m2=0.003), arm) > 0.97


def test_held_needs_contact_in_depth_not_only_in_the_image():
    depth = np.full((H, W), 0.8, np.float32)
    hand, near_box, far_box = np.zeros((H, W), bool), np.zeros((H, W), bool), np.zeros((H, W), bool)
    hand[100:140, 100:200] = True
    near_box[140:180, 100:200] = True
    far_box[60:100, 100:200] = True
    depth[hand], depth[near_box], depth[far_box] = 0.60, 0.61, 0.75
    assert held([near_box, far_box], hand, depth, touch_m=0.02) == [True, False]
    assert held([near_box], np.zeros((H, W), bool), depth, touch_m=0.02) == [False]


def test_held_needs_a_line_of_contact_not_a_couple_of_pixels():
    """A box along the hand's lower edge (100 px, 12 cm at 0.6 m) is held; a box touching its corner
    (one diagonal pixel) is not, once a 5 mm line of contact (2.5 px at 0.6 m) is asked for."""
    depth = np.full((H, W), 0.6, np.float32)
    hand, along, corner = np.zeros((H, W), bool), np.zeros((H, W), bool), np.zeros((H, W), bool)
    hand[100:140, 100:200] = True
    along[140:180, 100:200] = True
    corner[140:160, 200:230] = True
    assert held([along, corner], hand, depth, touch_m=0.02) == [True, True]
    assert held([along, corner], hand, depth, touch_m=0.02, line_m=0.005, fx=INTR.fx) == [True, False]


def test_a_hand_holds_with_its_palm_and_fingers_not_along_its_forearm():
    """An arm enters from the left border at 0.6 m, 300 px long (60 cm): its tip is its right end. A
    strip of its own sleeve along the forearm, at its depth, touches it near the border, 40-50 cm
    from the tip: not held once the distance to the tip counts (the strip is held without it); a box
    at the hand's end, 0-10 cm from the tip, is held. An arm that enters through pixels without a
    reading has no known tip, and what touches it anywhere is held."""
    depth = np.full((H, W), 0.8, np.float32)
    arm, strip, box = np.zeros((H, W), bool), np.zeros((H, W), bool), np.zeros((H, W), bool)
    arm[100:140, 0:300] = True
    strip[90:100, 20:80] = True
    box[140:180, 250:300] = True
    depth[arm | strip | box] = 0.6
    tips, tipless = hand_tips(arm, depth, INTR)
    assert len(tips) == 1 and not tipless.any()
    assert np.allclose(tips[0], INTR.points(np.array([299]), np.array([100]), np.array([0.6]))[0])
    assert held([strip, box], arm, depth, touch_m=0.02) == [True, True]
    assert held([strip, box], arm, depth, touch_m=0.02, intrinsics=INTR) == [False, True]
    gap = arm.copy()
    gap[:, 0:5] = False  # the sleeve's end without a reading: the arm no longer reaches the border
    assert held([strip, box], gap, depth, touch_m=0.02, intrinsics=INTR) == [True, True]


def test_arms_reach_the_border_stand_off_the_table_and_touch_the_hand():
    """A region reaching the right border at the hand's height (10 cm over the table), joined to it,
    is an arm; the same region with a front face down to the table (a box resting on it, touched by
    fingers lying on its top), one that the hand does not reach, and one short of the border are not,
    unless the rest of it, to the border, has no depth reading (a sleeve too near the sensor)."""
    table = Plane(normal=tuple(float(v) for v in UP), offset_m=0.5, inlier_fraction=0.6, noise_m=0.001)
    rows = np.s_[100:130]
    hand = np.zeros((H, W), bool)
    hand[rows, 150:200] = True

    def arm_of(region: np.ndarray, height: np.ndarray, edge: np.ndarray | None = None) -> np.ndarray:
        depth = table_depth(height).astype(np.float32)
        contact = on_plane(depth, INTR, table, step=np.zeros((H, W), bool), plane_distance_m=0.012)
        return arms(region, hand, depth, INTR, contact=contact, touch_m=0.02, edge=edge)

    sleeve = np.zeros((H, W), bool)
    sleeve[rows, 200:] = True
    height = np.where(hand | sleeve, 0.10, 0.0)
    assert mask_iou(arm_of(sleeve, height), sleeve) > 0.97

    front = np.zeros((H, W), bool)  # the box's front face: from its top down to the table
    front[130:145, 200:] = True
    resting = np.where(sleeve, 0.03, 0.0) + np.where(hand, 0.04, 0.0)
    resting[130:145, 200:] = np.linspace(0.03, 0.0, 15)[:, None]
    assert not arm_of(sleeve | front, resting).any()

    away = np.where(hand, 0.10, 0.0) + np.where(sleeve, 0.30, 0.0)  # 20 cm nearer the camera
    assert not arm_of(sleeve, away).any()
    short = sleeve & (np.arange(W)[None, :] < W - 10)
    assert not arm_of(short, np.where(hand | short, 0.10, 0.0)).any()
    # the rest of the sleeve, too near the sensor to be measured, reaches the border without a reading
    unread = sleeve & ~short
    assert mask_iou(arm_of(short, np.where(hand | short, 0.10, 0.0), edge=unread), short) > 0.97
    assert not arm_of(short, np.where(hand | short, 0.10, 0.0), edge=np.roll(unread, 40, axis=0)).any()


# -- whole frames and sequences --------------------------------------------------------------------


@pytest.mark.parametrize("skin", [LIGHT_SKIN, DARK_SKIN], ids=["light", "dark"])
def test_hand_mask_matches_the_drawn_hand(skin):
    """Measured IoU with the drawn hand: 0.99 (light and dark skin); its outline's mixed pixels are
    the rest. Bound: 0.9."""
    scene, box, hands = waving_scene(4, skin=skin)
    seg = DepthThresholdSegmenter()
    for i in range(len(scene)):
        found = seg.hand_mask(scene[i], sequence=scene)
        assert mask_iou(found, hands[i]) > 0.9, i
        assert not found[box & ~hands[i]].any()


def test_a_hand_with_depth_dropouts_is_still_one_hand():
    """A fifth of the hand's pixels without a reading (a sensor's dropouts on skin): the region is
    neither cut apart at them nor shrunk (measured IoU 0.99, as without dropouts)."""
    scene, _, hands = waving_scene(1)
    frame = scene[0]
    depth = frame.depth_m.copy()
    depth[hands[0] & (np.random.default_rng(1).random((H, W)) < 0.2)] = 0.0
    holed = Scene([Frame(0, "0", frame.rgb, depth)], name="dropouts")
    assert mask_iou(DepthThresholdSegmenter().hand_mask(holed[0], sequence=holed), hands[0]) > 0.9


def test_a_hand_waving_before_a_still_box_leaves_the_box_chosen():
    """Without the hand step the hand is the moving instance and is chosen in every frame (IoU with
    the hand 0.69-1.0); with it the box's visible part is chosen in every frame (IoU 0.95-1.0; bound
    0.85), and the scene is still."""
    scene, box, hands = waving_scene(10)
    seg = DepthThresholdSegmenter()
    off = DepthThresholdSegmenter(DepthThresholdParams(exclude_hands=False))
    for i in range(len(scene)):
        mask = seg.segment(scene[i], sequence=scene)
        assert mask_iou(mask, box & ~hands[i]) > 0.85, i
        assert not (mask & hands[i]).any(), i
        assert seg.choice(scene[i], sequence=scene).rule in ("still, fallback", "still, kept")
        assert mask_iou(off.segment(scene[i], sequence=scene), hands[i]) > 0.5, i


def test_a_hand_alone_is_never_the_object():
    frames, hands = [], []
    for i in range(6):
        hand = hand_shape(200 - 8 * i, 120)
        rgb, depth = render(np.zeros((H, W), bool), hand, hand_depth_m=0.55, seed=i)
        frames.append(Frame(i, str(i), rgb, depth))
        hands.append(hand)
    scene = Scene(frames, name="hand-only")
    seg = DepthThresholdSegmenter()
    assert all(seg.segment(scene[i], sequence=scene) is None for i in range(len(scene)))


def test_the_held_box_is_chosen_without_the_hand_that_carries_it():
    """Measured IoU with the box's visible part: 0.84 in every frame (the hand's 2-pixel margin is
    removed with it, about 300 of the box's 2000 visible pixels). Bound: 0.8."""
    scene, boxes, hands = carrying_scene(10)
    seg = DepthThresholdSegmenter()
    for i in range(len(scene)):
        mask = seg.segment(scene[i], sequence=scene)
        assert mask_iou(mask, boxes[i]) > 0.8, i
        assert np.count_nonzero(mask & hands[i]) == 0, i
        choice = seg.choice(scene[i], sequence=scene)
        assert choice.held and choice.held[choice.index], i


def test_the_pixels_a_hand_may_cover_reach_the_registration():
    """The pipeline keeps, with each frame's cloud, the pixels the segmenter left out for a hand (and
    its outline), where a point of the object landing later is hidden rather than gone."""
    scene, _, hands = carrying_scene(4)
    cloud = Pipeline(load_registry(), Config(segmenter="depth_threshold")).frame(scene, 2).cloud
    covered = cloud.view.covered
    assert covered[hands[2]].mean() > 0.95
    assert not (covered & cloud.view.mask).any()
    assert covered.sum() < 2 * hands[2].sum()


@pytest.mark.slow
def test_u2net_leaves_the_hand_out_too(u2netp_path):  # noqa: F811
    """u2net on the waving scene (real u2netp weights): the box is chosen in all 6 frames (measured
    IoU 0.98-1.0, bound 0.9); without the hand step the hand is chosen in 2 of them."""
    scene, box, hands = waving_scene(6)
    seg = U2netSegmenter(U2netParams(model_path=str(u2netp_path)))
    off = U2netSegmenter(U2netParams(model_path=str(u2netp_path), exclude_hands=False))
    chose_hand = 0
    for i in range(len(scene)):
        assert mask_iou(seg.segment(scene[i], sequence=scene), box & ~hands[i]) > 0.9, i
        assert mask_iou(seg.hand_mask(scene[i], sequence=scene), hands[i]) > 0.9, i
        chose_hand += mask_iou(off.segment(scene[i], sequence=scene), hands[i]) > 0.5
    assert chose_hand >= 1


@pytest.mark.slow
def test_u2net_keeps_a_still_box_whole_when_an_arm_crosses_it(u2netp_path):  # noqa: F811
    """An arm 25 cm in front of a still box cuts its visible part in two; u2net (real weights) chooses
    both sides as one object in every frame (measured IoU 0.93; one side alone, 0.68-0.70, was chosen
    before the sides were joined), so the object does not jump from one side to the other."""
    box = box_mask(130, 70, w=110, h=90)
    frames, hands = [], []
    for i in range(4):
        hand = hand_shape(95 + 3 * i, 92)
        rgb, depth = render(box, hand, hand_depth_m=0.55, seed=i)
        frames.append(Frame(i, f"{i:06d}", rgb, depth))
        hands.append(hand)
    scene = Scene(frames, name="arm-across")
    seg = U2netSegmenter(U2netParams(model_path=str(u2netp_path)))
    for i in range(len(scene)):
        assert cv2.connectedComponents((box & ~hands[i]).astype(np.uint8))[0] == 3  # two sides
        assert mask_iou(seg.segment(scene[i], sequence=scene), box & ~hands[i]) > 0.85, i


def test_a_gripper_is_removed_when_its_colour_is_given():
    box = box_mask(130, 130)
    frames, grippers = [], []
    for i in range(6):
        gripper = hand_shape(200 - 6 * i, 110)
        rgb, depth = render(box, gripper, hand_depth_m=0.55, hand_colour=GRIPPER, seed=i)
        frames.append(Frame(i, str(i), rgb, depth))
        grippers.append(gripper)
    scene = Scene(frames, name="gripper")
    seg = DepthThresholdSegmenter(DepthThresholdParams(gripper_hsv="0,0,0,180,100,100"))
    plain = DepthThresholdSegmenter()
    for i in range(len(scene)):
        assert mask_iou(seg.hand_mask(scene[i], sequence=scene), grippers[i]) > 0.9
        assert mask_iou(seg.segment(scene[i], sequence=scene), box & ~grippers[i]) > 0.85
        assert not plain.hand_mask(scene[i], sequence=scene).any()  # grey is not skin
    # a robot rig gives its gripper's colour in the sequence's own settings (meta.json)
    scene.meta["gripper_hsv"] = "0,0,0,180,100,100"
    assert mask_iou(DepthThresholdSegmenter().hand_mask(scene[0], sequence=scene), grippers[0]) > 0.9
    skin_only = DepthThresholdSegmenter(DepthThresholdParams(gripper_hsv="0,0,0,0,0,0"))
    assert not skin_only.hand_mask(scene[0], sequence=scene).any()  # the parameter wins
    scene.meta["gripper_hsv"] = "0,0,0,180,100"
    with pytest.raises(InputError, match="sequence's gripper_hsv") as err:
        DepthThresholdSegmenter().hand_mask(scene[1], sequence=scene)
    assert err.value.path == str(scene.path)


def test_a_skin_coloured_box_held_by_a_gripper_is_not_taken_for_it():
    """A wooden (skin-coloured) box held by a grey gripper whose fingers lie on it: skin and the
    gripper's colour are found apart, so the box neither joins the gripper nor is removed with it."""
    box = box_mask(130, 130)
    gripper = hand_shape(175, 150)
    rgb, depth = render(box, gripper, hand_depth_m=None, hand_colour=GRIPPER)
    wood = box & ~gripper
    paint(rgb, wood, (200, 150, 110), seed=1)
    assert skin_mask(rgb)[wood].mean() > 0.9
    scene = Scene([Frame(0, "0", rgb, depth)], name="wooden box")
    scene.meta["gripper_hsv"] = "0,0,0,180,100,100"
    seg = DepthThresholdSegmenter()
    found = seg.hand_mask(scene[0], sequence=scene)
    assert mask_iou(found, gripper) > 0.85
    assert np.count_nonzero(found & wood) < 0.05 * np.count_nonzero(wood)
    chosen = seg.segment(scene[0], sequence=scene)
    assert not (chosen & gripper).any() and np.count_nonzero(chosen & wood) > 0.5 * np.count_nonzero(wood)


def test_given_hand_masks_are_read_from_the_folder(tmp_path):
    scene, box, hands = waving_scene(3, skin=(120, 200, 120))  # a green glove: no skin colour
    scene.path = tmp_path
    (tmp_path / "hand").mkdir()
    for i, hand in enumerate(hands):
        cv2.imwrite(str(tmp_path / "hand" / f"{scene[i].name}.png"), hand.astype(np.uint8) * 255)
    seg = DepthThresholdSegmenter(DepthThresholdParams(hand_masks="hand"))
    assert mask_iou(seg.hand_mask(scene[1], sequence=scene), hands[1]) == 1.0
    assert mask_iou(seg.segment(scene[1], sequence=scene), box & ~hands[1]) > 0.85
    (tmp_path / "hand" / f"{scene[2].name}.png").unlink()
    with pytest.raises(InputError, match="hand mask missing") as err:
        seg.hand_mask(scene[2], sequence=scene)
    assert err.value.path.endswith(f"{scene[2].name}.png")


def test_hands_off_gives_no_hand_mask():
    scene, _, _ = waving_scene(2)
    seg = DepthThresholdSegmenter(DepthThresholdParams(exclude_hands=False))
    assert seg.hand_mask(scene[0], sequence=scene) is None
    p = DepthThresholdParams()
    planes = fit_planes(scene[0].depth_m, INTR, params=p)
    background, _ = background_mask(scene[0].depth_m, INTR, planes, params=p)
    off = DepthThresholdParams(exclude_hands=False)
    assert not find_hands(scene[0], background, INTR, params=off, sequence_path=scene.path).any()


@pytest.mark.slow
def test_a_still_scene_with_a_waving_hand_is_classified_static():
    """The whole pipeline (default rule, depth_threshold): the box never moves and the label is
    static; without the hand step the hand is taken for the object in some frames."""
    scene, box, hands = waving_scene(10)
    registry = load_registry()
    config = Config(segmenter="depth_threshold")
    assert Pipeline(registry, config).run(scene).label == "static"
    off = config.with_overrides(registry, {"exclude_hands": "false"})
    segmenter = Pipeline(registry, off).segmenter(scene)
    masks = [segmenter.segment(scene[i], sequence=scene) for i in range(len(scene))]
    assert any(m is not None and (m & hands[i]).sum() > 0.5 * hands[i].sum() for i, m in enumerate(masks))


def _sleeved_scene(box: np.ndarray, sleeved, name: str) -> tuple[Scene, list[np.ndarray]]:
    """Six frames of a still box and a hand moving left over the table, its arm from the right
    border; ``sleeved(columns, i)`` says which columns of frame i's arm are sleeved. The scene and
    the true hand-and-arm masks."""
    frames, hands = [], []
    for i in range(6):
        hand = hand_shape(200 - 6 * i, 110 + 4 * (i % 3))
        sleeve = hand & sleeved(np.arange(W)[None, :], i)
        rgb, depth = render(box, hand, hand_depth_m=0.55, sleeve=sleeve, seed=i)
        frames.append(Frame(i, f"{i:06d}", rgb, depth))
        hands.append(hand)
    return Scene(frames, name=name), hands


def test_a_sleeve_of_any_colour_is_removed_with_the_hand():
    """A green sleeve covers the forearm from the border to 40 px from the wrist, so the skin no longer
    reaches the border: the sleeve is found as the hand's arm and the hand is still found (measured
    IoU with hand and sleeve 0.998; bound 0.9), and the still box is chosen in every frame."""
    box = box_mask(130, 130)
    scene, hands = _sleeved_scene(box, lambda columns, i: columns > 240 - 6 * i, "sleeve")
    seg = DepthThresholdSegmenter()
    for i in range(len(scene)):
        assert mask_iou(seg.hand_mask(scene[i], sequence=scene), hands[i]) > 0.9, i
        mask = seg.segment(scene[i], sequence=scene)
        assert mask_iou(mask, box & ~hands[i]) > 0.85, i
        assert not (mask & hands[i]).any(), i


def test_a_sleeve_between_a_bare_forearm_and_the_hand_is_removed_with_them():
    """A short sleeve round the middle of the forearm: the bare skin beyond it reaches the border, the
    hand before it does not. The sleeve is a stretch of forearm from one to the other, so it continues
    the arm to the hand, and the hand, sleeve and forearm are all left out of the still box's mask."""
    scene, hands = _sleeved_scene(
        box_mask(130, 130),
        lambda columns, i: (columns > 240 - 6 * i) & (columns < 280 - 6 * i),
        "short sleeve",
    )
    seg = DepthThresholdSegmenter()
    for i in range(len(scene)):
        assert mask_iou(seg.hand_mask(scene[i], sequence=scene), hands[i]) > 0.9, i
        assert not (seg.segment(scene[i], sequence=scene) & hands[i]).any(), i


def test_a_stretch_of_forearm_is_as_wide_as_one_and_joins_arm_and_hand_at_its_two_ends():
    """At 0.5 m a pixel is 1.7 mm: a band 40 px (7 cm) wide from the arm (left) to the hand (right) is
    a forearm; a box 100 px (17 cm) wide is not, nor is the band when the hand touches it beside the
    arm (a held object touching the fingers along its side)."""
    depth = np.full((H, W), 0.5)
    band = np.zeros((H, W), bool)
    band[100:140, 100:200] = True
    arm, hand, beside = np.zeros((3, H, W), bool)
    arm[100:140, 80:100] = True
    hand[100:140, 200:220] = True
    beside[140:150, 100:120] = True
    assert forearm_between(band, arm, hand, depth, INTR)
    wide = np.zeros((H, W), bool)
    wide[70:170, 100:200] = True
    assert not forearm_between(wide, arm, hand, depth, INTR)
    assert not forearm_between(band, arm, beside, depth, INTR)


def test_projector_shadows_lie_between_a_near_and_a_far_reading_in_their_row():
    """At fx = 100 px a projector 10 cm beside the camera shifts 0.6 m against 0.8 m by 4.2 px."""
    depth = np.full((4, 60), 0.8, np.float32)
    depth[:, 3:6] = 0.0  # between 0.8 (left) and 0.6 (right): a shadow
    depth[:, 6:9] = 0.6
    depth[1, 9:] = 0.0  # from the object to the border: no reading on one side, not a shadow
    depth[2, 3:6] = 0.0
    depth[2, 6:] = 0.81  # between two readings 1 cm apart: a dropout on one surface
    depth[3, 9:49] = 0.0  # 40 px between 0.6 and 0.8: wider than any projector's shadow
    shadows = projector_shadows(depth, step_m=0.02, fx=100.0)
    assert shadows[0, 3:6].all() and shadows[1, 3:6].all() and not shadows[1, 9:].any()
    assert not shadows[2].any() and not shadows[3, 9:49].any() and not shadows[depth > 0].any()


def _random_depth(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """Depth (metres, float32) in steps of 5 mm over a few surfaces, with dropouts of any density."""
    depth = np.round(rng.random(shape) * 40).astype(np.float32) * np.float32(0.005)
    depth[rng.random(shape) < rng.random()] = 0
    return depth


def test_projector_shadows_match_a_numpy_scan_of_the_rows():
    """The compiled row scan against the same rule written with numpy: each dropout's nearest reading
    to the left and to the right (running maxima of column indices) more than step_m apart, in a gap
    no wider than the disparity between them (plus a pixel)."""
    rng = np.random.default_rng(0)
    for _ in range(50):
        depth = _random_depth(rng, tuple(rng.integers(1, 40, 2)))
        gaps, w = depth == 0, depth.shape[1]
        columns = np.arange(w)
        left = np.maximum.accumulate(np.where(gaps, -1, columns), axis=1)
        right = w - 1 - np.maximum.accumulate(np.where(gaps[:, ::-1], -1, columns), axis=1)[:, ::-1]
        expected = np.zeros(depth.shape, bool)
        v, u = np.nonzero(gaps & (left >= 0) & (right < w))
        near, far = depth[v, left[v, u]], depth[v, right[v, u]]
        apart = np.abs(near - far) > 0.02
        disparity = float(np.float32(0.1 * 3.0)) * np.abs(1 / near.astype(float) - 1 / far.astype(float))
        apart &= right[v, u] - left[v, u] - 2 <= disparity
        expected[v[apart], u[apart]] = True
        assert np.array_equal(projector_shadows(depth, step_m=0.02, fx=3.0), expected)


def _full_range(depth: np.ndarray, where: np.ndarray, reach_px: int) -> tuple[np.ndarray, np.ndarray]:
    """The nearest and farthest reading of ``where`` within reach, filtered over the whole image."""
    kernel = np.ones((2 * reach_px + 1, 2 * reach_px + 1), np.uint8)
    seen = where & (depth > 0)
    near = cv2.erode(np.where(seen, depth, np.float32(np.inf)), kernel, borderValue=np.inf)
    far = cv2.dilate(np.where(seen, depth, np.float32(0)), kernel, borderValue=0)
    return near, far


def test_depth_steps_match_the_range_of_each_pixels_neighbourhood():
    """The compiled 3x3 step test against the farthest minus the nearest reading around each pixel
    (OpenCV's minimum and maximum filters over the whole image), to the bit."""
    rng = np.random.default_rng(1)
    for _ in range(50):
        depth = _random_depth(rng, tuple(rng.integers(1, 40, 2)))
        near, far = _full_range(depth, np.ones(depth.shape, bool), 1)
        assert np.array_equal(depth_steps(depth, step_m=0.02), far - near > np.float32(0.02))


def test_depth_range_on_the_readings_box_equals_the_whole_image_filter():
    """The nearest and farthest readings of a region within reach, filtered on the region's bounding
    box grown by the reach, are those of a filter over the whole image."""
    rng = np.random.default_rng(2)
    for _ in range(50):
        depth = _random_depth(rng, tuple(rng.integers(1, 60, 2)))
        where = np.zeros(depth.shape, bool)
        y, x = (rng.integers(0, n) for n in depth.shape)
        where[y : y + rng.integers(1, 20), x : x + rng.integers(1, 20)] = True
        reach = int(rng.integers(1, 8))
        for got, expected in zip(_depth_range(depth, where, reach), _full_range(depth, where, reach)):
            assert np.array_equal(got, expected)


def test_an_object_the_hand_passes_in_front_of_is_one_object_on_both_sides_of_it():
    """A box at 0.8 m with an arm 20 cm in front of it across its middle: its two sides are one
    instance. Held (the arm at the box's depth), or with the box's sides 30 px apart from the arm (a
    hand near two boxes, hiding neither), they stay apart."""
    depth = np.full((H, W), 1.0, np.float32)
    left, right, arm = np.zeros((H, W), bool), np.zeros((H, W), bool), np.zeros((H, W), bool)
    left[100:150, 100:150] = True
    right[100:150, 160:210] = True
    arm[:, 150:160] = True
    depth[left | right] = 0.8
    depth[arm] = 0.6
    joined = join_hidden([left, right], arm, depth, INTR, touch_m=0.02)
    assert len(joined) == 1 and mask_iou(joined[0], left | right) == 1.0
    depth[arm] = 0.8
    assert len(join_hidden([left, right], arm, depth, INTR, touch_m=0.02)) == 2
    depth[arm] = 0.6
    far_left, far_right = np.roll(left, -30, axis=1), np.roll(right, 30, axis=1)
    assert len(join_hidden([far_left, far_right], arm, depth, INTR, touch_m=0.02)) == 2


def test_an_arm_too_near_the_sensor_to_be_measured_reaches_the_border_through_it():
    """A green sleeve from the border to 40 px from the wrist has no depth reading (nearer than the
    sensor's range), so neither the skin nor the sleeve reaches the border among the readings: the
    hand is still found (its skin region reaches the border through the pixels without a reading,
    where they are not between the hand and the table in their row: there they look like the
    projector's shadow of the hand), and the box is chosen."""
    box = box_mask(130, 130)
    frames, hands, sleeves = [], [], []
    for i in range(3):
        hand = hand_shape(200 - 6 * i, 110 + 4 * (i % 3))
        sleeve = hand & (np.arange(W)[None, :] > 240 - 6 * i)
        rgb, depth = render(box, hand, hand_depth_m=0.55, sleeve=sleeve, seed=i)
        depth[sleeve] = 0.0
        frames.append(Frame(i, f"{i:06d}", rgb, depth))
        hands.append(hand)
        sleeves.append(sleeve)
    scene = Scene(frames, name="near sleeve")
    seg = DepthThresholdSegmenter()
    for i, sleeve in enumerate(sleeves):
        found, skin = seg.hand_mask(scene[i], sequence=scene), hands[i] & ~sleeve
        assert np.count_nonzero(found & skin) > 0.95 * np.count_nonzero(skin), i
        assert not (found & ~hands[i]).any(), i
        assert mask_iou(seg.segment(scene[i], sequence=scene), box & ~hands[i]) > 0.85, i


def test_an_object_resting_on_the_table_at_the_border_is_kept_when_held():
    """A box lying on the table, cut by the left border, with its front face seen down to the table,
    and a hand from the right border resting its fingers on the box's top: the box is not taken for
    an arm (measured: 2-8 of its 5400 pixels in the hand mask, at the hand's outline); it is the held
    object chosen in every frame (measured IoU with its visible part 0.93-0.95;
    bound 0.85)."""
    top, front = np.zeros((H, W), bool), np.zeros((H, W), bool)
    top[130:175, 0:90] = True
    front[175:190, 0:90] = True
    height = np.where(top, 0.03, 0.0)
    height[175:190, 0:90] = np.linspace(0.03, 0.0, 15)[:, None]
    box = top | front
    frames, hands = [], []
    for i in range(6):
        hand = hand_shape(110 + 3 * i, 150, scale=0.8)
        rgb, depth = render(box, hand, hand_depth_m=None, depth=table_depth(height), seed=i)
        frames.append(Frame(i, f"{i:06d}", rgb, depth))
        hands.append(hand)
    scene = Scene(frames, name="box-at-the-border")
    seg = DepthThresholdSegmenter()
    for i in range(len(scene)):
        taken = seg.hand_mask(scene[i], sequence=scene) & box & ~hands[i]  # the hand outline's mixed pixels
        assert np.count_nonzero(taken) < 0.01 * np.count_nonzero(box), i
        assert mask_iou(seg.segment(scene[i], sequence=scene), box & ~hands[i]) > 0.85, i
        choice = seg.choice(scene[i], sequence=scene)
        assert choice.held and choice.held[choice.index], i


def test_a_gripper_finger_cut_off_from_its_body_is_removed_with_it():
    """A grey gripper held above the table with one finger seen apart from its body (a gap of 3 px,
    1 cm farther from the camera): the finger is too small to be a gripper by itself (6 cm^2), so it
    is found as a piece of the gripper it touches in 3-D, and it is neither an object nor the chosen
    one. A box of the gripper's colour lying on the table is kept, and chosen."""
    gripper = hand_shape(200, 110)
    finger = np.zeros((H, W), bool)
    finger[130:137, 165:195] = True  # below the palm, 3 px clear of it
    finger &= ~cv2.dilate(gripper.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    dark = box_mask(60, 150, 40, 30)  # a dark box of the gripper's colour on the table
    height = np.where(dark, 0.03, 0.0)
    depth = table_depth(height)
    frames = []
    for i in range(3):
        rgb, d = render(dark, gripper | finger, hand_depth_m=0.55, hand_colour=GRIPPER, depth=depth, seed=i)
        d[finger] = 0.56
        rgb[dark] = np.asarray(GRIPPER) + np.random.default_rng(i).normal(0, 2, (dark.sum(), 3))
        frames.append(Frame(i, f"{i:06d}", np.clip(rgb, 0, 255).astype(np.uint8), d))
    scene = Scene(frames, name="gripper finger")
    scene.meta["gripper_hsv"] = "0,0,0,180,100,100"
    seg = DepthThresholdSegmenter()
    for i in range(len(scene)):
        found = seg.hand_mask(scene[i], sequence=scene)
        assert np.count_nonzero(found & finger) > 0.8 * np.count_nonzero(finger), i
        assert np.count_nonzero(found & dark) < 0.05 * np.count_nonzero(dark), i
        assert not any((m & finger).any() for m in seg.frame_instances(scene[i], sequence=scene)), i
        assert mask_iou(seg.segment(scene[i], sequence=scene), dark) > 0.85, i


def test_a_held_object_of_another_skin_shade_keeps_its_pixels():
    """A wooden box (skin-coloured, but of another chromaticity) stands on the table, its front face
    coming down to it, and the hand lies on it with no depth step between them: the hand mask stops
    where the colour changes, so the box keeps its pixels (without the colour test the hand takes
    over a third of the box, all of it that stands out of the table's background cut, measured 37 %;
    checked with ``hand_chroma=0``)."""
    box = box_mask(110, 120, 70, 60)
    rows = np.mgrid[0:H, 0:W][0]
    height = np.where(box, 0.04 * (120 + 60 - rows) / 60, 0.0)  # its lower rows on the table
    hand = hand_shape(170, 140)
    rgb, depth = render(box, hand, hand_depth_m=None, depth=table_depth(height))
    wood = box & ~hand
    paint(rgb, wood, (205, 160, 100), seed=1)
    assert skin_mask(rgb)[wood].mean() > 0.9
    scene = Scene([Frame(0, "0", rgb, depth)], name="wooden box in the hand")
    found = DepthThresholdSegmenter().hand_mask(scene[0], sequence=scene)
    assert mask_iou(found, hand) > 0.85
    assert np.count_nonzero(found & wood) < 0.05 * np.count_nonzero(wood)
    without = DepthThresholdSegmenter(DepthThresholdParams(hand_chroma=0.0)).hand_mask(
        scene[0], sequence=scene
    )
    assert np.count_nonzero(without & wood) > 0.25 * np.count_nonzero(wood)


def test_a_carried_object_of_another_skin_shade_is_not_the_hand():
    """A hand held out by a green sleeve carries a wooden box (skin-coloured, another chromaticity),
    both 0.45 m from the camera, off the table, with no depth step between them. The box (0.04 m^2
    seen from the camera) is larger than any hand, so the hand mask stops where the colour changes
    though the box does not rest on the table, and the box is the object; without the size test
    (``hand_max_area_m2=0``) the hand takes all of it and no object is left."""
    box = box_mask(40, 50, 150, 120)
    hand = hand_shape(215, 120) & ~box
    depth = table_depth()
    depth[box | hand] = 0.45
    rgb, depth = render(box, hand, hand_depth_m=0.45, depth=depth)
    paint(rgb, box, (205, 160, 100), seed=1)
    paint(rgb, hand & (np.arange(W)[None, :] > 270), SLEEVE, seed=2)
    assert skin_mask(rgb)[box].mean() > 0.9
    scene = Scene([Frame(0, "0", rgb, depth)], name="wooden box carried")
    seg = DepthThresholdSegmenter()
    assert mask_iou(seg.hand_mask(scene[0], sequence=scene), hand) > 0.9
    assert mask_iou(seg.segment(scene[0], sequence=scene), box) > 0.9
    before = DepthThresholdSegmenter(DepthThresholdParams(hand_max_area_m2=0.0))
    assert before.hand_mask(scene[0], sequence=scene)[box].mean() > 0.9
    assert before.segment(scene[0], sequence=scene) is None


def test_a_box_carried_by_a_bare_arm_beside_an_unread_band_is_not_the_hand():
    """A bare arm carries a wooden box (skin-coloured, another chromaticity) 0.45 m from the camera,
    and a band without a reading (a window beyond the sensor's range) runs from the box's far side to
    the image border. The hand's colour is read where its arm leaves the picture, not along that
    band, which is no arm: the box (larger than any hand) is the object and the hand mask stops where
    the colour changes. Read along the band as well, the box's colour outvotes the arm's and the hand
    mask takes all of the box."""
    box = box_mask(40, 50, 150, 120)
    hand = hand_shape(215, 120) & ~box
    band = np.zeros((H, W), bool)
    band[50:170, :40] = True
    depth = table_depth()
    depth[box | hand] = 0.45
    rgb, depth = render(box, hand, hand_depth_m=0.45, depth=depth)
    paint(rgb, box, (205, 160, 100), seed=1)
    paint(rgb, band, WALL, seed=2)
    depth[band] = 0.0
    assert skin_mask(rgb)[box].mean() > 0.9
    scene = Scene([Frame(0, "0", rgb, depth)], name="wooden box carried by a bare arm")
    seg = DepthThresholdSegmenter()
    assert mask_iou(seg.hand_mask(scene[0], sequence=scene), hand) > 0.9
    assert mask_iou(seg.segment(scene[0], sequence=scene), box) > 0.9


def test_the_surfaces_of_labelled_regions_are_each_one_s_surface():
    """``surfaces_m2`` of every region at once equals ``surface_m2`` of each, pixels without a
    reading included (counted at their region's mean depth)."""
    rng = np.random.default_rng(0)
    labels = rng.integers(0, 5, (H, W))
    depth = rng.uniform(0.3, 1.0, (H, W)).astype(np.float32)
    depth[rng.random((H, W)) < 0.2] = 0
    where = rng.random((H, W)) < 0.8
    each = [surface_m2((labels == q) & where, depth, INTR) for q in range(5)]
    np.testing.assert_allclose(surfaces_m2(labels, where, 5, depth, INTR), each, rtol=1e-6)


def test_the_colour_of_a_hand_is_read_inside_its_outline():
    """A hand (resting on the table along its lower rows) held by a sleeve to its right, with a wooden
    block in its fingers (left of it, on the table too), and a strip 5 px thin of the table's colour
    along the sleeve's top, 2 px above it (mixed pixels of the sleeve's outline against the table,
    skin-coloured and joined to the hand): the hand's colour is read inside its outline, so the
    strip, though it lies along the sleeve, does not set it. The hand is kept; the block is cut off
    (reading the colour near the sleeve alone, the strip's colour was the hand's and the hand was
    cut: checked)."""
    hand, carriers, block, strip = (np.zeros((H, W), bool) for _ in range(4))
    hand[95:130, 120:200] = True
    carriers[100:130, 200:300] = True
    block[95:130, 90:120] = True
    strip[93:98, 200:300] = True
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[hand], rgb[block | strip] = LIGHT_SKIN, (120, 80, 50)
    contact = np.zeros((H, W), bool)
    contact[125:130, 90:200] = True
    kept, _ = own_colour(hand | block | strip, carriers, rgb, tolerance=0.02, contact=contact)
    assert kept[hand].all()
    assert not kept[block].any()


def test_a_hand_of_another_shade_than_its_skin_coloured_sleeve_stays_whole():
    """A tan (skin-coloured) sleeve holds out a hand of a lighter skin: the hand differs in colour from
    where the arm enters, but it does not rest on the table, so it stays in the hand mask."""
    box = box_mask(130, 130)
    hand = hand_shape(190, 100)
    sleeve = hand & (np.arange(W)[None, :] > 240)
    rgb, depth = render(box, hand, hand_depth_m=0.55)
    paint(rgb, sleeve, (190, 150, 95), seed=2)
    assert skin_mask(rgb)[sleeve].mean() > 0.9
    scene = Scene([Frame(0, "0", rgb, depth)], name="tan sleeve")
    found = DepthThresholdSegmenter().hand_mask(scene[0], sequence=scene)
    assert mask_iou(found, hand) > 0.9


def test_a_hand_grasping_on_the_table_is_found_though_its_fingertips_touch_it():
    """A green sleeve holds a hand out over the table, its fingers sloping down to it (their tips
    1.5 cm up: on a thin object lying there), its palm and wrist 8 cm up: the skin touches the table,
    but only at the tips, not along the bottom of its outline as an object standing there would, so
    the sleeve and the hand are found (without the outline test the hand is lost: checked)."""
    hand = hand_shape(170, 120)
    sleeve = hand & (np.arange(W)[None, :] > 240)
    slope = np.clip((np.arange(W)[None, :] - 122) / 80, 0, 1)  # 0 at the fingertips, 1 from the palm
    height = np.where(hand, 0.015 + 0.065 * slope, 0.0)
    rgb, _ = render(np.zeros((H, W), bool), hand, hand_depth_m=0.5, sleeve=sleeve)
    depth = np.round(table_depth(height) + np.random.default_rng(0).normal(0, 0.001, (H, W)), 3)
    scene = Scene([Frame(0, "0", rgb, depth.astype(np.float32))], name="grasping on the table")
    found = DepthThresholdSegmenter().hand_mask(scene[0], sequence=scene)
    assert mask_iou(found, hand) > 0.9


def test_chromaticity_and_colour_distances_as_numpy_reductions():
    """The chromaticity's sums and the squared colour distances taken column by column give the bits
    of numpy's reductions over the short axis (``sum(axis=1)``)."""
    rng = np.random.default_rng(8)
    rgb = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    where = rng.random((20, 30)) < 0.6
    c = cv2.blur(rgb, (3, 3))[where].astype(np.float32)
    assert np.array_equal(
        chromaticity(rgb, where), c / np.maximum(c.sum(axis=1, keepdims=True), np.float32(1))
    )
    for n in (1, 7, 1000):
        v = (rng.normal(size=(n, 3)) * rng.random((n, 1))).astype(np.float32)
        assert np.array_equal(_squared_norms(v), np.sum(v**2, axis=1))


def lit_sleeve_scene(n: int = 6) -> tuple[Scene, np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """A still box and a hand waving over it, in a dark red sleeve that passes for skin, with a lit
    facet of the sleeve (the same red, twice as bright) that passes for neither skin nor sleeve: the
    box, the hands with their sleeves, the facets."""
    box = box_mask(130, 130)
    frames, hands, facets = [], [], []
    columns = np.arange(W)[None, :]
    for i in range(n):
        hand = hand_shape(200 - 6 * i, 110 + 4 * (i % 3))
        sleeve = hand & (columns > 240 - 6 * i)
        inner = cv2.erode(sleeve.astype(np.uint8), np.ones((13, 13), np.uint8)) > 0
        facet = inner & (columns < W - 12)  # enclosed by the sleeve's dark faces
        rgb, depth = render(box, hand, hand_depth_m=0.55, skin=DARK_SKIN, seed=i)
        paint(rgb, sleeve & ~facet, RED_SLEEVE, seed=100 + i)
        paint(rgb, facet, LIT_RED_SLEEVE, seed=200 + i)
        frames.append(Frame(i, f"{i:06d}", rgb, depth))
        hands.append(hand)
        facets.append(facet)
    return Scene(frames, name=f"lit-sleeve-{n}"), box, hands, facets


RED_SLEEVE, LIT_RED_SLEEVE = (110, 50, 45), (220, 100, 90)


def test_a_lit_facet_of_a_sleeve_cut_off_by_colour_joins_the_hand_by_depth():
    """The sleeve's dark faces pass for skin and its lit facet for neither: the facet does not reach
    the border and is no arm by colour, but its depth continues the sleeve's all round (one surface),
    so it joins the hand mask (measured: all of it, hand IoU 0.998; bounds 0.9) and the still box is
    chosen in every frame (IoU 0.95-1.0; bound 0.85). With ``arm_outline_share`` 0 the facet stays
    out of the hand mask and is chosen in every frame (the box's IoU 0)."""
    one = np.zeros((1, 2, 3), np.uint8)
    one[0, 0], one[0, 1] = RED_SLEEVE, LIT_RED_SLEEVE
    assert skin_mask(one).tolist() == [[True, False]]  # the premise: the facet is not skin coloured
    scene, box, hands, facets = lit_sleeve_scene()
    seg = DepthThresholdSegmenter()
    off = DepthThresholdSegmenter(DepthThresholdParams(arm_outline_share=0.0))
    for i in range(len(scene)):
        found = seg.hand_mask(scene[i], sequence=scene)
        assert np.count_nonzero(found & facets[i]) > 0.9 * np.count_nonzero(facets[i]), i
        assert mask_iou(found, hands[i]) > 0.9, i
        mask = seg.segment(scene[i], sequence=scene)
        assert mask_iou(mask, box & ~hands[i]) > 0.85, i
        assert np.count_nonzero(off.hand_mask(scene[i], sequence=scene) & facets[i]) < 0.1 * np.count_nonzero(
            facets[i]
        ), i


def test_arm_pieces_continue_the_arm_s_surface_all_round():
    """A piece enclosed by the arm at its depth is arm; the same piece 3 cm nearer (a box held over the
    forearm: a depth step all round), one on the table, and one touching the arm's end along one side
    only (an object in the hand at its depth) are not."""
    table = Plane(normal=tuple(float(v) for v in UP), offset_m=0.5, inlier_fraction=0.6, noise_m=0.001)
    arm = np.zeros((H, W), bool)
    arm[100:130, 150:] = True
    piece = np.zeros((H, W), bool)
    piece[106:124, 220:270] = True
    arm &= ~piece

    def pieces_of(region: np.ndarray, height: np.ndarray) -> np.ndarray:
        depth = table_depth(height).astype(np.float32)
        contact = on_plane(depth, INTR, table, step=np.zeros((H, W), bool), plane_distance_m=0.012)
        return arm_pieces(region, arm, depth, contact=contact, touch_m=0.02, share=0.5)

    assert mask_iou(pieces_of(piece, np.where(arm | piece, 0.10, 0.0)), piece) > 0.97
    assert not pieces_of(piece, np.where(arm, 0.10, 0.0) + np.where(piece, 0.13, 0.0)).any()
    assert not pieces_of(piece, np.where(arm, 0.10, 0.0)).any()
    beyond = np.zeros((H, W), bool)  # beyond the arm's end at x = 150, touching it along one side
    beyond[95:135, 110:150] = True
    assert not pieces_of(beyond, np.where(arm | beyond, 0.10, 0.0)).any()


def test_a_box_carried_in_a_lit_sleeve_s_hand_stays_the_object():
    """The hand of the lit red sleeve lies on a box of the lit facet's own colour and slides it across
    the table: colour cannot tell the box from the facet, depth does (the box meets the fingers 1.5 cm
    below them and the table along a 5 cm step; the facet continues the sleeve). Measured: the box's
    IoU 0.83-0.84 in every frame (bound 0.8; the same without the facet step), all of the facet in the
    hand mask (none without)."""
    frames, boxes, hands, facets = [], [], [], []
    columns = np.arange(W)[None, :]
    for i in range(8):
        box = box_mask(100 + 4 * i, 130)
        hand = hand_shape(150 + 4 * i, 145, scale=0.8)
        sleeve = hand & (columns > 200 + 4 * i)
        facet = (cv2.erode(sleeve.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0) & (columns < W - 12)
        rgb, depth = render(box, hand, hand_depth_m=None, skin=DARK_SKIN, seed=i)
        paint(rgb, box & ~hand, LIT_RED_SLEEVE, seed=300 + i)
        paint(rgb, sleeve & ~facet, RED_SLEEVE, seed=100 + i)
        paint(rgb, facet, LIT_RED_SLEEVE, seed=200 + i)
        frames.append(Frame(i, f"{i:06d}", rgb, depth))
        boxes.append(box & ~hand)
        hands.append(hand)
        facets.append(facet)
    scene = Scene(frames, name="carrying-lit-sleeve")
    seg = DepthThresholdSegmenter()
    for i in range(len(scene)):
        found = seg.hand_mask(scene[i], sequence=scene)
        assert np.count_nonzero(found & facets[i]) > 0.9 * np.count_nonzero(facets[i]), i
        mask = seg.segment(scene[i], sequence=scene)
        assert mask_iou(mask, boxes[i]) > 0.8, i
        assert np.count_nonzero(mask & hands[i]) == 0, i


def test_a_bare_forearm_too_near_the_sensor_is_the_hand_s_and_a_window_beside_it_is_not():
    """The forearm of a bare arm, from the border to 40 px from the wrist, has no depth reading (nearer
    than the sensor's range), nor has a window beyond the sensor's range that it passes in front of:
    the unread forearm is of the hand's colour and joins the hand mask (measured: 91 % of it; the
    rest is the outline it shares with the window and the palm, of mixed colour); the window beside
    it, of another colour, stays out. Without the hand's colour (``hand_chroma`` 0) the forearm stays
    out too (measured: none of it)."""
    box = box_mask(130, 130)
    window = np.zeros((H, W), bool)
    window[80:170, 270:] = True
    for i in range(3):
        hand = hand_shape(200 - 6 * i, 110 + 4 * (i % 3))
        forearm = hand & (np.arange(W)[None, :] > 240 - 6 * i)
        rgb, depth = render(box, hand, hand_depth_m=0.55, seed=i)
        paint(rgb, window & ~hand, WALL, seed=i)
        depth[forearm | window] = 0.0
        scene = Scene([Frame(0, "000000", rgb, depth)], name="near forearm")
        found = DepthThresholdSegmenter().hand_mask(scene[0], sequence=scene)
        colourless = DepthThresholdSegmenter(DepthThresholdParams(hand_chroma=0.0)).hand_mask(
            scene[0], sequence=scene
        )
        assert np.count_nonzero(found & forearm) > 0.85 * np.count_nonzero(forearm), i
        assert not (found & window & ~hand).any(), i
        assert np.count_nonzero(colourless & forearm) < 0.5 * np.count_nonzero(forearm), i
