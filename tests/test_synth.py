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
from artclass_plugins.synth.sensors import add_tof_noise, draw_sensor

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
    assert set(MOTIONS) == {"articulate", "carry_articulate", "carry", "static", "spin", "slide", "lift"}
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


def _quiet(level):
    """``level`` with every effect switched off (but a disparity bias, when one is given)."""
    return dataclasses.replace(
        level,
        axial_a_m=0.0,
        axial_b_per_m=0.0,
        disparity_subpixel=0.0,
        grazing_drop_prob=0.0,
        edge_drop_prob=0.0,
        lateral_fraction=0.0,
        random_drop_fraction=0.0,
        speckle_fraction=0.0,
        projector_shadow=False,
        flying_fraction=0.0,
        depth_step_m=0.0,
    )


def test_flying_pixels_only_at_depth_edges():
    intr = Intrinsics.for_resolution(160, 120)
    clean = render_clean(
        _jump_scene(), T_camera_from_world=np.eye(4), intrinsics=intr, projector_baseline_m=0.0
    )
    edge_col = int(np.argmax(clean.depth_m[60] > 1.0))  # first column of the far wall
    assert 60 < edge_col < 100
    only_flying = dataclasses.replace(_quiet(NOISE_LEVELS["low"]), name="flying only", flying_fraction=1.0)
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
    assert set(PRESETS) == {"sample", "benchmark", "benchmark-vga", "benchmark-rs", "smoke", "benchmark-wild"}
    labels = [MOTIONS[p.motion].label for p in plans]
    n = len(plans)
    assert 0.45 <= labels.count("articulated") / n <= 0.55
    assert 0.2 <= labels.count("rigid") / n <= 0.3
    assert 0.2 <= labels.count("static") / n <= 0.3
    assert {p.object_name for p in plans} == set(OBJECTS) - {"kettle"}  # every object but the newest
    assert {p.motion for p in plans} == {"articulate", "carry_articulate", "carry", "static"}
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


# ---------------------------------------------------------------- randomised sequences (benchmark-wild)

WILD = dict(noise="drawn", hand="drawn", texture="drawn", wild=True)


def test_structured_light_bias_field_is_smooth_and_grows_with_range():
    """A fixed disparity error over the image: its depth bias has the drawn RMS at 1 m, grows as z**2,
    and is smooth (neighbouring pixels agree far better than the field's spread)."""
    intr = Intrinsics.for_resolution(160, 120)
    for seed in range(3):
        sensor = draw_sensor("structured_light", np.random.default_rng(seed), intrinsics=intr)
        assert 0.001 <= sensor.bias_rms_1m_m <= 0.004  # a few millimetres at 1 m
        bias = sensor.disparity_bias_px(intr)
        rms = {}
        for z in (0.6, 1.0, 1.5):
            clean = render_clean(_plane_scene(z), T_camera_from_world=np.eye(4), intrinsics=intr)
            depth, _ = add_sensor_noise(
                clean, noise=_quiet(sensor.level), rng=np.random.default_rng(0), disparity_bias_px=bias
            )
            err = depth.astype(float) - clean.depth_m
            rms[z] = float(np.sqrt(np.mean(err**2)))
            assert np.abs(np.diff(err, axis=1)).max() < 0.1 * np.ptp(err)  # a few cycles across at most
        assert rms[1.0] == pytest.approx(sensor.bias_rms_1m_m, rel=0.05)
        assert rms[1.5] / rms[0.6] == pytest.approx((1.5 / 0.6) ** 2, rel=0.1)
    # with every other effect on, the bias still shows once the per-pixel noise is smoothed away
    sensor = draw_sensor("structured_light", np.random.default_rng(7), intrinsics=intr)
    smooth = {}
    for z in (0.6, 1.5):
        clean = render_clean(_plane_scene(z), T_camera_from_world=np.eye(4), intrinsics=intr)
        depth, _ = add_sensor_noise(
            clean,
            noise=sensor.level,
            rng=np.random.default_rng(1),
            disparity_bias_px=sensor.disparity_bias_px(intr),
        )
        valid = (depth > 0).astype(np.float32)
        err = np.where(depth > 0, depth - clean.depth_m, 0).astype(np.float32)
        mean = cv2.blur(err, (15, 15)) / np.maximum(cv2.blur(valid, (15, 15)), 1e-6)
        smooth[z] = float(np.sqrt(np.mean((mean - np.median(mean)) ** 2)))
    assert smooth[1.5] > 2.5 * smooth[0.6]


