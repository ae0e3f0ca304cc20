"""The video's label: a joint whose parent or part looks the same after the joint's step tells
nothing; a part that leaves its parent is no part; a part's state moves continuously."""

from __future__ import annotations

import numpy as np
import pytest

from artclass_core.articulation import Articulation, JointEstimate, Part, PartJoint
from artclass_core.types import PairPoints, PairResult, RunResult
from artclass_core.video import moves_continuously, separated, symmetric

N_FRAMES, K = 20, 5


def _run() -> RunResult:
    """Pairs (i, i + K) with the noise of a Kinect at 0.8 m (1 mm) and a pixel of 1.4 mm."""
    seen = PairPoints(np.zeros((0, 2), int), np.zeros((0, 3)), 0, 0.001, 0.0014, 1)
    pairs = [PairResult(i, i + K, "AM", points=seen) for i in range(N_FRAMES - K)]
    rule = {"min_part_points": 20, "min_part_share": 0.03}  # the dense rule's smallest part
    return RunResult({}, "articulated", {}, pairs, [], [], {"rule": rule}, {}, {})


def _joint(parent: np.ndarray, kind: str, axis, at, step: float) -> tuple[RunResult, Articulation, PartJoint]:
    states = step / K * np.arange(N_FRAMES)
    e = JointEstimate(kind, np.asarray(axis, float), np.asarray(at, float), states, np.ones(N_FRAMES, bool))
    parts = [Part(0, "base", -1, parent, [0], len(parent)), Part(1, "part1", 0, parent[:5], [0], 5)]
    joint = PartJoint(0, 1, e, N_FRAMES - K)
    return _run(), Articulation(parts, [joint], np.tile(np.eye(4), (N_FRAMES, 1, 1)), {}), joint


def _half_cylinder(radius_m=0.06, height_m=0.15, spacing_m=0.003) -> np.ndarray:
    """The half of a vertical cylinder (axis y, through (0, 0, 0.8)) that faces a camera at the origin."""
    angles = np.arange(-np.pi / 2, np.pi / 2, spacing_m / radius_m)
    ys = np.arange(-height_m / 2, height_m / 2, spacing_m)
    a, y = np.meshgrid(angles, ys)
    return np.column_stack([radius_m * np.sin(a.ravel()), y.ravel(), 0.8 - radius_m * np.cos(a.ravel())])


def _plane(size_m=0.25, spacing_m=0.003) -> np.ndarray:
    """A laptop's base: a horizontal plate, its hinge along x at z = 0.8, reaching away from the camera."""
    x, z = np.meshgrid(np.arange(-size_m / 2, size_m / 2, spacing_m), np.arange(0, size_m, spacing_m))
    return np.column_stack([x.ravel(), np.full(x.size, 0.1), 0.8 + z.ravel()])


def _box(spacing_m=0.003) -> np.ndarray:
    """A microwave's carcass seen from above: a top 40 cm deep, and a front 15 cm high below its near
    edge at z = 0.8. The top is most of the points."""
    x, z = np.meshgrid(np.arange(-0.2, 0.2, spacing_m), np.arange(0.8, 1.2, spacing_m))
    top = np.column_stack([x.ravel(), np.full(x.size, 0.2), z.ravel()])
    x, y = np.meshgrid(np.arange(-0.2, 0.2, spacing_m), np.arange(0.2 + spacing_m, 0.35, spacing_m))
    return np.vstack([top, np.column_stack([x.ravel(), y.ravel(), np.full(x.size, 0.8)])])


@pytest.mark.parametrize("step_rad", [0.1, 0.5])
def test_a_body_of_revolution_turning_about_its_axis_is_symmetric(step_rad):
    """A kettle's body under its handle's revolute joint about the body's axis: the step moves the
    visible half of the cylinder along itself."""
    assert symmetric(*_joint(_half_cylinder(), "revolute", (0, 1, 0), (0, 0, 0.8), step_rad), 0)


@pytest.mark.parametrize("step_rad", [0.05, 0.3])
def test_a_laptop_base_under_its_lid_hinge_is_not(step_rad):
    assert not symmetric(*_joint(_plane(), "revolute", (1, 0, 0), (0, 0.1, 0.8), step_rad), 0)


@pytest.mark.parametrize("step_rad", [0.05, 0.3])
def test_a_carcass_under_its_door_hinge_is_not_though_its_top_turns_in_its_own_plane(step_rad):
    """The vertical hinge at the front's edge turns the top within its own plane: most points stay on
    the carcass' surface. The front would turn toward or away from the camera, as large as a part."""
    assert not symmetric(*_joint(_box(), "revolute", (0, 1, 0), (0.2, 0, 0.8), step_rad), 0)


