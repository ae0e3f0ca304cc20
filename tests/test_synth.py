"""Tests of the synthetic RGB-D generator (real Open3D ray casting, no mocks)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest

from artclass_plugins.readers.folder import FolderReader
from artclass_plugins.synth import (
    HANDS,
    MOTIONS,
    NOISE_LEVELS,
    OBJECTS,
    PRESETS,
    Intrinsics,
    T_object_from_child,
    generate_sequence,
    generate_set,
    part_poses,
    plan_sequence,
    preset_plans,
)
from artclass_plugins.synth.motion import look_at
from artclass_plugins.synth.objects import box, object_extent_m, rotation_about_axis
from artclass_plugins.synth.render import (
    SceneMesh,
    add_sensor_noise,
    object_meshes,
    render_clean,
    room_meshes,
)

SMALL = dict(width=160, height=120)


def _backproject(depth_m: np.ndarray, intr: Intrinsics) -> np.ndarray:
    v, u = np.indices(depth_m.shape)
    x = (u - intr.cx_px) / intr.fx_px * depth_m
    y = (v - intr.cy_px) / intr.fy_px * depth_m
    return np.stack([x, y, depth_m], axis=-1)


def _plane_scene(distance_m: float, tilt_deg: float = 0.0) -> list[SceneMesh]:
    """A 4 m x 4 m slab whose near face is the plane z = distance_m (camera = world frame)."""
    R = np.array(
        [
            [1, 0, 0],
            [0, math.cos(math.radians(tilt_deg)), -math.sin(math.radians(tilt_deg))],
            [0, math.sin(math.radians(tilt_deg)), math.cos(math.radians(tilt_deg))],
        ]
    )
    centre = R @ np.array([0.0, 0.0, 0.05]) + [0.0, 0.0, distance_m]
    piece = box((4.0, 4.0, 0.1), tuple(centre), (0.5, 0.5, 0.5), R=R)
    return [SceneMesh(piece.vertices_m, piece.triangles, -1, piece, np.eye(4))]


def _rotation_angle(R: np.ndarray) -> float:
    return math.acos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))


def _digest(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


# ---------------------------------------------------------------- catalogue


def test_catalogue_has_required_objects():
    arts = [o for o in OBJECTS.values() if o.kind == "articulated"]
    rigid = [o for o in OBJECTS.values() if o.kind == "rigid"]
    assert len(arts) >= 4 and len(rigid) >= 4
    assert {o.joint_type for o in arts} == {"revolute", "prismatic"}
    assert all(o.joint_type is None for o in rigid)
    for o in OBJECTS.values():
        assert 0.05 <= object_extent_m(o) <= 0.45, (o.name, object_extent_m(o))
    assert set(MOTIONS) == {"articulate", "carry_articulate", "carry", "static"}
    assert {"low", "high"} <= set(NOISE_LEVELS)


def test_intrinsics_scale_with_resolution():
    full, half = Intrinsics.for_resolution(640, 480), Intrinsics.for_resolution(320, 240)
    assert 525 <= full.fx_px <= 615 and full.fx_px == full.fy_px
    assert half.fx_px == pytest.approx(full.fx_px / 2)
    assert (half.cx_px + 0.5) == pytest.approx((full.cx_px + 0.5) / 2)
    rs = Intrinsics.for_resolution(848, 480)  # RealSense-like, wider field of view
    assert (rs.fx_px, rs.fy_px, rs.cx_px, rs.cy_px) == (615.0, 615.0, 423.5, 239.5)
    assert 2 * math.degrees(math.atan(424 / rs.fx_px)) > 2 * math.degrees(math.atan(320 / full.fx_px))


def test_chains_compose_joint_by_joint():
    lamp = OBJECTS["desk_lamp"]
    assert [j.parent for j in lamp.joints] == [0, 1] and lamp.subtree(1) == [1, 2]
    a, b = math.radians(20), math.radians(-35)
    _, lower, upper = part_poses(lamp, [a, b])
    shoulder, elbow = lamp.joints
    np.testing.assert_allclose(lower, T_object_from_child(shoulder, a), atol=1e-12)
    np.testing.assert_allclose(upper, lower @ T_object_from_child(elbow, b), atol=1e-12)
    # The elbow rides on the lower arm: its axis point turns about the shoulder axis by a.
    e = np.asarray(elbow.origin_m)
    p = np.asarray(shoulder.origin_m)
    moved_elbow = lower[:3, :3] @ e + lower[:3, 3]
    np.testing.assert_allclose(moved_elbow, rotation_about_axis(shoulder.axis, a) @ (e - p) + p, atol=1e-12)
    # ...and it is a fixed point of the upper arm's pose relative to the lower arm.
    rel = np.linalg.inv(lower) @ upper
    np.testing.assert_allclose(rel[:3, :3] @ e + rel[:3, 3], e, atol=1e-12)
    # Moving only the elbow leaves the base and the lower arm where they were.
    _, lower_b, _ = part_poses(lamp, [a, 0.3])
    np.testing.assert_allclose(lower_b, lower, atol=1e-12)
    # A folding ruler's segments all turn about vertical axes: the last one turns by the sum.
    ruler = OBJECTS["folding_ruler"]
    q = [0.3, -0.5, 0.9]
    last = part_poses(ruler, q)[-1]
    assert math.atan2(last[1, 0], last[0, 0]) == pytest.approx(sum(q))
    with pytest.raises(ValueError, match="3 joints"):
        part_poses(ruler, [0.1, 0.2])


def test_every_joint_of_a_chain_moves():
    seq = plan_sequence(
        object_name="folding_ruler", motion="articulate", noise="low", n_frames=10, seed=5, **SMALL
    )
    q = seq.trajectory.joint_positions
    assert q.shape == (10, 3)
    for k, joint in enumerate(OBJECTS["folding_ruler"].joints):
        assert joint.travel[0] - 1e-9 <= abs(q[-1, k] - q[0, k]) <= joint.travel[1] + 1e-9
        assert joint.limits[0] - 1e-9 <= q[:, k].min() and q[:, k].max() <= joint.limits[1] + 1e-9
    joints = seq.truth["joints"]
    assert [(j["parent"], j["child"]) for j in joints] == [(0, 1), (1, 2), (2, 3)]
    np.testing.assert_allclose([j["state"] for j in joints], q.T, atol=1e-9)


# ---------------------------------------------------------------- rendering


def test_plane_depth_is_z_depth_not_ray_length():
    intr = Intrinsics.for_resolution(160, 120)
    frame = render_clean(_plane_scene(0.8), T_camera_from_world=np.eye(4), intrinsics=intr)
    # Corners are 30 degrees off axis: a ray length would read about 0.8 / cos = 0.92 m.
    np.testing.assert_allclose(frame.depth_m, 0.8, atol=2e-5)
    assert not frame.mask.any()


def test_plane_depth_with_sensor_noise_matches_within_noise():
    intr = Intrinsics.for_resolution(320, 240)
    clean = render_clean(_plane_scene(1.0), T_camera_from_world=np.eye(4), intrinsics=intr)
    stds = {}
    for level in ("low", "high"):
        depth, _ = add_sensor_noise(clean, noise=NOISE_LEVELS[level], rng=np.random.default_rng(5))
        valid = depth > 0
        assert valid.mean() > 0.97  # a frontal plane loses only random dropouts and speckle
        d = depth[valid]
        sigma = float(NOISE_LEVELS[level].axial_sigma_m(1.0))
        assert abs(np.median(d) - 1.0) < 0.5 * sigma
        core = d[np.abs(d - 1.0) < 5 * sigma]  # without the speckle outliers
        stds[level] = core.std()
        # Quantisation adds variance, so the spread is at least the axial sigma, not much more.
        assert sigma * 0.8 < stds[level] < sigma * 2.0, (level, stds[level], sigma)
    assert stds["high"] > 2 * stds["low"]


def test_grazing_surfaces_drop_out():
    intr = Intrinsics.for_resolution(160, 120)
    clean = render_clean(_plane_scene(1.0, tilt_deg=70.0), T_camera_from_world=np.eye(4), intrinsics=intr)
    level = NOISE_LEVELS["low"]
    depth, _ = add_sensor_noise(clean, noise=level, rng=np.random.default_rng(0))
    angle = np.degrees(np.arccos(clean.cos_incidence))
    grazing = (clean.depth_m > 0) & (angle > level.grazing_end_deg)
    moderate = (clean.depth_m > 0) & (angle < level.grazing_start_deg - 5)
    assert grazing.sum() > 300 and moderate.sum() > 300  # the tilted plane is seen...
    assert (depth[grazing] > 0).mean() < 0.15  # ...but the sensor cannot decode it there
    assert (depth[moderate] > 0).mean() > 0.9


def test_box_back_projects_onto_its_surface():
    spec = OBJECTS["cereal_box"]  # 19 x 7 x 28 cm box, origin at the bottom centre
    intr = Intrinsics.for_resolution(320, 240)
    T_wo = np.eye(4)
    T_wo[:3, :3] = o3d.geometry.get_rotation_matrix_from_xyz((0.0, 0.0, 0.4))
    T_wo[:3, 3] = [0.05, -0.02, 0.0]
    T_cw = look_at([0.3, -0.7, 0.45], [0.05, 0.0, 0.14])
    frame = render_clean(
        room_meshes() + object_meshes(spec, None, T_wo), T_camera_from_world=T_cw, intrinsics=intr
    )
    mask = frame.mask
    assert mask.sum() > 2000
    pts_cam = _backproject(frame.depth_m, intr)[mask]
    T_oc = np.linalg.inv(T_cw @ T_wo)
    p = pts_cam @ T_oc[:3, :3].T + T_oc[:3, 3] - [0.0, 0.0, 0.14]
    half = np.array([0.095, 0.035, 0.14])
    excess = np.abs(p) - half
    outside = np.linalg.norm(np.maximum(excess, 0), axis=1)
    inside = np.minimum(-np.max(excess, axis=1), 1.0) * (np.max(excess, axis=1) < 0)
    dist = outside + inside
    assert dist.max() < 1e-3, dist.max()
    # and the 16-bit millimetre depth written to disk keeps that within 1.5 mm
    d_mm = np.rint(frame.depth_m * 1000).astype(np.uint16).astype(float) / 1000
    pts_mm = _backproject(d_mm, intr)[mask] @ T_oc[:3, :3].T + T_oc[:3, 3] - [0, 0, 0.14]
    ex = np.abs(pts_mm) - half
    d2 = np.linalg.norm(np.maximum(ex, 0), axis=1) + np.clip(-ex.max(1), 0, None)
    assert d2.max() < 1.5e-3


def test_mask_is_exactly_the_object_pixels():
    seq = plan_sequence(
        object_name="laptop", motion="articulate", noise="none", n_frames=4, seed=11, width=320, height=240
    )
    frame = seq.render(2)
    traj = seq.trajectory
    q = traj.joint_positions[2]
    obj = o3d.t.geometry.RaycastingScene()
    for m in object_meshes(OBJECTS["laptop"], q, traj.T_world_from_object[2]):
        obj.add_triangles(o3d.core.Tensor(m.vertices_m.astype(np.float32)), o3d.core.Tensor(m.triangles))
    room = o3d.t.geometry.RaycastingScene()
    for m in room_meshes():
        room.add_triangles(o3d.core.Tensor(m.vertices_m.astype(np.float32)), o3d.core.Tensor(m.triangles))
    valid = frame.depth_m > 0
    T_wc = np.linalg.inv(traj.T_camera_from_world[2])
    pts = _backproject(frame.depth_m, seq.intrinsics)[valid]
    pts_w = (pts @ T_wc[:3, :3].T + T_wc[:3, 3]).astype(np.float32)
    d_obj = obj.compute_distance(o3d.core.Tensor(pts_w)).numpy()
    d_room = room.compute_distance(o3d.core.Tensor(pts_w)).numpy()
    on_object = d_obj < d_room
    clear = np.abs(d_obj - d_room) > 1e-3  # skip the contact line with the table
    assert frame.mask[valid][clear].sum() > 1000
    np.testing.assert_array_equal(frame.mask[valid][clear], on_object[clear])
    assert frame.mask[~valid].sum() == 0  # noise-free: every object pixel has depth
    # The written mask is the renderer's part map, both parts included
    assert set(np.unique(frame.clean.part_ids[frame.mask])) == {0, 1}


def test_colour_channels_are_written_in_rgb_order(tmp_path):
    out = generate_sequence(
        tmp_path / "mug",
        object_name="mug",
        motion="static",
        noise="low",
        n_frames=2,
        seed=1,
        width=320,
        height=240,
    )
    rgb = cv2.cvtColor(cv2.imread(str(out / "rgb" / "000000.png")), cv2.COLOR_BGR2RGB)
    mask = cv2.imread(str(out / "mask" / "000000.png"), cv2.IMREAD_UNCHANGED) == 255
    r, g, b = rgb[mask].astype(float).mean(0)
    assert b < 0.5 * r and b < 0.5 * g  # the mug is yellow


def _jump_scene():
    """A near board (0.8 m) over the left half of the view, in front of a far wall (1.2 m)."""
    near = box((2.0, 4.0, 0.1), (-1.0, 0.0, 0.85), (0.5, 0.5, 0.5))
    far = box((8.0, 8.0, 0.1), (0.0, 0.0, 1.25), (0.5, 0.5, 0.5))
    return [SceneMesh(p.vertices_m, p.triangles, -1, p, np.eye(4)) for p in (near, far)]


def test_flying_pixels_only_at_depth_edges():
    intr = Intrinsics.for_resolution(160, 120)
    clean = render_clean(
        _jump_scene(), T_camera_from_world=np.eye(4), intrinsics=intr, projector_baseline_m=0.0
    )
    edge_col = int(np.argmax(clean.depth_m[60] > 1.0))  # first column of the far wall
    assert 60 < edge_col < 100
    only_flying = dataclasses.replace(
        NOISE_LEVELS["low"],
        name="flying only",
        axial_a_m=0.0,
        axial_b_per_m=0.0,
        disparity_subpixel=0.0,
        grazing_drop_prob=0.0,
        edge_drop_prob=0.0,
        lateral_fraction=0.0,
        random_drop_fraction=0.0,
        speckle_fraction=0.0,
        projector_shadow=False,
        flying_fraction=1.0,
    )
    depth, _ = add_sensor_noise(clean, noise=only_flying, rng=np.random.default_rng(3))
    between = (depth > 0.805) & (depth < 1.195)  # neither surface: flying
    cols = np.nonzero(between)[1]
    assert between.sum() >= 100  # the whole edge flies...
    assert cols.min() >= edge_col - 2 and cols.max() <= edge_col + 1  # ...and nothing else does
    none, _ = add_sensor_noise(
        clean, noise=dataclasses.replace(only_flying, flying_fraction=0.0), rng=np.random.default_rng(3)
    )
    assert not ((none > 0.805) & (none < 1.195)).any()


def test_depth_is_delivered_in_millimetres():
    intr = Intrinsics.for_resolution(160, 120)
    clean = render_clean(_plane_scene(0.9, tilt_deg=30.0), T_camera_from_world=np.eye(4), intrinsics=intr)
    for level in ("low", "high"):
        depth, _ = add_sensor_noise(clean, noise=NOISE_LEVELS[level], rng=np.random.default_rng(1))
        mm = depth[depth > 0].astype(np.float64) * 1000.0
        assert len(mm) > 10000
        np.testing.assert_allclose(mm, np.rint(mm), atol=1e-3)
        assert len(np.unique(np.rint(mm))) > 20  # a tilted plane spans many steps


def test_plain_surfaces_are_uniform_colours():
    kw = dict(object_name="cereal_box", motion="static", noise="none", n_frames=2, seed=3, **SMALL)
    spread = {}
    for texture in ("textured", "plain"):
        frame = plan_sequence(texture=texture, **kw).render(0)
        rgb = frame.clean.rgb[frame.mask]
        chroma = rgb / np.maximum(rgb.sum(1, keepdims=True), 1e-6)  # shading changes brightness only
        spread[texture] = chroma.std(0).max()
    assert spread["plain"] < 1e-3 < spread["textured"]


# ---------------------------------------------------------------- hands


@pytest.mark.parametrize(
    "object_name, motion, hand",
    [
        ("laptop", "articulate", "hand"),
        ("slide_case", "carry_articulate", "hand"),
        ("book", "carry", "gripper"),
        ("mug", "static", "hand"),
    ],
)
def test_hand_occludes_the_object_and_is_never_in_its_mask(tmp_path, object_name, motion, hand):
    out = generate_sequence(
        tmp_path / "seq",
        object_name=object_name,
        motion=motion,
        noise="low",
        n_frames=4,
        seed=2,
        hand=hand,
        **SMALL,
    )
    truth = json.loads((out / "truth.json").read_text())
    assert len(truth["holders"]) == (2 if motion == "carry_articulate" else 1)
    assert {h["kind"] for h in truth["holders"]} == {hand}
    assert (truth["holders"][0]["holds"] is None) == (motion == "static")
    bare = plan_sequence(object_name=object_name, motion=motion, noise="none", n_frames=4, seed=2, **SMALL)
    hidden = 0
    for i in range(4):
        mask = cv2.imread(str(out / "mask" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED) > 0
        hand_px = cv2.imread(str(out / "hand" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED) > 0
        parts = cv2.imread(str(out / "parts" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert hand_px.sum() > 20 and not (hand_px & mask).any()
        np.testing.assert_array_equal(parts > 0, mask)
        hidden += int((bare.render(i).mask & hand_px).sum())
    assert hidden > 0  # the hand hides part of the object
    if motion == "static":  # it moves in front, not touching
        poses = np.array(truth["object_poses"])
        np.testing.assert_allclose(poses[0][:3, :3], poses[-1][:3, :3], atol=1e-12)
        assert truth["joint_positions"] == [None] * 4
        seq = plan_sequence(
            object_name=object_name, motion=motion, noise="low", n_frames=4, seed=2, hand=hand, **SMALL
        )
        for i in range(4):
            meshes = seq.meshes(i)
            obj = np.concatenate([m.vertices_m for m in meshes if m.part >= 0])
            held = np.concatenate([m.vertices_m for m in meshes if m.part == -2])
            centre = 0.5 * (obj.min(0) + obj.max(0))
            radius = np.linalg.norm(obj - centre, axis=1).max()
            assert np.linalg.norm(held - centre, axis=1).min() > radius + 0.02


def test_arms_reach_out_of_the_picture():
    """A real arm enters from outside the picture: whenever a hand or gripper is in view, its
    mask reaches the image border (it never ends in mid-air or comes up through the table)."""
    for i, plan in enumerate(preset_plans("benchmark")):
        if plan.hand == "none":
            continue
        seq = plan_sequence(
            object_name=plan.object_name,
            motion=plan.motion,
            noise="none",
            n_frames=plan.n_frames,
            seed=i,
            texture=plan.texture,
            hand=plan.hand,
            **SMALL,
        )
        for f in (0, plan.n_frames // 2, plan.n_frames - 1):
            hand = seq.render(f).hand
            if hand.any():
                edge = hand[0].any() or hand[-1].any() or hand[:, 0].any() or hand[:, -1].any()
                assert edge, f"{plan.name} frame {f}: the arm ends inside the picture"


@pytest.mark.parametrize("noise", ["low", "high"])
def test_the_rig_records_its_gripper_colour(noise):
    from artclass_plugins.segmenters.hands import hsv_mask, parse_hsv

    kw = dict(object_name="book", motion="carry", noise=noise, n_frames=2, **SMALL)
    assert "gripper_hsv" not in plan_sequence(seed=2, hand="hand", **kw).meta
    inside = []
    for seed in range(4):  # both gripper colours
        seq = plan_sequence(seed=seed, hand="gripper", **kw)
        frame = seq.render(0)
        boxes = parse_hsv(seq.meta["gripper_hsv"])
        inside.append(hsv_mask(frame.rgb, boxes)[frame.hand].mean())
        assert hsv_mask(frame.rgb, boxes)[frame.mask].mean() < 0.5  # the red book is not the gripper
    assert min(inside) > 0.95


def test_two_grippers_of_two_colours_get_a_box_each():
    """A grey and a near-black gripper carry a pair of blue pliers (high noise): one box a colour.
    Every gripper pixel is in one of them, and half of the shaded pliers (measured 0.49); the one
    box that holds both colours, every dark colour, holds 0.83 of them."""
    from artclass_plugins.segmenters.hands import hsv_mask, parse_hsv

    kw = dict(object_name="pliers", motion="carry_articulate", noise="high", n_frames=2, **SMALL)
    seq = plan_sequence(seed=1, hand="gripper", **kw)
    frame = seq.render(0)
    boxes = parse_hsv(seq.meta["gripper_hsv"])
    assert len(boxes) == 2
    one = [((0, 0, 0), (180, 255, max(high[2] for _, high in boxes)))]
    assert hsv_mask(frame.rgb, boxes)[frame.hand].mean() > 0.99
    assert hsv_mask(frame.rgb, boxes)[frame.mask].mean() < 0.6 < hsv_mask(frame.rgb, one)[frame.mask].mean()


def test_hand_colours_span_human_skin():
    from artclass_plugins.synth.hands import SKIN_TONES, holder_pieces

    skins = [holder_pieces("hand", np.random.default_rng(s))[0].colour for s in range(200)]
    lightness = np.array([sum(c) / 3 for c in skins])
    assert lightness.min() < 0.35 and lightness.max() > 0.75
    lo, hi = np.min(SKIN_TONES, 0), np.max(SKIN_TONES, 0)
    assert all(np.all(lo - 1e-9 <= c) and np.all(np.asarray(c) <= hi + 1e-9) for c in skins)
    assert set(HANDS) == {"none", "hand", "gripper"}


# ---------------------------------------------------------------- motion and truth


def test_joint_axes_in_the_first_camera_frame_explain_the_part_motion():
    seq = plan_sequence(
        object_name="microwave", motion="articulate", noise="low", n_frames=6, seed=9, **SMALL
    )
    (joint,) = seq.truth["joints"]
    poses = np.array(seq.truth["part_poses"])  # camera_from_part, per frame
    door0, door5 = poses[0][1], poses[5][1]
    origin, axis = np.array(joint["origin_camera0_m"][5]), np.array(joint["axis_camera0"][5])
    dq = joint["state"][5] - joint["state"][0]
    R = rotation_about_axis(axis, dq)
    expect = np.eye(4)
    expect[:3, :3], expect[:3, 3] = R, origin - R @ origin
    np.testing.assert_allclose(door5, expect @ door0, atol=1e-8)  # the camera does not move
    assert abs(dq) > math.radians(15)


def test_truth_carries_visible_points_per_part(tmp_path):
    out = generate_sequence(
        tmp_path / "lamp",
        object_name="desk_lamp",
        motion="articulate",
        noise="low",
        n_frames=4,
        seed=1,
        hand="hand",
        **SMALL,
    )
    truth = json.loads((out / "truth.json").read_text())
    assert [p["parent"] for p in truth["parts"]] == [-1, 0, 1]
    assert truth["sensor"]["fx_px"] == Intrinsics.for_resolution(160, 120).fx_px
    for i in range(4):
        parts = cv2.imread(str(out / "parts" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        depth = cv2.imread(str(out / "depth" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        for k in range(3):
            assert truth["part_valid_px"][i][k] == int(((parts == k + 1) & (depth > 0)).sum())
            pts = np.array(truth["part_points_m"][i][k]).reshape(-1, 3)
            assert len(pts) == min(256, truth["part_valid_px"][i][k])
            # Each sample, posed by its part's pose, lands on a depth pixel of that part.
            P = np.array(truth["part_poses"][i][k])
            cam = pts @ P[:3, :3].T + P[:3, 3]
            K = Intrinsics.for_resolution(160, 120)
            u = np.rint(K.fx_px * cam[:, 0] / cam[:, 2] + K.cx_px).astype(int)
            v = np.rint(K.fy_px * cam[:, 1] / cam[:, 2] + K.cy_px).astype(int)
            assert (parts[v, u] == k + 1).all()
    seq = FolderReader().sequences(out)[0]
    assert seq.pair_truth(0, 3) == seq.pair_truth_legacy(0, 3) == "AM"  # both arms turn 10-30 deg


# ---------------------------------------------------------------- motion and truth (continued)


@pytest.mark.slow
def test_articulate_moves_the_joint_and_keeps_the_base(tmp_path):
    for name in ("laptop", "drawer"):
        spec = OBJECTS[name]
        out = generate_sequence(
            tmp_path / name, object_name=name, motion="articulate", noise="low", n_frames=10, seed=3, **SMALL
        )
        truth = json.loads((out / "truth.json").read_text())
        meta = json.loads((out / "meta.json").read_text())
        assert meta["label"] == "articulated" and meta["joint_type"] == spec.joint_type
        q = np.array(truth["joint_positions"])
        travel = abs(q[-1] - q[0])
        assert spec.joint.travel[0] - 1e-9 <= travel <= spec.joint.travel[1] + 1e-9
        assert np.all(np.diff(q) * np.sign(q[-1] - q[0]) >= -1e-12)  # monotonic, smooth
        lo, hi = spec.joint.limits
        assert q.min() >= lo - 1e-9 and q.max() <= hi + 1e-9
        poses = np.array(truth["object_poses"])
        np.testing.assert_allclose(poses, poses[:1].repeat(len(poses), 0), atol=1e-12)
        # What the camera sees of the moving part, per frame, for the per-pair truth.
        seen = truth["part_visibility"]
        assert len(seen) == len(q) and all(0.0 < s["share"] < 1.0 for s in seen)
        if name == "laptop":  # the lid's visible points reach centimetres from its hinge
            assert all(0.03 < s["axis_distance_m"] < 0.5 for s in seen)
        # The moving part's poses realise exactly that joint travel.
        child = np.array(truth["moving_part_poses"])
        rel = np.linalg.inv(child[0]) @ child[-1]
        if spec.joint_type == "revolute":
            assert _rotation_angle(rel[:3, :3]) == pytest.approx(travel, abs=1e-6)
        else:
            assert np.linalg.norm(rel[:3, 3]) == pytest.approx(travel, abs=1e-6)
            np.testing.assert_allclose(rel[:3, :3], np.eye(3), atol=1e-9)
        # ...and the images show it: the object's silhouette changes.
        m0 = cv2.imread(str(out / "mask" / "000000.png"), cv2.IMREAD_UNCHANGED) > 0
        m9 = cv2.imread(str(out / "mask" / "000009.png"), cv2.IMREAD_UNCHANGED) > 0
        assert (m0 ^ m9).sum() > 30


def test_carry_moves_the_object_rigidly():
    for name, motion in (("mug", "carry"), ("laptop", "carry"), ("pliers", "carry_articulate")):
        seq = plan_sequence(object_name=name, motion=motion, noise="low", n_frames=12, seed=8, **SMALL)
        poses = np.array(seq.truth["object_poses"])
        rel = np.linalg.inv(poses[0]) @ poses[-1]
        angle = math.degrees(_rotation_angle(rel[:3, :3]))
        shift = np.linalg.norm(poses[-1][:3, 3] - poses[0][:3, 3])
        assert 9.0 <= angle <= 41.0, angle
        assert shift > 0.02, shift
        q = seq.truth["joint_positions"]
        if OBJECTS[name].joint is None:
            assert q == [None] * 12 and seq.meta["label"] == "rigid"
        elif motion == "carry":
            assert len(set(q)) == 1 and seq.meta["label"] == "rigid"
        else:
            assert abs(q[-1] - q[0]) > 0.1 and seq.meta["label"] == "articulated"
        # The object never dips into the table.
        for i in range(12):
            T_wo = seq.trajectory.T_world_from_object[i]
            qi = None if q[i] is None else q[i]
            for m in object_meshes(OBJECTS[name], qi, T_wo):
                assert m.vertices_m[:, 2].min() > 0.0


def test_static_truth_has_no_motion():
    seq = plan_sequence(object_name="microwave", motion="static", noise="high", n_frames=10, seed=2, **SMALL)
    assert seq.meta["label"] == "static"
    q = seq.truth["joint_positions"]
    assert len(set(q)) == 1
    poses = np.array(seq.truth["object_poses"])
    for P in poses[1:]:
        rel = np.linalg.inv(poses[0]) @ P
        assert np.linalg.norm(rel[:3, 3]) <= 1e-3 + 1e-9  # camera jitter only
        assert _rotation_angle(rel[:3, :3]) < 1e-9


def test_rigid_objects_cannot_articulate(tmp_path):
    with pytest.raises(ValueError, match="rigid"):
        generate_sequence(
            tmp_path / "x", object_name="mug", motion="articulate", noise="low", n_frames=4, seed=0, **SMALL
        )
    with pytest.raises(ValueError, match="noise"):
        plan_sequence(object_name="mug", motion="carry", noise="medium", n_frames=4, seed=0)
    assert not (tmp_path / "x").exists()


# ---------------------------------------------------------------- writer


def test_native_layout(tmp_path):
    out = generate_sequence(
        tmp_path / "seq",
        object_name="box_lid",
        motion="carry_articulate",
        noise="high",
        n_frames=5,
        seed=4,
        **SMALL,
    )
    assert sorted(p.name for p in out.iterdir()) == [
        "depth",
        "hand",
        "mask",
        "meta.json",
        "parts",
        "rgb",
        "truth.json",
    ]
    meta = json.loads((out / "meta.json").read_text())
    assert set(meta) == {
        "fx",
        "fy",
        "cx",
        "cy",
        "depth_scale",
        "label",
        "object",
        "motion",
        "noise",
        "seed",
        "generator",
        "joint_type",
        "texture",
        "hand",
    }
    intr = Intrinsics.for_resolution(160, 120)
    assert (meta["fx"], meta["fy"], meta["cx"], meta["cy"]) == (
        intr.fx_px,
        intr.fy_px,
        intr.cx_px,
        intr.cy_px,
    )
    assert meta["depth_scale"] == 1000 and meta["label"] == "articulated"
    assert meta["object"] == "box_lid" and meta["seed"] == 4 and meta["noise"] == "high"
    assert meta["generator"].startswith("artclass synth ")
    truth = json.loads((out / "truth.json").read_text())
    assert truth["joint_type"] == "revolute"
    assert len(truth["joint_positions"]) == 5 and len(truth["object_poses"]) == 5
    assert np.array(truth["object_poses"]).shape == (5, 4, 4)
    for sub in ("rgb", "depth", "mask", "hand", "parts"):
        assert sorted(p.name for p in (out / sub).iterdir()) == [f"{i:06d}.png" for i in range(5)]
    depth = cv2.imread(str(out / "depth" / "000002.png"), cv2.IMREAD_UNCHANGED)
    rgb = cv2.imread(str(out / "rgb" / "000002.png"), cv2.IMREAD_UNCHANGED)
    mask = cv2.imread(str(out / "mask" / "000002.png"), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and depth.shape == (120, 160)
    assert rgb.dtype == np.uint8 and rgb.shape == (120, 160, 3)
    assert mask.dtype == np.uint8 and set(np.unique(mask)) == {0, 255}
    valid = depth[depth > 0].astype(float) / meta["depth_scale"]
    assert 0.3 < valid.min() and valid.max() < 4.5
    # The object is where truth puts it: its origin projects inside the mask's bounding box.
    P = np.array(truth["object_poses"][2])
    x, y, z = P[:3, 3]
    u, v = intr.fx_px * x / z + intr.cx_px, intr.fy_px * y / z + intr.cy_px
    vs, us = np.nonzero(mask)
    assert us.min() - 3 <= u <= us.max() + 3 and vs.min() - 3 <= v <= vs.max() + 3


def test_same_seed_same_bytes_different_seed_different(tmp_path):
    kw = dict(
        object_name="pliers",
        motion="articulate",
        noise="high",
        n_frames=3,
        hand="hand",
        texture="plain",
        **SMALL,
    )
    a = _digest(generate_sequence(tmp_path / "a", seed=7, **kw))
    b = _digest(generate_sequence(tmp_path / "b", seed=7, **kw))
    c = _digest(generate_sequence(tmp_path / "c", seed=8, **kw))
    assert a == b
    differing = [k for k in a if a[k] != c[k]]
    assert "truth.json" in differing and "depth/000000.png" in differing
    assert "hand/000000.png" in differing


def test_writer_refuses_to_overwrite(tmp_path):
    target = tmp_path / "seq"
    target.mkdir()
    (target / "notes.txt").write_text("keep me")
    kw = dict(object_name="can", motion="static", noise="low", n_frames=2, seed=0, **SMALL)
    with pytest.raises(FileExistsError, match="not empty"):
        generate_sequence(target, **kw)
    assert sorted(p.name for p in target.iterdir()) == ["notes.txt"]
    generate_sequence(target, overwrite=True, **kw)
    generate_sequence(target, overwrite=True, **dict(kw, n_frames=3))
    assert (target / "notes.txt").read_text() == "keep me"
    assert len(list((target / "rgb").iterdir())) == 3
    with pytest.raises(FileExistsError):
        generate_sequence(target, **kw)


# ---------------------------------------------------------------- presets


@pytest.mark.slow
def test_smoke_preset(tmp_path):
    paths = generate_set(tmp_path / "set", preset="smoke", seed=1)
    assert 3 <= len(paths) <= 4
    labels = {json.loads((p / "meta.json").read_text())["label"] for p in paths}
    assert labels == {"articulated", "rigid", "static"}
    index = json.loads((tmp_path / "set" / "index.json").read_text())
    assert [e["name"] for e in index["sequences"]] == [p.name for p in paths]
    assert [e["seed"] for e in index["sequences"]] == [1000 + i for i in range(len(paths))]
    with pytest.raises(FileExistsError):
        generate_set(tmp_path / "set", preset="smoke", seed=1)


@pytest.mark.parametrize(
    "preset, size", [("benchmark", (320, 240)), ("benchmark-vga", (640, 480)), ("benchmark-rs", (848, 480))]
)
def test_benchmark_preset_is_balanced(preset, size):
    plans = preset_plans(preset)
    assert 60 <= len(plans) <= 70
    assert set(PRESETS) == {"sample", "benchmark", "benchmark-vga", "benchmark-rs", "smoke"}
    labels = [MOTIONS[p.motion].label for p in plans]
    n = len(plans)
    assert 0.45 <= labels.count("articulated") / n <= 0.55
    assert 0.2 <= labels.count("rigid") / n <= 0.3
    assert 0.2 <= labels.count("static") / n <= 0.3
    assert {p.object_name for p in plans} == set(OBJECTS)  # every object is in it
    assert {p.motion for p in plans} == set(MOTIONS)
    assert {p.noise for p in plans} == {"low", "high"}
    assert {p.texture for p in plans} == {"textured", "plain"}
    assert 0.6 <= sum(p.hand != "none" for p in plans) / n <= 0.8  # most are handled
    assert {p.hand for p in plans if p.motion == "static"} == set(HANDS)
    assert {OBJECTS[p.object_name].joint_type for p in plans if MOTIONS[p.motion].moves_joint} == {
        "revolute",
        "prismatic",
    }
    assert all((p.width, p.height) == size and 24 <= p.n_frames <= 30 for p in plans)
    assert [p.name for p in plans] == [p.name for p in preset_plans("benchmark")]
    assert len({p.name for p in plans}) == n


def test_sample_data_matches_the_sample_preset():
    root = Path(__file__).resolve().parents[1] / "sample_data"
    if not (root / "index.json").exists():
        pytest.skip("sample_data/ not generated")
    index = json.loads((root / "index.json").read_text())
    assert index["preset"] == "sample"
    names = [p.name for p in preset_plans("sample")]
    assert [e["name"] for e in index["sequences"]] == names
    for e in index["sequences"]:
        meta = json.loads((root / e["name"] / "meta.json").read_text())
        assert meta["label"] == e["label"] and meta["seed"] == e["seed"]
        assert len(list((root / e["name"] / "depth").iterdir())) == e["n_frames"]
        # The committed files were written by an earlier generator version: the current one draws
        # the same sequences (trajectories, truth, masks) from the same seeds, and adds truth fields.
        seq = plan_sequence(
            object_name=e["object_name"],
            motion=e["motion"],
            noise=e["noise"],
            n_frames=e["n_frames"],
            seed=e["seed"],
            width=e["width"],
            height=e["height"],
        )
        written = json.loads((root / e["name"] / "truth.json").read_text())
        shared = set(written) & set(seq.truth)
        assert {"joint_positions", "object_poses", "moving_part_poses"} <= shared
        assert {k: written[k] for k in shared} == json.loads(json.dumps({k: seq.truth[k] for k in shared}))
        assert ("part_visibility" in written) == (seq.truth["joint_positions"][0] is not None)
        assert {k: v for k, v in meta.items() if k != "generator"} == {
            k: v for k, v in seq.meta.items() if k in meta and k != "generator"
        }
        frame = seq.render(e["n_frames"] - 1)
        mask = (
            cv2.imread(str(root / e["name"] / "mask" / f"{e['n_frames'] - 1:06d}.png"), cv2.IMREAD_UNCHANGED)
            > 0
        )
        assert (mask == frame.mask).mean() > 0.999


# ---------------------------------------------------------------- command line


@pytest.mark.slow
def test_hook_register_commands_sample(tmp_path, capsys):
    """``artclass sample OUT --preset smoke`` through the real command line (plugin registry)."""
    from artclass_core.cli import main

    out = tmp_path / "smoke"
    assert main(["sample", str(out), "--preset", "smoke", "--seed", "3"]) == 0
    names = [p.name for p in preset_plans("smoke")]
    assert sorted(p.name for p in out.iterdir()) == sorted(names + ["index.json"])
    first = _digest(out)
    assert main(["sample", str(out), "--preset", "smoke", "--seed", "3"]) == 2
    assert "refusing to overwrite" in capsys.readouterr().err
    assert main(["sample", str(out), "--preset", "smoke", "--seed", "3", "--overwrite"]) == 0
    assert _digest(out) == first