def test_structured_light_depth_takes_disparity_steps():
    """The delivered depth lies on the disparity grid 1 / z = k s / (f b) (to the 1 mm unit)."""
    intr = Intrinsics.for_resolution(160, 120)
    level = draw_sensor("structured_light", np.random.default_rng(4), intrinsics=intr).level
    clean = render_clean(_plane_scene(1.4, tilt_deg=20.0), T_camera_from_world=np.eye(4), intrinsics=intr)
    depth, _ = add_sensor_noise(clean, noise=level, rng=np.random.default_rng(2))
    z = depth[depth > 0].astype(float)
    step_inv = level.disparity_subpixel / (level.focal_px * level.baseline_m)
    k = 1.0 / (z * step_inv)
    grid = 1.0 / (np.rint(k) * step_inv)
    speckle = np.abs(z - np.median(z)) > 0.15
    assert np.mean(np.abs(z - grid)[~speckle] <= 0.0005 + 1e-9) > 0.99
    assert len(np.unique(np.rint(k[~speckle]))) >= 3  # a tilted plane spans several steps


def _two_tone_plane(dark: float, light: float) -> list[SceneMesh]:
    """A plane at 1 m facing the camera: its left half of reflectance ``dark``, its right ``light``."""
    out = []
    for x, value in ((-1.0, dark), (1.0, light)):
        p = box((2.0, 4.0, 0.1), (x, 0.0, 1.05), (value, value, value), pattern="plain")
        out.append(SceneMesh(p.vertices_m, p.triangles, -1, p, np.eye(4)))
    return out


def test_time_of_flight_fails_on_dark_surfaces():
    """Amplitude is reflectance x cos / z**2: a 4.5 % surface at 1 m is noisy and mostly lost, a 60 %
    one is kept and quiet."""
    intr = Intrinsics.for_resolution(160, 120)
    clean = render_clean(_two_tone_plane(0.045, 0.6), T_camera_from_world=np.eye(4), intrinsics=intr)
    left, right = np.zeros((120, 160), bool), np.zeros((120, 160), bool)
    left[:, 5:70], right[:, 90:155] = True, True
    for seed in range(3):
        sensor = dataclasses.replace(
            draw_sensor("time_of_flight", np.random.default_rng(seed), intrinsics=intr), amplitude_min=0.04
        )
        depth, _ = add_tof_noise(clean, sensor=sensor, fx_px=intr.fx_px, rng=np.random.default_rng(seed))
        kept = depth > 0
        assert kept[left].mean() < 0.2 and kept[right].mean() > 0.95
        noisy = depth[left & kept] - 1.0
        assert np.std(noisy) > 2 * np.std(depth[right & kept] - 1.0)


def test_time_of_flight_reads_concave_corners_too_far():
    """Multipath: where the table meets the wall (a concave corner) the depth reads too far; on the
    flat table and wall far from it, it reads true."""
    from artclass_plugins.synth.render import WALL_Y_M

    intr = Intrinsics.for_resolution(160, 120)
    T_cw = look_at([0.0, WALL_Y_M - 0.75, 0.45], [0.0, WALL_Y_M, 0.0])
    clean = render_clean(room_meshes(), T_camera_from_world=T_cw, intrinsics=intr, projector_baseline_m=0.0)
    sensor = dataclasses.replace(
        draw_sensor("time_of_flight", np.random.default_rng(0), intrinsics=intr),
        sigma_1m_m=1e-7,
        amplitude_min=1e-6,
        wiggle_m=0.0,
        flying_fraction=0.0,
        edge_drop_prob=0.0,
        random_drop_fraction=0.0,
        multipath_gain=0.8,
        depth_step_m=1e-6,
    )
    depth, _ = add_tof_noise(clean, sensor=sensor, fx_px=intr.fx_px, rng=np.random.default_rng(0))
    pts = _backproject(clean.depth_m, intr)
    T_wc = np.linalg.inv(T_cw)
    world = pts @ T_wc[:3, :3].T + T_wc[:3, 3]
    corner = np.hypot(world[..., 1] - WALL_Y_M, world[..., 2])  # distance to the corner line
    ok = (clean.depth_m > 0) & (depth > 0)
    err = depth - clean.depth_m
    near, far = ok & (corner < 0.03), ok & (corner > 0.25)
    assert near.sum() > 50 and far.sum() > 500
    assert np.median(err[near]) > 0.003
    assert np.abs(np.median(err[far])) < 0.0005


