"""Tests of the synthetic RGB-D generator (real Open3D ray casting, no mocks)."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest

from artclass_plugins.synth import (
    MOTIONS,
    NOISE_LEVELS,
    OBJECTS,
    PRESETS,
    Intrinsics,
    T_object_from_child,
    generate_sequence,
    generate_set,
    plan_sequence,
    preset_plans,
)
from artclass_plugins.synth.motion import look_at
from artclass_plugins.synth.objects import box, object_extent_m
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
    R = np.array([[1, 0, 0], [0, math.cos(math.radians(tilt_deg)), -math.sin(math.radians(tilt_deg))],
                  [0, math.sin(math.radians(tilt_deg)), math.cos(math.radians(tilt_deg))]])
    centre = R @ np.array([0.0, 0.0, 0.05]) + [0.0, 0.0, distance_m]
    piece = box((4.0, 4.0, 0.1), tuple(centre), (0.5, 0.5, 0.5), R=R)
    return [SceneMesh(piece.vertices_m, piece.triangles, -1, piece, np.eye(4))]


def _rotation_angle(R: np.ndarray) -> float:
    return math.acos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))


def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


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
        depth, _ = add_sensor_noise(clean, noise=NOISE_LEVELS[level],
                                    rng=np.random.default_rng(5))
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
    clean = render_clean(_plane_scene(1.0, tilt_deg=70.0), T_camera_from_world=np.eye(4),
                         intrinsics=intr)
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
    frame = render_clean(room_meshes() + object_meshes(spec, None, T_wo),
                         T_camera_from_world=T_cw, intrinsics=intr)
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
    seq = plan_sequence(object_name="laptop", motion="articulate", noise="none", n_frames=4,
                        seed=11, width=320, height=240)
    frame = seq.render(2)
    traj = seq.trajectory
    q = float(traj.joint_positions[2])
    obj = o3d.t.geometry.RaycastingScene()
    for m in object_meshes(OBJECTS["laptop"], q, traj.T_world_from_object[2]):
        obj.add_triangles(o3d.core.Tensor(m.vertices_m.astype(np.float32)),
                          o3d.core.Tensor(m.triangles))
    room = o3d.t.geometry.RaycastingScene()
    for m in room_meshes():
        room.add_triangles(o3d.core.Tensor(m.vertices_m.astype(np.float32)),
                           o3d.core.Tensor(m.triangles))
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
    out = generate_sequence(tmp_path / "mug", object_name="mug", motion="static", noise="low",
                            n_frames=2, seed=1, width=320, height=240)
    rgb = cv2.cvtColor(cv2.imread(str(out / "rgb" / "000000.png")), cv2.COLOR_BGR2RGB)
    mask = cv2.imread(str(out / "mask" / "000000.png"), cv2.IMREAD_UNCHANGED) == 255
    r, g, b = rgb[mask].astype(float).mean(0)
    assert b < 0.5 * r and b < 0.5 * g  # the mug is yellow


# ---------------------------------------------------------------- motion and truth


def test_articulate_moves_the_joint_and_keeps_the_base(tmp_path):
    for name in ("laptop", "drawer"):
        spec = OBJECTS[name]
        out = generate_sequence(tmp_path / name, object_name=name, motion="articulate",
                                noise="low", n_frames=10, seed=3, **SMALL)
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
        if name == "laptop":   # the lid's visible points reach centimetres from its hinge
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
        seq = plan_sequence(object_name=name, motion=motion, noise="low", n_frames=12, seed=8,
                            **SMALL)
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
    seq = plan_sequence(object_name="microwave", motion="static", noise="high", n_frames=10,
                        seed=2, **SMALL)
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
        generate_sequence(tmp_path / "x", object_name="mug", motion="articulate",
                          noise="low", n_frames=4, seed=0, **SMALL)
    with pytest.raises(ValueError, match="noise"):
        plan_sequence(object_name="mug", motion="carry", noise="medium", n_frames=4, seed=0)
    assert not (tmp_path / "x").exists()


# ---------------------------------------------------------------- writer


def test_native_layout(tmp_path):
    out = generate_sequence(tmp_path / "seq", object_name="box_lid", motion="carry_articulate",
                            noise="high", n_frames=5, seed=4, **SMALL)
    assert sorted(p.name for p in out.iterdir()) == ["depth", "mask", "meta.json", "rgb",
                                                     "truth.json"]
    meta = json.loads((out / "meta.json").read_text())
    assert set(meta) == {"fx", "fy", "cx", "cy", "depth_scale", "label", "object", "motion",
                         "noise", "seed", "generator", "joint_type"}
    intr = Intrinsics.for_resolution(160, 120)
    assert (meta["fx"], meta["fy"], meta["cx"], meta["cy"]) == (
        intr.fx_px, intr.fy_px, intr.cx_px, intr.cy_px)
    assert meta["depth_scale"] == 1000 and meta["label"] == "articulated"
    assert meta["object"] == "box_lid" and meta["seed"] == 4 and meta["noise"] == "high"
    assert meta["generator"].startswith("artclass synth ")
    truth = json.loads((out / "truth.json").read_text())
    assert truth["joint_type"] == "revolute"
    assert len(truth["joint_positions"]) == 5 and len(truth["object_poses"]) == 5
    assert np.array(truth["object_poses"]).shape == (5, 4, 4)
    for sub in ("rgb", "depth", "mask"):
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
    kw = dict(object_name="pliers", motion="articulate", noise="high", n_frames=3, **SMALL)
    a = _digest(generate_sequence(tmp_path / "a", seed=7, **kw))
    b = _digest(generate_sequence(tmp_path / "b", seed=7, **kw))
    c = _digest(generate_sequence(tmp_path / "c", seed=8, **kw))
    assert a == b
    differing = [k for k in a if a[k] != c[k]]
    assert "truth.json" in differing and "depth/000000.png" in differing


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


@pytest.mark.parametrize("preset, size", [("benchmark", (320, 240)), ("benchmark-vga", (640, 480))])
def test_benchmark_preset_is_balanced(preset, size):
    plans = preset_plans(preset)
    assert len(plans) >= 48 and set(PRESETS) == {"sample", "benchmark", "benchmark-vga", "smoke"}
    labels = [MOTIONS[p.motion].label for p in plans]
    n = len(plans)
    assert 0.4 <= labels.count("articulated") / n <= 0.6
    assert 0.25 <= labels.count("rigid") / n <= 0.4
    assert 0.1 <= labels.count("static") / n <= 0.25
    assert len({p.object_name for p in plans}) >= 8
    assert {p.motion for p in plans} == set(MOTIONS)
    assert {p.noise for p in plans} == {"low", "high"}
    assert {OBJECTS[p.object_name].joint_type for p in plans
            if MOTIONS[p.motion].moves_joint} == {"revolute", "prismatic"}
    assert {"pliers", "globe", "box_lid"} <= {p.object_name for p in plans}
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
        # The committed files are what the current generator makes (re-run the command in
        # sample_data/README.md after changing it).
        seq = plan_sequence(object_name=e["object_name"], motion=e["motion"], noise=e["noise"],
                            n_frames=e["n_frames"], seed=e["seed"], width=e["width"],
                            height=e["height"])
        written = json.loads((root / e["name"] / "truth.json").read_text())
        assert {k: written[k] for k in seq.truth} == json.loads(json.dumps(seq.truth))
        assert ("part_visibility" in written) == (seq.truth["joint_positions"][0] is not None)
        assert meta == seq.meta
        frame = seq.render(e["n_frames"] - 1)
        mask = cv2.imread(str(root / e["name"] / "mask" / f"{e['n_frames'] - 1:06d}.png"),
                          cv2.IMREAD_UNCHANGED) > 0
        assert (mask == frame.mask).mean() > 0.999


# ---------------------------------------------------------------- command line


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
