"""The robust decision rule against the failure modes of quantise-and-hash, one test each.

Clouds are sampled from boxes as a depth camera at the origin sees them (only the faces turned to
the camera), with Gaussian depth noise, and go through the real pipeline stages: the configured
registrar registers the cells (Open3D ICP) and the rule decides. Where the point of a test is a
failure of the paper's rule, the test also shows that failure on the same pair.
"""

from __future__ import annotations

import dataclasses
import gc
import weakref

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from artclass_core import CellMotion, Cloud, Config, Intrinsics, Pipeline, Registration, View, open_sequences
from artclass_core.geometry import transform
from artclass_plugins.preprocessors import camera_facing_normals
from artclass_plugins.rules import flow
from artclass_plugins.rules.robust import RobustRule, joint_like, surface_noise
from artclass_plugins.synth.generate import plan_sequence
from artclass_plugins.synth.presets import preset_plans
from artclass_plugins.synth.write import prepare_sequence_dir, write_frame, write_json

pytestmark = pytest.mark.slow  # full runs of rendered scenes

SPACING_M = 0.005


def box_surface(centre, size, *, spacing=SPACING_M) -> np.ndarray:
    """Points on the faces of an axis-aligned box that face a camera at the origin."""
    centre, size = np.asarray(centre, float), np.asarray(size, float)
    faces = []
    for axis in range(3):
        for sign in (-1, 1):
            normal = np.zeros(3)
            normal[axis] = sign
            face_centre = centre + normal * size / 2
            if normal @ (-face_centre) <= 0:  # faces away from the camera
                continue
            u, v = [a for a in range(3) if a != axis]
            gu = np.arange(-size[u] / 2, size[u] / 2 + 1e-9, spacing)
            gv = np.arange(-size[v] / 2, size[v] / 2 + 1e-9, spacing)
            pts = np.zeros((len(gu) * len(gv), 3))
            pts[:, u], pts[:, v] = np.repeat(gu, len(gv)), np.tile(gv, len(gu))
            faces.append(pts + face_centre)
    return np.concatenate(faces)