def test_multipath_bias_changes_gradually_as_an_edge_comes_near():
    """A hand moving a pixel at a time towards a concave corner changes the corner's multipath bias a
    little at each step: scattered light fades with distance; it does not switch off at once."""
    from artclass_plugins.synth.sensors import multipath_bias_m

    h, w = 120, 160
    x = np.arange(w)
    trough = np.tile(1.0 + 0.06 * (1 - np.abs(x - w / 2) / (w / 2)), (h, 1))  # its middle is farthest
    corner = (slice(70, 110), slice(70, 90))
    biases = []
    for top in range(0, 50):  # a nearer square coming down to 11 px above the corner, a pixel a step
        depth = trough.copy()
        depth[top : top + 10, 70:90] = 0.5
        biases.append(multipath_bias_m(depth, fx_px=150.0, scale_m=0.05, gain=0.8, max_m=0.03)[corner])
    biases = np.array(biases)
    assert biases[0].max() > 0.002  # millimetres, far from the square
    before, after = biases[:-1], biases[1:]
    assert (after / before)[before > 0.001].min() > 0.75  # a pixel's step never switches it off


def test_stated_intrinsics_are_off_the_rendered_ones_within_bounds():
    from artclass_plugins.synth.sensors import draw_camera

    focal, principal, offset = [], [], []
    for seed in range(60):
        cam = draw_camera(640, 480, np.random.default_rng(seed))
        r, s = cam.rendered, cam.stated
        focal += [s.fx_px / r.fx_px - 1, s.fy_px / r.fy_px - 1]
        principal += [s.cx_px - r.cx_px, s.cy_px - r.cy_px]
        offset.append(np.hypot(*cam.colour_offset_px))
        assert 0.9 * 570 <= r.fx_px <= 1.1 * 570
    assert np.max(np.abs(focal)) <= 0.035 and np.max(np.abs(focal)) > 0.025
    assert np.max(np.abs(principal)) <= 5.0 and np.max(np.abs(principal)) > 4.0
    assert max(offset) <= 2.0 and max(offset) > 1.5 and min(offset) < 0.5
    # ...and the sequence's meta.json states them, while the truth keeps the rendered camera
    seq = plan_sequence(object_name="mug", motion="static", n_frames=2, seed=3, **SMALL, **WILD)
    stated, rendered = seq.truth["camera"]["stated"], seq.truth["camera"]["rendered"]
    assert [seq.meta[k] for k in ("fx", "fy", "cx", "cy")] == pytest.approx(
        [stated[k] for k in ("fx", "fy", "cx", "cy")], abs=1e-5
    )
    assert seq.meta["fx"] != pytest.approx(rendered["fx"], abs=1e-3)
    assert seq.truth["sensor"]["fx_px"] == pytest.approx(seq.intrinsics.fx_px, abs=1e-5)
    assert seq.intrinsics.fx_px == pytest.approx(rendered["fx"], abs=1e-5)