def test_a_thin_part_rolled_about_its_own_length_shows_no_joint_and_a_lid_turned_on_its_hinge_does():
    """Two fits of a carried pair of pliers that differ by a 70 degree roll about a handle's length
    move the handle's points by millimetres, along its surface."""
    run, art, joint = _joint(_plane(), "revolute", (0, 1, 0), (0, 0, 0.8), 1.2)
    handle = _half_cylinder(radius_m=0.008, height_m=0.1, spacing_m=0.001)
    art.parts[1] = Part(1, "part1", 0, handle, [0], len(handle))
    assert symmetric(run, art, joint, 1)
    lid = _plane()
    run, art, joint = _joint(lid, "revolute", (1, 0, 0), (0, 0.1, 0.8), 0.3)
    art.parts[1] = Part(1, "part1", 0, lid, [0], len(lid))
    assert not symmetric(run, art, joint, 1)


def test_a_step_no_pair_could_see_on_the_parent_tells_nothing():
    """0.01 rad moves the plate's far edge by 2.5 mm, less than three noise sigmas and a pixel."""
    assert symmetric(*_joint(_plane(), "revolute", (1, 0, 0), (0, 0.1, 0.8), 0.01), 0)


def test_a_plate_sliding_along_itself_is_symmetric_and_a_box_pulled_out_of_it_is_not():
    plate = _plane()
    assert symmetric(*_joint(plate, "prismatic", (1, 0, 0), (0, 0, 0), 0.02), 0)  # along the plate
    assert not symmetric(*_joint(plate, "prismatic", (0, 1, 0), (0, 0, 0), 0.02), 0)  # across it


def test_a_part_lifted_off_its_parent_is_no_joint_and_a_hinged_lid_is():
    """A kettle lifted 10 cm off its base (a prismatic 'joint' that parts the bodies) and a lid on a
    hinge along the base's far edge (in contact at every state)."""
    base = _plane()
    lifted = base[::5] + (0, -0.005, 0)  # a body resting on the plate, lifted 38 cm over the video
    run, art, joint = _joint(base, "prismatic", (0, -1, 0), (0, 0, 0), 0.1)
    art.parts[1] = Part(1, "part1", 0, lifted, [0], len(lifted))
    assert separated(art, joint)
    lid = base + (0, 0, base[:, 2].max() - 0.8)  # continues the plate beyond the hinge at its far edge
    run, art, joint = _joint(base, "revolute", (1, 0, 0), (0, 0.1, base[:, 2].max()), 0.3)
    art.parts[1] = Part(1, "part1", 0, lid, [0], len(lid))
    assert not separated(art, joint)


def test_a_part_opened_closed_or_flipped_moves_continuously():
    """A lid opened, opened and closed again, or flipped in three frames between rests; a NaN where
    the part was not tracked."""
    t = np.arange(N_FRAMES, dtype=float)
    rng = np.random.default_rng(0)
    opened = 0.05 * t + rng.normal(0, 0.01, N_FRAMES)
    back = np.minimum(t, N_FRAMES - t) * 0.05
    flipped = np.clip(t - 8, 0, 3) * np.pi / 3
    flipped[4] = np.nan
    assert all(moves_continuously(s) for s in (opened, back, flipped))
    assert moves_continuously(np.array([0.0, 0.1, 0.2, 0.3, 0.4]))  # the fewest states that can pass
    drawer = np.full(15, np.nan)  # opened 4 cm and closed again, tracked in 6 frames with gaps
    drawer[[2, 8, 9, 12, 13, 14]] = 0.0, 0.0428, 0.0422, 0.0221, 0.0111, -0.0008
    assert moves_continuously(drawer)


@pytest.mark.parametrize("seed", range(5))
def test_states_that_are_noise_about_one_value_do_not(seed):
    """A still part whose state each pair measures anew: independent errors about zero, as a real
    recording's wandering patches give; and too few states to tell."""
    rng = np.random.default_rng(seed)
    assert not moves_continuously(rng.normal(0, 0.01, 8))
    assert not moves_continuously(np.array([0.0, 0.026, 0.005, -0.006, -0.0075, -0.009, -0.005, -0.001]))
    assert not moves_continuously(np.array([0.0, 0.1, 0.2, 0.3]))
    assert not moves_continuously(np.zeros(6))