def motion(*, rot_deg=(0.0, 0.0, 0.0), about=(0.0, 0.0, 0.0), shift=(0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 rigid motion: a rotation (xyz Euler, degrees) about the point ``about``, then a shift."""
    R = Rotation.from_euler("xyz", rot_deg, degrees=True).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(about) - R @ np.asarray(about) + np.asarray(shift)
    return T


def cloud(points: np.ndarray, *, noise_m: float, seed: int, index: int = 0) -> Cloud:
    rng = np.random.default_rng(seed)
    noisy = points + rng.normal(0.0, noise_m, points.shape) * [0.3, 0.3, 1.0]  # mostly axial, as a sensor
    return Cloud(index, noisy, camera_facing_normals(noisy, radius_m=3 * SPACING_M), {"v_m": SPACING_M})


def decide(pipeline: Pipeline, a: Cloud, b: Cloud, between: tuple[Cloud, ...] = ()):
    cells, x = pipeline.register(a, b)
    return pipeline.decide(0, 1, cells, a, b, x, between)


# The per-cell pipeline the robust rule decides from.
ROBUST = Config(preprocessor="fine", registrar="icp_point_to_point", rule="robust")


@pytest.fixture(scope="module")
def robust(registry):
    return Pipeline(registry, ROBUST)


@pytest.fixture(scope="module")
def paper_rule(registry):
    return Pipeline(registry, dataclasses.replace(ROBUST, rule="paper"))


# A box 20 x 12 x 15 cm, 1 m in front of the camera, seen from slightly above.
BOX = box_surface((0.05, 0.08, 1.0), (0.20, 0.12, 0.15))
BOX_CENTRE = np.array([0.05, 0.08, 1.0])


def test_rigid_rotation_about_the_object_is_one_motion_not_many_keys(robust, paper_rule):
    """Rotation-translation coupling: 4 degrees about the box's own centre, 1 m from the camera, gives
    every cell a different translation about the camera origin (up to ~7 cm): many paper keys, one
    motion of the points."""
    T = motion(rot_deg=(0, 4, 2), about=BOX_CENTRE, shift=(0.01, 0, 0))
    a, b = cloud(BOX, noise_m=0.001, seed=1), cloud(transform(BOX, T), noise_m=0.001, seed=2, index=1)
    assert decide(robust, a, b).decision == "RM"
    assert decide(paper_rule, a, b).decision == "AM", (
        "the paper's keys split this rigid motion (the failure mode)"
    )


def test_static_scene_with_noise_is_no_motion(robust, paper_rule):
    a, b = cloud(BOX, noise_m=0.002, seed=3), cloud(BOX, noise_m=0.002, seed=4, index=1)
    pair = decide(robust, a, b)
    assert pair.decision == "NM", pair.info
    assert decide(paper_rule, a, b).decision == "AM", (
        "noise scatters the paper's cell keys (the failure mode)"
    )


def test_threshold_follows_the_measured_noise(robust):
    """tau is measured on the data: six times the noise gives a tau several times larger, and a
    static scene stays NM at both levels."""
    taus = []
    for noise_m in (0.0005, 0.003):
        a, b = cloud(BOX, noise_m=noise_m, seed=5), cloud(BOX, noise_m=noise_m, seed=6, index=1)
        pair = decide(robust, a, b)
        assert pair.decision == "NM", pair.info
        taus.append(pair.info["tau_m"])
    assert taus[0] == pytest.approx(RobustRule.Params().noise_floor_m)  # low noise: the floor
    assert taus[1] > 2.5 * taus[0], taus


def test_surface_noise_measures_axial_noise():
    from scipy.spatial import cKDTree

    flat = box_surface((0, 0, 1.0), (0.3, 0.3, 0.001))
    for sigma in (0.001, 0.003):
        noisy = flat + np.random.default_rng(0).normal(0, sigma, flat.shape) * [0, 0, 1]
        assert surface_noise(noisy, cKDTree(noisy)) == pytest.approx(sigma, rel=0.3)


def test_tiny_motion_within_noise_is_no_motion(robust):
    T = motion(shift=(0.0004, 0.0, 0.0003))
    a, b = cloud(BOX, noise_m=0.0015, seed=7), cloud(transform(BOX, T), noise_m=0.0015, seed=8, index=1)
    assert decide(robust, a, b).decision == "NM"


def test_degenerate_cells_that_slid_do_not_vote_for_a_motion(robust):
    """On a flat face ICP slides freely: cells whose transform slid 2 cm within their face still
    agree with the box's true motion on where their points lie, so they are no second motion."""
    T = motion(rot_deg=(0, 3, 0), about=BOX_CENTRE, shift=(0.02, 0, -0.01))
    a, b = cloud(BOX, noise_m=0.001, seed=9), cloud(transform(BOX, T), noise_m=0.001, seed=10, index=1)
    cells, x = robust.register(a, b)
    front = [
        c for c in cells if c.matched and np.allclose(a.normals[c.source_idx].mean(0), [0, 0, -1], atol=0.05)
    ]
    assert len(front) >= 3, "the box's front face should span several cells"
    slide = motion(shift=(0.02, 0.015, 0.0))  # within the front face (normal -z)
    for c in front[: len(front) // 2 + 1]:
        c.registration = dataclasses.replace(
            c.registration, T_target_from_source=slide @ c.registration.T_target_from_source
        )
    assert robust.decide(0, 1, cells, a, b, x).decision == "RM"


def test_one_wrong_cell_is_cross_explained_not_a_part(robust):
    """Support: a single cell whose ICP went wrong is explained by the motion of the rest (or is too
    small to be a part), so it does not make the pair articulated."""
    T = motion(rot_deg=(0, 0, 5), about=BOX_CENTRE, shift=(0.0, 0.01, 0.0))
    a, b = cloud(BOX, noise_m=0.001, seed=11), cloud(transform(BOX, T), noise_m=0.001, seed=12, index=1)
    cells, x = robust.register(a, b)
    wrong = next(c for c in cells if c.matched)
    wrong.registration = dataclasses.replace(
        wrong.registration, T_target_from_source=motion(rot_deg=(20, 0, 0))
    )
    pair = robust.decide(0, 1, cells, a, b, x)
    assert pair.decision == "RM", pair.info


# An articulated box: a base 24 x 8 x 16 cm and a lid 24 x 2 x 16 cm hinged on the base's back top edge.
BASE = box_surface((0.0, 0.10, 1.0), (0.24, 0.08, 0.16))
HINGE = np.array([0.0, 0.06, 1.08])  # back top edge (y down: top is at smaller y)


def lid(angle_deg: float) -> np.ndarray:
    closed = box_surface((0.0, 0.05, 1.0), (0.24, 0.02, 0.16))
    return transform(closed, motion(rot_deg=(angle_deg, 0, 0), about=HINGE))


@pytest.mark.parametrize("carried", [False, True])
def test_lid_opening_is_two_motions(robust, carried):
    carry = motion(rot_deg=(0, 6, 0), about=(0, 0.1, 1.0), shift=(0.02, 0, 0)) if carried else np.eye(4)
    a = cloud(np.concatenate([BASE, lid(-10)]), noise_m=0.001, seed=13)
    b = cloud(transform(np.concatenate([BASE, lid(-25)]), carry), noise_m=0.001, seed=14, index=1)
    pair = decide(robust, a, b)
    assert pair.decision == "AM", pair.info
    clusters = {c.cluster for c in pair.cells if c.cluster is not None}
    assert len(clusters) >= 2


def test_rule_reports_clusters_and_evidence(robust):
    T = motion(rot_deg=(0, 5, 0), about=BOX_CENTRE)
    a, b = cloud(BOX, noise_m=0.001, seed=15), cloud(transform(BOX, T), noise_m=0.001, seed=16, index=1)
    pair = decide(robust, a, b)
    matched = [c for c in pair.cells if c.matched]
    assert all(c.cluster == 0 for c in matched if c.cluster is not None)
    assert {"tau_m", "n_informative", "motions", "support"} <= set(pair.info)
    assert isinstance(pair.cells[0], CellMotion) and isinstance(matched[0].registration, Registration)


# A textured panel 1 m in front of a 320x240 camera: its left half stands still while the texture of
# its right half slides 8 px (2.8 cm) to the right within the panel's plane, like a belt. Depth is the
# same in both frames, so only the colour images can tell that anything moved.
INTRINSICS = Intrinsics(285.0, 285.0, 159.5, 119.5, 320, 240)
ROWS, COLS, SPLIT, SLIDE_PX = slice(60, 180), slice(80, 240), 160, 8


def belt_cloud(
    index: int, *, with_view: bool = True, slide_px: int = SLIDE_PX, stripes: bool = False
) -> Cloud:
    """Frame ``index`` of the belt; with ``stripes`` its texture varies across the slide only (vertical
    stripes of random widths: an edge everywhere, never a corner), seen with a camera's pixel noise (on
    a noise-free 1D texture DIS cannot solve even the flow across it)."""
    rng = np.random.default_rng(7)
    noise = rng.random((1, 360) if stripes else (240, 360)).astype(np.float32)
    texture = cv2.GaussianBlur(np.repeat(noise, 240, axis=0) if stripes else noise, (0, 0), 1.5)
    texture = cv2.normalize(texture, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    gray = texture[:, 20:340].copy()
    if index:
        gray[:, SPLIT:] = texture[:, 20 + SPLIT - index * slide_px : 340 - index * slide_px]
    if stripes:
        pixel_noise = np.random.default_rng(index).normal(0.0, 2.0, gray.shape)
        gray = np.clip(gray + pixel_noise, 0, 255).astype(np.uint8)
    depth = np.zeros((240, 320), np.float32)
    depth[ROWS, COLS] = 1.0
    grid = np.zeros_like(depth, bool)
    grid[ROWS.start : ROWS.stop : 2, COLS.start : COLS.stop : 2] = True
    points = INTRINSICS.backproject(depth, grid)
    view = View(gray, depth, INTRINSICS) if with_view else None
    return Cloud(index, points, camera_facing_normals(points, radius_m=0.02), {"v_m": 0.007}, view=view)


def test_optical_flow_sees_a_slide_that_keeps_the_surface_in_place(robust):
    pair = decide(robust, belt_cloud(0), belt_cloud(1))
    assert pair.decision == "AM", pair.info
    blind = decide(robust, belt_cloud(0, with_view=False), belt_cloud(1, with_view=False))
    assert blind.decision == "NM", "without images, depth alone cannot see the slide"


def test_optical_flow_across_stripes_sees_a_slide(robust, monkeypatch):
    """On stripes the flow is known only across them (the aperture problem), and that is enough to see a
    slide across them."""
    a, b = belt_cloud(0, stripes=True), belt_cloud(1, stripes=True)
    pair = decide(robust, a, b)
    assert pair.decision == "AM", pair.info
    monkeypatch.setattr(flow, "EDGE_FACTOR", np.inf)
    assert decide(robust, belt_cloud(0, stripes=True), belt_cloud(1, stripes=True)).decision == "NM", (
        "without edges, the stripes were expected to give the flow nothing to go on"
    )


def test_optical_flow_is_followed_from_frame_to_frame_where_it_cannot_jump(robust):
    """A belt sliding 4 px a frame has gone 20 px by frame 5: too far for the flow from frame 0 straight
    to frame 5 on this fine texture, but followed through frames 1..4 the slide is seen."""
    frames = [belt_cloud(i, slide_px=4) for i in range(6)]
    assert decide(robust, frames[0], frames[5]).decision == "NM", "the direct flow was expected to fail here"
    pair = decide(robust, frames[0], frames[5], tuple(frames[1:5]))
    assert pair.decision == "AM", pair.info


def panel_cloud(index: int, *, behind: str = "wall") -> Cloud:
    """A flat, untextured panel 1 m in front of the camera and of a wall at 1.5 m. In frame 1 the panel's
    right half is gone, and where it was the camera sees the wall (``behind="wall"``: it moved off) or
    a hand 20 cm in front of the panel (``"hand"``: it may be there, hidden)."""
    scene = np.full((240, 320), 1.5, np.float32)
    panel = np.zeros_like(scene, bool)
    panel[ROWS, COLS] = True
    if index:
        panel[:, SPLIT:] = False
        if behind == "hand":
            scene[ROWS, SPLIT : COLS.stop] = 0.8
    scene[panel] = 1.0
    depth = np.where(panel, scene, 0.0).astype(np.float32)
    grid = np.zeros_like(panel)
    grid[::2, ::2] = True
    points = INTRINSICS.backproject(depth, grid)
    view = View(np.full((240, 320), 128, np.uint8), depth, INTRINSICS, scene)
    return Cloud(index, points, camera_facing_normals(points, radius_m=0.02), {"v_m": 0.007}, view=view)


@pytest.mark.parametrize("behind, expected", [("wall", "AM"), ("hand", "NM")])
def test_a_part_is_gone_where_the_camera_sees_through_it(robust, behind, expected):
    """Half the object is gone from where it was and nowhere to be seen (a lid turned edge-on, a part
    moved out of view): no motion explains its points, but the camera now sees the wall through the place
    where they were, so they did move. Behind a hand in front they may only be hidden."""
    pair = decide(robust, panel_cloud(0), panel_cloud(1, behind=behind))
    assert pair.decision == expected, pair.info


@pytest.mark.parametrize(
    "relative, expected",
    [
        (motion(rot_deg=(0, 0, 30), about=(0.05, 0.0, 1.0)), True),  # a hinge through the object
        (motion(shift=(0.04, 0.0, 0.0)), True),  # a drawer
        (
            motion(rot_deg=(0, 0, 30), about=(0.05, 0.0, 1.0), shift=(0, 0, 0.05)),
            False,
        ),  # a screw: 5 cm along the axis
        (motion(rot_deg=(0, 0, 30), about=(0.6, 0.0, 1.0)), False),  # a hinge 55 cm away
    ],
)
def test_a_part_moves_on_a_joint(relative, expected):
    carry = motion(rot_deg=(5, 10, 0), about=(0, 0, 1.0), shift=(0.02, 0, 0))
    assert joint_like(carry, relative @ carry, np.array([0.0, 0.0, 1.0]), 0.3) is expected


def test_a_motion_that_is_no_part_is_passed_over_for_the_next():
    """The greedy cover tries further motions best first. One that the data cannot tell from the first,
    or that no joint makes, is passed over, and the next best is tried: a cell-sized screw fit must not
    hide a part that a plausible motion explains. Four cells: the first motion explains cell 0;
    motion 1 (implausible) explains cells 1-3, motion 2 cells 1-2."""
    explains = np.array([[1, 0, 0, 0], [0, 1, 1, 1], [0, 1, 1, 0]], bool)
    weight, informative = np.full(4, 10.0), np.ones(4, bool)

    def cover(distinct):
        return RobustRule()._cover(explains, explains, weight, weight.sum(), informative, 0.15, 0, distinct)

    chosen, members, passed = cover(lambda h, cells: True)
    assert chosen == [0, 1] and passed == 0 and members[1].tolist() == [1, 2, 3]
    chosen, members, passed = cover(lambda h, cells: h == 2)  # motion 1: no joint moves so
    assert chosen == [0, 2] and passed == 1 and members[1].tolist() == [1, 2]
    assert sorted(members[0].tolist()) == [0, 3], "cells of a motion passed over stay with the first"
    chosen, members, passed = cover(lambda h, cells: False)
    assert chosen == [0] and passed == 2 and sorted(members[0].tolist()) == [0, 1, 2, 3]
    # Motion 1 cannot be told from the first on cells 1-3: they moved as the first did, for no other to take.
    chosen, members, passed = cover(lambda h, cells: None if h == 1 else True)
    assert chosen == [0] and passed == 1 and sorted(members[0].tolist()) == [0, 1, 2, 3]


def test_evidence_does_not_keep_the_clouds_alive(robust):
    """The rule keeps its evidence in the pair's memo, which lives as long as the clouds: if the evidence
    held the clouds, no cloud of a streaming run would ever be freed (memory grows with the length)."""
    a, b = cloud(BOX, noise_m=0.001, seed=17), cloud(BOX, noise_m=0.001, seed=18, index=1)
    decide(robust, a, b)
    gone = weakref.ref(a), weakref.ref(b)
    del a, b
    gc.collect()
    assert all(ref() is None for ref in gone)


def test_only_the_whole_object_may_hide_points_behind_itself(registry, tmp_path):
    """Regression, on the first 15 frames of the 640x480 benchmark's carried box
    (`38_box_lid_carry_low`) with the `depth_threshold` segmenter: in pair (9, 14) the whole-object
    ICP started from the centroid shift flips the box by 92 degrees. With the self-occlusion excuse,
    which is meant for the object's own motion, that flip "explained" two cells as a second motion,
    and the rigid box was called articulated. A part is scored without the excuse."""
    seq = benchmark_frames(registry, tmp_path, "38_box_lid_carry_low", 15)
    result = Pipeline(registry, dataclasses.replace(ROBUST, segmenter="depth_threshold")).run(seq)
    assert result.pairs[9].decision == "RM", result.pairs[9].info
    assert "AM" not in [p.decision for p in result.pairs] and result.label == "rigid"


@pytest.mark.parametrize("still_share, part_found", [(None, True), (0.15, False)])
def test_a_small_part_moves_while_the_object_stands_still(registry, tmp_path, still_share, part_found):
    """Regression, on the first 12 frames of the 640x480 benchmark's `10_microwave_articulate_low`:
    the door, seen nearly edge-on, is 8% of the microwave's points. While the body stands still the
    identity explains 90% or more of the points, so a part can have no more than the rest; asking it
    for the 15% asked of a part of a moving object (``min_part_share``) called every pair NM."""
    seq = benchmark_frames(registry, tmp_path, "10_microwave_articulate_low", 12)
    over = {} if still_share is None else {"min_still_part_share": still_share}
    decisions = [p.decision for p in Pipeline(registry, ROBUST.with_overrides(registry, over)).run(seq).pairs]
    assert set(decisions) <= {"NM", "AM"} and ("AM" in decisions) is part_found, decisions


def test_a_tray_sliding_out_of_its_sleeve_is_a_part(registry, tmp_path):
    """Regression, on the first 16 frames of the 640x480 benchmark's `13_matchbox_articulate_high`: in
    pair (10, 15) the tray slides 3 cm out of the sleeve, which stands still. Depth barely sees it (the
    tray's floor and walls slide along themselves); the flow does, but each small tray cell's own fit
    to it turns by 5-10 degrees, which no joint does. The best of those was taken as the only candidate
    part, failed the joint test, and the pair was called NM; the next best candidate is a plain part."""
    seq = benchmark_frames(registry, tmp_path, "13_matchbox_articulate_high", 16)
    pair = Pipeline(registry, ROBUST).run(seq).pairs[10]
    assert pair.decision == "AM", pair.info
    assert len({c.cluster for c in pair.cells if c.cluster is not None}) >= 2


def benchmark_frames(registry, tmp_path, name: str, n_frames: int):
    """The first ``n_frames`` of the 640x480 benchmark's sequence ``name``, rendered into ``tmp_path``."""
    index = int(name[:2])
    plan = preset_plans("benchmark-vga")[index]
    assert plan.name == name
    seq = plan_sequence(
        object_name=plan.object_name,
        motion=plan.motion,
        noise=plan.noise,
        n_frames=plan.n_frames,
        seed=index,
        width=plan.width,
        height=plan.height,
    )
    out = prepare_sequence_dir(tmp_path / name)
    for i in range(n_frames):
        frame = seq.render(i)
        write_frame(out, i, rgb=frame.rgb, depth_m=frame.depth_m, mask=frame.mask)
    write_json(out / "meta.json", seq.meta)
    return open_sequences(registry, out)[0]