def test_colour_is_offset_from_depth_by_the_drawn_pixels():
    """Colour pixel (u + dx, v + dy) sees what depth pixel (u, v) sees: the noisy colour is the
    depth-registered rendering moved by the drawn offset (measured by phase correlation)."""
    for seed in (2, 5):
        seq = plan_sequence(
            object_name="cereal_box", motion="static", n_frames=2, seed=seed, width=320, height=240, **WILD
        )
        dx, dy = seq.truth["camera"]["colour_offset_px"]
        frame = seq.render(0)
        registered = cv2.cvtColor((frame.clean.rgb * 255).astype(np.float32), cv2.COLOR_RGB2GRAY)
        seen = cv2.cvtColor(frame.rgb.astype(np.float32), cv2.COLOR_RGB2GRAY)
        window = cv2.createHanningWindow(registered.shape[::-1], cv2.CV_32F)
        (mx, my), _ = cv2.phaseCorrelate(registered, seen, window)
        assert (mx, my) == pytest.approx((dx, dy), abs=0.15), (seed, (mx, my), (dx, dy))
    assert np.hypot(dx, dy) > 0.3  # a draw that moves it


def test_a_flip_of_180_degrees_in_12_frames_is_the_fastest_turn():
    from artclass_plugins.synth.motion import MAX_TURN_DEG_PER_FRAME, draw_motion_style, make_trajectory

    fastest = 0.0
    for seed in range(80):
        rng = np.random.default_rng(seed)
        style = draw_motion_style("carry", 24, rng)
        traj = make_trajectory(OBJECTS["cereal_box"], "carry", n_frames=24, rng=rng, style=style)
        R = traj.T_world_from_object[:, :3, :3]
        turns = [math.degrees(_rotation_angle(R[i].T @ R[i + 12])) for i in range(12)]
        fastest = max(fastest, max(turns))
        assert max(turns) <= 180.0 + 0.7  # the tremor's 0.3 degrees, twice
        assert abs(style["angle_deg"]) <= MAX_TURN_DEG_PER_FRAME * style["frames"] + 1e-6
    assert fastest > 170.0


def test_spins_slides_and_lifts():
    from artclass_plugins.synth.motion import draw_motion_style, make_trajectory

    for seed in range(6):
        rng = np.random.default_rng(seed)
        style = draw_motion_style("spin", 24, rng)
        traj = make_trajectory(OBJECTS["can"], "spin", n_frames=24, rng=rng, style=style)
        T = traj.T_world_from_object
        axes = T[:, :3, 2]  # the can's own axis does not move, but the can turns by the drawn angle
        np.testing.assert_allclose(axes, axes[:1].repeat(24, 0), atol=0.02)
        turn = math.degrees(_rotation_angle(T[0, :3, :3].T @ T[-1, :3, :3]))
        assert turn == pytest.approx(min(abs(style["angle_deg"]), 360 - abs(style["angle_deg"])), abs=1.0)
        style = draw_motion_style("slide", 24, rng)
        traj = make_trajectory(OBJECTS["book"], "slide", n_frames=24, rng=rng, style=style)
        T = traj.T_world_from_object
        np.testing.assert_allclose(T[:, 2, 3], 0.0, atol=1e-12)  # on the table...
        np.testing.assert_allclose(
            T[:, :3, 2], [[0.0, 0.0, 1.0]] * 24, atol=1e-12
        )  # ...turning about its normal
        assert np.linalg.norm(T[-1, :2, 3] - T[0, :2, 3]) > 0.03
    with pytest.raises(ValueError, match="revolution"):
        plan_sequence(object_name="book", motion="spin", noise="low", n_frames=4, seed=0)
    # lifted off a stand that stays: the stand is never the object, and the object clears it once up
    seq = plan_sequence(object_name="kettle", motion="lift", n_frames=24, seed=1, **SMALL, **WILD)
    style, stand = seq.truth["motion_style"], seq.truth["stand"]
    T = seq.trajectory.T_world_from_object
    low = [
        min(m.vertices_m[:, 2].min() for m in object_meshes(OBJECTS["kettle"], None, T[f])) for f in range(24)
    ]
    top = stand["height_m"] + 0.004
    assert low[0] == pytest.approx(stand["height_m"], abs=1e-6)
    assert min(low[style["start"] + style["lift_frames"] :]) > top
    for f in (0, 23):
        frame = seq.render(f)
        on_stand = frame.clean.part_ids == -3
        assert on_stand.sum() > 5 and not (on_stand & frame.mask).any()


def test_randomised_hands_sleeves_gloves_and_grippers_vary():
    import colorsys

    from artclass_plugins.synth.hands import SLEEVE_STYLES, gripper_limb, hand_limb

    limbs = [hand_limb(np.random.default_rng(s)) for s in range(80)]
    assert {limb.style["sleeve"] for limb in limbs} == set(SLEEVE_STYLES)
    assert 0.05 < np.mean(["glove" in limb.style for limb in limbs]) < 0.4
    sleeves = [limb.style["sleeve_colour"] for limb in limbs if "sleeve_colour" in limb.style]
    hsv = np.array([colorsys.rgb_to_hsv(*c) for c in sleeves])
    assert len(np.unique(np.floor(hsv[hsv[:, 1] > 0.3, 0] * 6))) == 6  # every hue
    assert hsv[:, 2].min() < 0.15 and hsv[:, 2].max() > 0.85  # dark and light
    # rounded fingers: every finger ends in a ball
    hand = limbs[0].hand
    balls = [
        p
        for p in hand
        if len(p.vertices_m) > 2
        and np.ptp(np.linalg.norm(p.vertices_m - p.vertices_m.mean(0), axis=1)) < 1e-6
    ]
    assert len(balls) >= 15
    bodies = np.array([gripper_limb(np.random.default_rng(s)).style["body"] for s in range(40)])
    ghsv = np.array([colorsys.rgb_to_hsv(*c) for c in bodies])
    assert len(np.unique(np.floor(ghsv[ghsv[:, 1] > 0.3, 0] * 6))) >= 5


def test_wrists_bend_and_arms_rise_away_from_the_camera():
    from artclass_plugins.synth.hands import MIN_ARM_ELEVATION_DEG, arm_poses, hand_limb

    limb = hand_limb(np.random.default_rng(0))
    T_wh = np.repeat(np.eye(4)[None], 24, axis=0)
    T_wh[:, :3, :3] = rotation_about_axis((1, 0, 0), math.radians(150))  # the forearm (-z) points up, back
    bends = []
    for seed in range(10):
        T_ha = arm_poses(limb, T_wh, np.random.default_rng(seed), bend_deg=30.0, sway_deg=20.0)
        d = T_wh[0, :3, :3] @ T_ha[:, :3, :3] @ [0.0, 0.0, -1.0]
        bend = np.degrees(np.arccos(np.clip(d @ (T_wh[0, :3, :3] @ [0.0, 0.0, -1.0]), -1, 1)))
        bends.append(np.ptp(bend))
        assert (np.degrees(np.arcsin(d[:, 2])) >= MIN_ARM_ELEVATION_DEG - 1e-6).all()
        np.testing.assert_allclose(T_ha[:, :3, 3], [limb.wrist_m] * 24)
    assert max(bends) > 10.0  # the wrist moves over the sequence
    # an arm pointing straight at the camera is turned away from it
    forearm = T_wh[0, :3, :3] @ [0.0, 0.0, -1.0]
    eye = (T_wh[0] @ np.r_[limb.wrist_m, 1.0])[:3] + 0.8 * forearm
    T_ha = arm_poses(limb, T_wh, np.random.default_rng(0), bend_deg=0.0, sway_deg=0.0, eye_world=eye)
    d = T_wh[0, :3, :3] @ T_ha[0, :3, :3] @ [0.0, 0.0, -1.0]
    assert np.degrees(np.arccos(np.clip(d @ forearm, -1, 1))) >= 45.0 - 1e-6


def _wild_preset(*, width: int, height: int, n_frames: int | None = None):
    """The benchmark-wild plans (seed 0) planned at a small size: (plan, SynthSequence) pairs."""
    for i, p in enumerate(preset_plans("benchmark-wild")):
        kw = dict(noise=p.noise, texture=p.texture, hand=p.hand, wild=True)
        yield (
            p,
            plan_sequence(
                object_name=p.object_name,
                motion=p.motion,
                n_frames=n_frames or p.n_frames,
                seed=i,
                width=width,
                height=height,
                **kw,
            ),
        )


def test_the_wild_preset_draws_every_holder_role():
    roles, kinds, sensors, two = set(), set(), set(), 0
    for _, seq in _wild_preset(width=64, height=48, n_frames=4):
        holders = seq.truth["holders"]
        roles |= {h["role"] for h in holders}
        kinds.add(seq.meta["hand"])
        sensors.add(seq.meta["noise"])
        two += sum(h["kind"] == "hand" for h in holders) == 2
        if seq.meta["hand"] == "gripper":
            from artclass_plugins.segmenters.hands import parse_hsv

            assert len(parse_hsv(seq.meta["gripper_hsv"])) >= 1
    assert roles == {"grasp", "rest", "pass", "pass_close"}
    assert kinds == {"none", "hand", "gripper"} and sensors == {"structured_light", "time_of_flight"}
    assert two >= 3


def test_a_resting_hand_touches_the_still_object_and_a_close_pass_nears_the_camera():
    found = set()
    for seed in range(40):
        seq = plan_sequence(
            object_name="cereal_box",
            motion="static",
            n_frames=6,
            seed=seed,
            hand="hand",
            width=64,
            height=48,
            noise="drawn",
            texture="drawn",
            wild=True,
        )
        for h in seq.holders:
            if h.role in found:
                continue
            found.add(h.role)
            world = [np.concatenate([m.vertices_m for m in seq.meshes(f) if m.part == -2]) for f in range(6)]
            obj = np.concatenate([m.vertices_m for m in seq.meshes(0) if m.part >= 0])
            if h.role == "rest":
                palm = h.T_world_from_holder[:, :3, 3]
                assert np.ptp(palm, axis=0).max() < 0.004  # it rests: a tremor of a millimetre or two
                hand_low = np.concatenate([place[:, 2] for place in world]).min()
                assert abs(hand_low - obj[:, 2].max()) < 0.01 or hand_low < obj[:, 2].max()
            if h.role == "pass_close":
                eye = np.linalg.inv(seq.trajectory.T_camera_from_world[0])[:3, 3]
                assert min(np.linalg.norm(w - eye, axis=1).min() for w in world) < 0.35
    assert {"rest", "pass_close"} <= found


@pytest.mark.slow
def test_randomised_arms_reach_out_of_the_picture():
    for p, seq in _wild_preset(width=80, height=60):
        for f in (0, p.n_frames - 1):
            hand = seq.render(f).hand
            if hand.any():
                assert hand[0].any() or hand[-1].any() or hand[:, 0].any() or hand[:, -1].any(), (p.name, f)


@pytest.mark.slow
def test_randomised_sequences_repeat_by_seed(tmp_path):
    kw = dict(object_name="laptop", motion="carry_articulate", n_frames=3, width=80, height=60, **WILD)
    a = _digest(generate_sequence(tmp_path / "a", seed=11, **kw))
    b = _digest(generate_sequence(tmp_path / "b", seed=11, **kw))
    c = _digest(generate_sequence(tmp_path / "c", seed=12, **kw))
    assert a == b
    assert {"meta.json", "truth.json", "depth/000000.png", "rgb/000000.png"} <= {k for k in a if a[k] != c[k]}
    meta = json.loads((tmp_path / "a" / "meta.json").read_text())
    assert meta["noise"] in ("structured_light", "time_of_flight") and meta["generator"].endswith("0.4.1")
    seq = FolderReader().sequences(tmp_path / "a")[0]  # read as any sequence, with its truth
    assert seq.pair_truth(0, 2) in ("AM", "RM", None)
    with pytest.raises(ValueError, match="randomised"):
        plan_sequence(object_name="mug", motion="carry", n_frames=2, seed=0, noise="low", wild=True)


def test_the_wild_preset_is_balanced():
    plans = preset_plans("benchmark-wild")
    labels = [MOTIONS[p.motion].label for p in plans]
    assert len(plans) == 70 and len({p.name for p in plans}) == 70
    assert (labels.count("articulated"), labels.count("rigid"), labels.count("static")) == (35, 18, 17)
    assert {p.object_name for p in plans} == set(OBJECTS) and {p.motion for p in plans} == set(MOTIONS)
    assert all((p.width, p.height, p.n_frames) == (640, 480, 24) and p.wild for p in plans)
