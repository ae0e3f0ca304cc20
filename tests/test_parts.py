"""Parts and joints over a video: per-pair motion labels linked into parts, joints fitted to the
parts' motions relative to the base, on a synthetic scene with known motions and labels."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from artclass_core import ArtclassError
from artclass_core.geometry import transform
from artclass_core.joint_metrics import axis_direction_error_rad, axis_position_error_m, score_articulation
from artclass_core.labels import labelled_result
from artclass_core.plugins import load_registry
from artclass_core.types import (
    Cloud,
    FrameResult,
    Intrinsics,
    Motion,
    MotionEvidence,
    PairResult,
    RunResult,
    View,
)
from artclass_core.video import joints_over_video
from artclass_plugins.parts import (
    PartsParams,
    chain_interleaved,
    find_articulation,
    frame_states,
    images,
    motions,
    observations,
    tracks,
    tree,
)
from artclass_plugins.parts.base import _base_motions, _one_body_pairs_on, _still_track
from artclass_plugins.parts.images import _look
from artclass_plugins.parts.joints import smooth_misfit

K = Intrinsics(500.0, 500.0, 160.0, 120.0, 320, 240)
HINGE = np.array([0.0, 0.0, 0.8])  # camera frame of frame 0, metres
AXIS = np.array([0.0, 1.0, 0.0])  # vertical (the camera's y)
N_FRAMES, K_PAIRS = 24, 4
rng = np.random.default_rng(1)


def _grid(x, y, z) -> np.ndarray:
    return np.stack(np.meshgrid(x, y, z, indexing="ij"), -1).reshape(-1, 3)


# a panel facing the camera and a door hinged on its right edge, sampled about every 1.5 pixels
# (with 0.5 mm of depth noise: a measured surface is never exactly flat)
BASE = _grid(np.arange(-0.14, 0.0, 0.0025), np.arange(-0.08, 0.08, 0.0025), [0.8])
LID = _grid(np.arange(0.0025, 0.1, 0.0025), np.arange(-0.08, 0.08, 0.0025), [0.8])
# for a chain (a folding ruler's second leg): a tip hinged on the lid's far edge, turning back
TIP = _grid(np.arange(0.1025, 0.18, 0.0025), np.arange(-0.08, 0.08, 0.0025), [0.8])
TIP_HINGE = np.array([0.1, 0.0, 0.8])
BASE[:, 2] += rng.normal(0.0, 0.0005, len(BASE))
LID[:, 2] += rng.normal(0.0, 0.0005, len(LID))
TIP[:, 2] += rng.normal(0.0, 0.0005, len(TIP))
STATES = np.radians(np.linspace(0.0, 60.0, N_FRAMES))
TIP_STATES = -0.6 * STATES  # relative to the lid


def _T(R=None, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = np.eye(3) if R is None else R, t
    return T


def _hinge(q: float, at: np.ndarray = HINGE) -> np.ndarray:
    R = Rotation.from_rotvec(q * AXIS).as_matrix()
    return _T(R, at - R @ at)


def _states(linkage: bool) -> tuple[np.ndarray, np.ndarray]:
    """The lid's and the tip's states per frame (radians): the tip turns back 0.6 of the lid's turn
    (a folding ruler), or all of it (a linkage: a desk lamp's parallelogram carries its head along a
    circle, keeping its orientation); the linkage's lid turns 45 degrees."""
    if not linkage:
        return STATES, TIP_STATES
    lid = np.radians(np.linspace(0.0, 45.0, N_FRAMES))
    return lid, -lid


def _poses(f: int, chain: bool, linkage: bool = False, slide: bool = False) -> list[np.ndarray]:
    """Each part's pose in frame f (camera frame of frame 0, before any carrying): base, lid, tip.
    ``slide``: the lid slides 6 cm away from the base in their common plane, the way a drawer's front
    slides along its cabinet's side (no hinge)."""
    if slide:
        return [np.eye(4), _T(t=(0.06 * f / (N_FRAMES - 1), 0.0, 0.0))]
    lid_states, tip_states = _states(linkage)
    lid = _hinge(lid_states[f])
    return [np.eye(4), lid] + ([lid @ _hinge(tip_states[f], TIP_HINGE)] if chain else [])


def _carry(f: int, carried: bool) -> np.ndarray:
    """Where the hand has moved the whole object in frame f (camera frame)."""
    if not carried:
        return np.eye(4)
    return _T(
        Rotation.from_rotvec([0.0, 0.004 * f, 0.002 * f]).as_matrix(), np.array([0.002, 0.001, 0.0]) * f
    )


def _cloud(
    f: int, carried: bool, chain: bool = False, linkage: bool = False, slide: bool = False
) -> tuple[Cloud, np.ndarray]:
    """Frame f's cloud and each point's true part (0 base, 1 lid, 2 tip). Untextured, but for a
    ``slide``, whose parts are painted with stripes across the slide (2 cm apart)."""
    shapes = [BASE, LID, TIP][: 3 if chain else 2]
    C = _carry(f, carried)
    points = np.vstack([transform(x, C @ T) for x, T in zip(shapes, _poses(f, chain, linkage, slide))])
    part = np.concatenate([np.full(len(x), n) for n, x in enumerate(shapes)])
    u, v = K.pixels(points)
    pixels = np.column_stack([np.rint(u), np.rint(v)]).astype(int)
    mask = np.zeros((K.height, K.width), bool)
    mask[pixels[:, 1], pixels[:, 0]] = True
    depth = _depth_image(pixels, points[:, 2])
    shade = 128 + 100 * np.sin(2 * np.pi * np.vstack(shapes)[:, 0] / 0.02) if slide else np.zeros(len(points))
    gray = _depth_image(pixels, points[:, 2], shade).astype(np.uint8)
    view = View(gray, depth, K, scene_depth_m=depth, mask=mask)
    return Cloud(f, points, pixels=pixels, view=view, info={"stride_px": 1}), part


def _depth_image(pixels: np.ndarray, z: np.ndarray, value: np.ndarray | None = None) -> np.ndarray:
    """A depth image (H, W) of points at ``pixels`` (nearest point first), the pixels between them
    filled from their nearest neighbour (a depth camera measures every pixel of a surface); or, with
    ``value``, the image of the nearest point's value (its intensity)."""
    value = z if value is None else value
    depth, image = np.zeros((K.height, K.width), np.float32), np.zeros((K.height, K.width), np.float32)
    order = np.argsort(-z)  # the nearest point written last wins its pixel
    depth[pixels[order, 1], pixels[order, 0]] = z[order]
    image[pixels[order, 1], pixels[order, 0]] = value[order]
    near = ndimage.binary_closing(depth > 0, np.ones((3, 3)), iterations=2) | (depth > 0)
    _, (rows, cols) = ndimage.distance_transform_edt(depth == 0, return_indices=True)
    return np.where(near, image[rows, cols], 0.0).astype(np.float32)


def run_result(
    *,
    carried: bool = False,
    hidden: range = range(0),
    label: str = "articulated",
    chain: bool = False,
    mislabelled: float = 0.0,
    linkage: bool = False,
    slide: bool = False,
    motion_noise: tuple[tuple[float, float], ...] = (),
) -> RunResult:
    """A run of pairs (i, i + k) whose rule found every part's motion exactly (the moving parts' only
    where they moved and were not hidden), and labelled every point with its part, but for a
    ``mislabelled`` share of each pair's points (the part's nearest its neighbour's: a band along the
    seam) given to the neighbouring part. ``linkage``: see :func:`_states`; ``slide``: see
    :func:`_poses`. ``motion_noise``: per
    moving part, the standard deviations (metres, radians, per axis) of an error added to each of
    its motions, about the part's centre (seeded)."""
    clouds = [_cloud(f, carried, chain, linkage, slide) for f in range(N_FRAMES)]
    noise = np.random.default_rng(0)
    frames = [FrameResult(f, f"{f:06d}", clouds[f][0], info={"stride_px": 1}) for f in range(N_FRAMES)]
    pairs = []
    for i in range(N_FRAMES - K_PAIRS):
        j = i + K_PAIRS
        (a, part_a), (b, part_b) = clouds[i], clouds[j]
        found = i not in hidden and j not in hidden
        motions = [
            Motion(
                _carry(j, carried) @ Pj @ np.linalg.inv(_carry(i, carried) @ Pi),
                f"cell {n}" if n else "object",
                int((part_a == n).sum()),
                0.01 * n,
            )
            for n, (Pi, Pj) in enumerate(
                zip(_poses(i, chain, linkage, slide), _poses(j, chain, linkage, slide))
            )
            if found or n == 0
        ]
        for m, (sigma_m, sigma_rad), shape in zip(motions[1:], motion_noise, [LID, TIP]):
            centre = transform(shape.mean(axis=0, keepdims=True), m.T_target_from_source)[0]
            R = Rotation.from_rotvec(noise.normal(0.0, sigma_rad, 3)).as_matrix()
            error = _T(R, centre - R @ centre + noise.normal(0.0, sigma_m, 3))
            m.T_target_from_source = error @ m.T_target_from_source
        labels = np.r_[part_a, part_b] if found else np.zeros(len(part_a) + len(part_b), int)
        if found and mislabelled:
            labels[_band(np.vstack([a.points, b.points]), labels, mislabelled)] = 0
        ev = MotionEvidence(
            np.stack([m.T_target_from_source for m in motions]),
            [m.name for m in motions],
            np.zeros((len(motions), len(labels)), np.float32),
            np.zeros((len(motions), len(labels)), np.int8),
            np.zeros((len(motions), len(labels)), np.float32),
            0.001,
            np.vstack([a.points, b.points]),
            np.vstack([a.pixels, b.pixels]),
            0.0016,
            {"stride_px": 1},
            n_source=len(a.points),
        )
        pairs.append(PairResult(i, j, "AM" if found else "RM", motions=motions, labels=labels, evidence=ev))
    return RunResult(
        dict(name="flap", path="", object="flap", n_frames=N_FRAMES, truth=label),
        label,
        {},
        pairs,
        [p.decision for p in pairs],
        frames,
        {},
        {},
        {},
    )


def _band(points: np.ndarray, labels: np.ndarray, share: float) -> np.ndarray:
    """The ``share`` of the moving parts' points (labels > 0) nearest the base: indices."""
    moving = np.flatnonzero(labels > 0)
    gap = cKDTree(points[labels == 0]).query(points[moving])[0]
    return moving[np.argsort(gap)[: int(share * len(moving))]]


@pytest.fixture(scope="module")
def bic():
    return load_registry().create("joint_estimator", "bic")


def _check_hinge(art):
    assert [p.index for p in art.parts] == [0, 1] and art.parts[1].parent == 0
    (joint,) = art.joints
    e = joint.estimate
    assert e.type == "revolute"
    assert np.degrees(axis_direction_error_rad(AXIS, e.axis_direction)) < 1.0
    at = LID.mean(axis=0)
    assert axis_position_error_m(HINGE, AXIS, e.axis_point_m, e.axis_direction, at_m=at) < 0.002
    known = np.isfinite(e.states)
    sign = np.sign(AXIS @ e.axis_direction)
    truth = STATES - STATES[np.flatnonzero(known)[0]]
    np.testing.assert_allclose(sign * e.states[known], truth[known], atol=np.radians(1.0))
    return e


def test_a_hinged_flap_on_a_still_base(bic):
    art = find_articulation(run_result(), estimator=bic)
    e = _check_hinge(art)
    assert np.isfinite(e.states).all(), "pairs (i, i + 4) give a state to every frame"
    assert art.summary() == e.summary(up=art.UP)
    assert "axis 0 deg from vertical, 0-60 deg over the video" in art.summary()
    # the flap's points, brought back to state 0, are where the flap is in frame 0
    assert np.abs(np.sort(art.parts[1].points_m[:, 2]) - np.sort(LID[:, 2])).max() < 0.003


def test_a_drift_of_the_base_below_the_rules_threshold_is_no_motion(bic):
    """A fit of the whole object over a still base and a turning flap drags the base's points by a
    fraction of the flap's motion (here 1 degree about the base's centre, about 1 mm). Below the
    rule's motion threshold that is noise: the base stays where it is, instead of turning by the
    drift at every pair of a chain, and the hinge comes out as if the base's motions were exact."""
    run = run_result()
    centre = BASE.mean(axis=0)
    R = Rotation.from_rotvec(np.radians([0.0, 0.0, 1.0])).as_matrix()
    drift = _T(R, centre - R @ centre)
    moved_m = float(np.median(np.linalg.norm(transform(BASE, drift) - BASE, axis=1)))
    for p in run.pairs:
        p.motions[0] = Motion(drift, "object", p.motions[0].n_points, moved_m)
        p.info["threshold_m"] = 2 * moved_m
    art = find_articulation(run, estimator=bic)
    np.testing.assert_allclose(art.base_poses, np.tile(np.eye(4), (N_FRAMES, 1, 1)), atol=1e-12)
    _check_hinge(art)


def test_a_carried_object_gives_the_joint_in_the_first_frame(bic):
    """The base moves too: its motions are chained (and the interleaved chains of pairs tied) so that
    the axis comes out in the camera frame of frame 0."""
    art = find_articulation(run_result(carried=True), estimator=bic)
    _check_hinge(art)
    np.testing.assert_allclose(art.base_poses[7], _carry(7, True), atol=2e-3)


def test_a_part_hidden_for_a_while(bic):
    """Pairs that cannot see the flap contribute nothing; the joint is still found."""
    art = find_articulation(run_result(hidden=range(9, 13)), estimator=bic)
    _check_hinge(art)
    assert art.joints[0].n_pairs < N_FRAMES - K_PAIRS


def test_a_chain_hangs_its_outer_part_on_the_inner_one(bic):
    """A tip hinged on the lid's far edge turns back as the lid opens: relative to the base it turns
    about a moving axis, relative to the lid about a fixed one, so the tree hangs it on the lid."""
    art = find_articulation(run_result(chain=True), estimator=bic)
    assert [(p.index, p.parent) for p in art.parts] == [(0, -1), (1, 0), (2, 1)]
    lid, tip = art.joints
    assert (lid.parent, lid.child, tip.parent, tip.child) == (0, 1, 1, 2)
    assert art.summary().startswith("part1 on base: revolute joint") and "; part2 on part1: " in art.summary()
    e = tip.estimate
    assert e.type == "revolute"
    assert np.degrees(axis_direction_error_rad(AXIS, e.axis_direction)) < 1.0
    at = TIP.mean(axis=0)
    assert axis_position_error_m(TIP_HINGE, AXIS, e.axis_point_m, e.axis_direction, at_m=at) < 0.002
    sign = np.sign(AXIS @ e.axis_direction)
    np.testing.assert_allclose(sign * e.states, TIP_STATES, atol=np.radians(1.0))
    # the tip's points, brought back to every joint's state 0, are where the tip is in frame 0
    assert np.abs(np.sort(art.parts[2].points_m[:, 0]) - np.sort(TIP[:, 0])).max() < 0.003


def test_a_part_told_apart_in_two_pairs_is_no_parent_for_one_tracked_over_the_video(bic):
    """A joint that two pairs tell is untested: an axis passes through any two poses, at a cost near
    nothing. With the lid told apart from the base in two pairs only (elsewhere the base's fit takes
    it), the tip, tracked in every pair, hangs on the base, where every pair tests its joint."""
    run = run_result(chain=True)
    for p in run.pairs[2:]:
        keep = [0, 2]  # the base's and the tip's motions; the lid's points go to the base
        p.labels = np.select([p.labels == 1, p.labels == 2], [0, 1], p.labels)
        p.motions = [p.motions[k] for k in keep]
        ev = p.evidence
        p.evidence = dataclasses.replace(
            ev,
            motions=ev.motions[keep],
            names=[ev.names[k] for k in keep],
            residual_m=ev.residual_m[keep],
            status=ev.status[keep],
            flow_px=ev.flow_px[keep],
        )
    art = find_articulation(run, estimator=bic)
    tip = max(art.joints, key=lambda j: j.n_pairs)
    assert tip.parent == 0 and tip.n_pairs >= 10


def test_a_linkage_hangs_the_head_on_the_arm_it_turns_against(bic):
    """A desk lamp's parallelogram: the tip turns back as far as the lid turns, so relative to the
    base it keeps its orientation and moves along a circle. That passes for a slide (its poses
    scatter about one, and the noise level is taken from the scatter), and a slide relative to the
    still, exact base costs less than a hinge on the noisier lid. But the travel turns from pair
    to pair, a misfit neighbouring pairs share, which noise is not: the tip hangs on the lid."""
    noisy = dict(chain=True, linkage=True, motion_noise=((0.001, 0.007), (0.0005, 0.0035)))
    art = find_articulation(run_result(**noisy), estimator=bic)
    assert [(j.parent, j.child, j.estimate.type) for j in art.joints] == [
        (0, 1, "revolute"),
        (1, 2, "revolute"),
    ]
    lid, tip = (j.estimate for j in art.joints)
    for e in (lid, tip):
        assert np.degrees(axis_direction_error_rad(AXIS, e.axis_direction)) < 3.0
    at = TIP.mean(axis=0)
    assert axis_position_error_m(TIP_HINGE, AXIS, tip.axis_point_m, tip.axis_direction, at_m=at) < 0.005
    assert np.ptp(tip.states[np.isfinite(tip.states)]) == pytest.approx(np.radians(45.0), abs=np.radians(3.0))


def test_smooth_misfit_tells_a_trend_from_noise():
    """Residuals that neighbouring pairs share (a path the joint does not follow) are misfit; the same
    residuals shuffled in time are noise (0 but for chance)."""
    trend = np.column_stack([np.linspace(-0.003, 0.003, 20)] * 3 + [np.zeros((20, 3))])
    assert smooth_misfit(trend) > 100.0
    shuffled = trend[np.random.default_rng(0).permutation(20)]
    assert smooth_misfit(shuffled) < 3.0
    assert smooth_misfit(trend[:2]) == 0.0  # too few pairs to judge


def test_without_scores_every_part_hangs_on_the_base(bic):
    """An estimator that gives no scores cannot rank parents: the tree falls back to the base."""

    class Unscored:
        def estimate(self, poses):
            return dataclasses.replace(bic.estimate(poses), scores={})

    art = find_articulation(run_result(chain=True), estimator=Unscored())
    assert [(j.parent, j.child) for j in art.joints] == [(0, 1), (0, 2)]


def test_the_estimator_is_told_one_pose_per_pair_is_independent(bic):
    """The estimator sees each pair's motion twice (and its inverse) and the unmoved pose, and is
    told the number of pairs; one whose ``estimate`` takes no ``n_independent`` is called without it."""
    calls = []

    class Told:
        def estimate(self, poses, *, n_independent=None):
            calls.append((len(poses), n_independent))
            return bic.estimate(poses, n_independent=n_independent)

    class Untold:
        def estimate(self, poses):
            calls.append((len(poses), None))
            return bic.estimate(poses)

    told = find_articulation(run_result(), estimator=Told())
    n_pairs = told.joints[0].estimate.info["n_pairs"]
    assert calls == [(2 * n_pairs + 1, n_pairs)]
    _check_hinge(told)
    _check_hinge(find_articulation(run_result(), estimator=Untold()))
    assert calls[1] == (2 * n_pairs + 1, None)


def test_the_estimator_is_told_how_far_the_object_reaches(bic):
    """``reach_m``: how far the flap's and the base's points reach from the flap's centre, about the
    far corner of the base (the points the pairs label, so up to a couple of centimetres short)."""
    reaches = []

    class Told:
        def estimate(self, poses, *, n_independent=None, reach_m=None):
            reaches.append(reach_m)
            return bic.estimate(poses, n_independent=n_independent, reach_m=reach_m)

    _check_hinge(find_articulation(run_result(), estimator=Told()))
    far = np.linalg.norm(np.vstack([BASE, LID]) - np.median(LID, axis=0), axis=1).max()
    assert len(reaches) == 1 and far - 0.02 < reaches[0] <= far + 0.005


def test_a_joint_must_explain_more_than_one_pair(bic):
    """One relative motion is always a screw motion about some axis, so it tells no joint: a part whose
    joint explains only one pair (the estimator finding every other pair an outlier) is left out."""

    class OneInlier:
        def estimate(self, poses, *, n_independent=None):
            e = bic.estimate(poses, n_independent=n_independent)
            inliers = e.inliers.copy()
            inliers[2 : n_independent + 1] = inliers[n_independent + 2 :] = False  # all but the first pair
            return dataclasses.replace(e, inliers=inliers)

    art = find_articulation(run_result(), estimator=OneInlier())
    assert art.joints == [] and [p.index for p in art.parts] == [0]
    assert art.summary().startswith("no joint")


def test_a_part_whose_regions_overlap_little_is_linked_by_its_motion(bic):
    """A carried flap whose regions in neighbouring pairs overlap too little to be linked (IoU 0.92-0.95
    here, the base's 0.96-0.98) falls apart into one part per chain of pairs (i, i + 4); its motions
    relative to the base, one joint's, link it back into one part with every pair's evidence."""
    loose = PartsParams(min_overlap=0.955, link_sigmas=0.0)
    assert len(find_articulation(run_result(carried=True), estimator=bic, params=loose).parts) == 5
    art = find_articulation(
        run_result(carried=True), estimator=bic, params=dataclasses.replace(loose, link_sigmas=5.0)
    )
    (joint,) = art.joints
    assert joint.n_pairs == len(run_result().pairs)
    _check_hinge(art)


def test_a_part_that_moves_little_is_linked_against_its_own_pairs_noise(bic):
    """Each motion's velocity field is one pair's measurement: it must move the points by more than
    link_sigmas of that pair's depth noise, not of the two pairs' noise together (which only the
    difference of the two fields carries). A flap moving its points by 6 noise levels a pair (4.2 of
    the two pairs' together) is linked into one part with every pair's evidence."""
    run = run_result(carried=True)
    pair = run.pairs[0]
    field = motions._twist_log(
        np.linalg.inv(pair.motions[0].T_target_from_source) @ pair.motions[1].T_target_from_source
    )
    moved_m = np.median(np.linalg.norm(np.cross(field[0], LID) + field[1], axis=1))
    for p in run.pairs:
        p.evidence.noise_m = moved_m / 6.0
    art = find_articulation(run, estimator=bic, params=PartsParams(min_overlap=0.955, link_sigmas=5.0))
    (joint,) = art.joints
    assert joint.n_pairs == len(run.pairs)
    _check_hinge(art)


def test_labels_become_part_images(bic):
    art = find_articulation(run_result(), estimator=bic)
    cloud, part = _cloud(5, False)
    image = art.label_image(5)
    assert image.shape == (K.height, K.width)
    u, v = cloud.pixels.T
    agree = image[v, u] == part + 1
    assert agree.mean() > 0.97  # points sharing a pixel with the other part may differ
    assert art.label_image(99) is None


def _agreement(art, f: int, chain: bool = False, carried: bool = False, slide: bool = False) -> float:
    """Share of frame f's points whose pixel in the part image has their true part."""
    cloud, part = _cloud(f, carried, chain, slide=slide)
    u, v = cloud.pixels.T
    return float(np.mean(art.label_image(f)[v, u] == part + 1))


def test_each_frame_is_labelled_from_the_parts_motions_not_one_pairs_labels(bic):
    """Every pair gives 40 % of the flap's points (a band along the hinge) to the base; moved by each
    part's motion to the frames where the flap has turned most, they land on the flap's surface only
    under the flap's motion, so each frame's part image is right nonetheless."""
    art = find_articulation(run_result(mislabelled=0.4), estimator=bic)
    _check_hinge(art)
    for f in (0, 10, 23):
        assert _agreement(art, f) > 0.95
    # the pairs' labels alone leave the band on the base
    plain = find_articulation(run_result(mislabelled=0.4), estimator=bic, params=PartsParams(n_views=0))
    assert _agreement(plain, 10) < 0.85


def test_texture_shows_a_part_sliding_along_a_surface(bic, monkeypatch):
    """A flap slides away from its base in their common plane: either part's motion puts most points of
    either part on that plane, so the depth cannot tell them apart, and the pairs give 40 % of the
    flap's points (a band along the seam) to the base. The stripes painted across the slide can:
    moved by the other part's motion, a point lands on another shade."""
    art = find_articulation(run_result(slide=True, mislabelled=0.4), estimator=bic)
    assert [j.estimate.type for j in art.joints] == ["prismatic"]
    assert min(_agreement(art, f, slide=True) for f in (0, 10, 23)) > 0.95
    # with the depth alone, the band stays on the base in some frame
    monkeypatch.setattr(images, "_by_shade", lambda best, decisive, *args, **kw: (best, decisive))
    depth_only = find_articulation(run_result(slide=True, mislabelled=0.4), estimator=bic)
    assert min(_agreement(depth_only, f, slide=True) for f in (0, 10, 23)) < 0.9


def test_a_frame_no_pair_separates_gets_its_parts(bic):
    """The last frames are in no pair that sees the flap move: the flap's state there is found by
    looking its points up in the frame at each state of its joint, and the frames get both parts."""
    art = find_articulation(run_result(hidden=range(20, 24)), estimator=bic)
    assert not np.isfinite(art.joints[0].estimate.states[21]), "no pair gives the state of frame 21"
    assert _agreement(art, 21) > 0.95
    assert (art.label_image(21) == 2).any()


def test_a_frame_where_the_part_is_not_found_gets_it_from_the_joint(bic, monkeypatch):
    """Where looking the flap's points up finds none of them (hidden, or turned away), its state is
    held from the nearest frame that gave one, and the frame's points take the part whose points,
    placed there by the joint, are nearest: the flap keeps its part, a few degrees off."""
    monkeypatch.setattr(
        images, "_look", lambda motions, points, view, reach_m: np.full((len(motions), len(points)), np.nan)
    )
    art = find_articulation(run_result(hidden=range(20, 24)), estimator=bic)
    for f in (21, 23):
        assert (art.label_image(f) == 2).any()
        assert _agreement(art, f) > 0.9


def test_a_frame_no_pair_reaches_is_placed_between_its_neighbours(bic):
    """The pairs from and to frame 10 of a carried object are skipped: no pair gives the base's pose
    there, which stays unknown, but the frame's parts are found with the base placed between the
    frames before and after it and the flap at its state there."""
    result = run_result(carried=True)
    for p in result.pairs:
        if 10 in (p.i, p.j):
            p.decision, p.motions, p.labels, p.evidence = "skipped", [], None, None
    art = find_articulation(result, estimator=bic)
    assert np.isnan(art.base_poses[10]).all()
    assert _agreement(art, 10, carried=True) > 0.9


def test_a_chain_is_followed_into_frames_no_pair_separates(bic):
    """The lid's state is found first, then the tip's on the lid."""
    art = find_articulation(run_result(hidden=range(20, 24), chain=True), estimator=bic)
    assert [(j.parent, j.child) for j in art.joints] == [(0, 1), (1, 2)]
    assert not np.isfinite(art.joints[1].estimate.states[22])
    assert _agreement(art, 22, chain=True) > 0.9
    assert set(np.unique(art.label_image(22))) == {0, 1, 2, 3}


def test_a_moved_point_is_looked_up_where_it_projects():
    """On the surface, or in front of it (the camera sees past it): its distance along the ray; behind
    it, or out of the picture: no evidence (NaN). A part pays that distance, or infinitely when it is
    beyond reach, and the reach when there is no evidence: the unmoved points go to the part that
    stays, by more than the reach against one beyond reach, by less against one without evidence."""
    from artclass_plugins.parts._compiled import by_depth

    cloud, _ = _cloud(0, False)
    points = cloud.points[:: len(cloud.points) // 50]
    moves = np.stack([_T(t=(0.0, 0.0, dz)) for dz in (0.0, 0.002, -0.05, 0.05)] + [_T(t=(5.0, 0.0, 0.0))])
    found = _look(moves, points, cloud.view, reach_m=0.01)
    assert np.abs(found[0]).max() < 0.002  # 0.5 mm of depth noise, and a pixel's rounding
    assert np.abs(found[1] - 0.002).max() < 0.002
    assert (found[2] > 0.045).all()  # 5 cm (or, near the edge, no surface at all: inf)
    assert np.isnan(found[3]).all() and np.isnan(found[4]).all()
    none = np.zeros((2, len(points)))
    for moved, decisive in ((2, True), (3, False), (4, False)):
        best, sure, _ = by_depth(found[[moved, 0]].copy(), none, none, 0.01, 0.01)
        assert (best == 1).all() and (sure == decisive).all()


def test_points_go_to_the_part_that_explains_them_by_depth_then_by_texture():
    """The compiled choice does what its numpy expression does: each part pays the distance to the
    surface where it lands the point (inf off the surface, the reach where hidden), the cheapest wins
    when the next costs more than the margin more, and a point left open goes to the part (among
    those within the margin) that changes its intensity least, when the next changes it by more than
    the limit more."""
    from artclass_plugins.parts._compiled import by_depth, by_shade

    rng = np.random.default_rng(8)
    residual = rng.choice([np.nan, np.inf, 0.001, 0.004, 0.006, 0.02], (3, 400))
    landings = rng.integers(0, 3, (3, 400)).astype(float)
    change = rng.uniform(0, 30, (3, 400)) * landings
    reach, margin, limit = 0.01, 0.003, 8.0
    cost = np.where(np.isnan(residual), reach, np.where(residual < reach, residual, np.inf))
    nearest = np.sort(cost, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        decisive = nearest[1] - nearest[0] > margin
        mean = np.where(landings > 0, change / landings, np.inf)
    mean = np.where(cost <= nearest[0] + margin, mean, np.inf)
    best, sure, found = by_depth(residual, change, landings, reach, margin)
    np.testing.assert_array_equal(best, np.argmin(cost, axis=0))
    np.testing.assert_array_equal(sure, decisive)
    np.testing.assert_array_equal(found, mean)
    assert 0 < decisive.sum() < 400 and np.isinf(mean).any()
    lowest = np.sort(mean, axis=0)
    with np.errstate(invalid="ignore"):
        shade = ~decisive & (lowest[1] - lowest[0] > limit)
    best, sure = by_shade(best, sure, found, limit)
    np.testing.assert_array_equal(best, np.where(shade, np.argmin(mean, axis=0), np.argmin(cost, axis=0)))
    np.testing.assert_array_equal(sure, decisive | shade)
    assert shade.any()


def test_a_rigid_sequence_gets_no_joint(bic):
    art = find_articulation(run_result(label="rigid"), estimator=bic)
    assert art.joints == [] and len(art.parts) == 1
    assert art.to_dict()["joints"] == [] and art.summary().startswith("no joint")


def test_parts_need_the_labelled_points(bic):
    result = run_result()
    for p in result.pairs:
        p.evidence = None
    for f in result.frames:
        f.cloud = None
    with pytest.raises(ArtclassError, match="keep_clouds=True"):
        find_articulation(result, estimator=bic)


def test_frame_states_from_pair_differences():
    """States from the differences of interleaved pairs (i, i + 3), with a gap: each chain is exact,
    and the constant-speed term places the chains relative to each other and bridges the gap."""
    truth = np.linspace(0.0, 1.0, 16) ** 2
    pairs = [(i, i + 3) for i in range(13) if not {i, i + 3} & {6, 7, 8}]  # frames 6-8 unseen
    deltas = np.array([truth[j] - truth[i] for i, j in pairs])
    states, std = frame_states(16, pairs, deltas, np.full(len(pairs), 0.01), smoothness=1e-3)
    assert np.isnan(states[6:9]).all() and np.isfinite(np.delete(states, [6, 7, 8])).all()
    np.testing.assert_allclose(states[[0, 3]], truth[[0, 3]], atol=1e-6)  # frame 0's chain, exact
    np.testing.assert_allclose(np.delete(states, [6, 7, 8]), np.delete(truth, [6, 7, 8]), atol=0.05)
    assert std[0] == 0 and (std[np.isfinite(states)][1:] > 0).all()


def test_a_pair_with_one_motion_moves_the_base():
    """A pair that found one motion saw the whole object move as one body: that motion joins the base's
    track, even when its region overlapped a moving part's more; pairs with two motions keep theirs."""
    from types import SimpleNamespace

    pairs = [SimpleNamespace(motions=[None] * n) for n in (2, 1, 2)]
    track = {(0, 0): 0, (0, 1): 1, (1, 0): 1, (2, 0): 0, (2, 1): 1}
    moved = _one_body_pairs_on(0, SimpleNamespace(pairs=pairs), track)
    assert moved == {(0, 0): 0, (0, 1): 1, (1, 0): 0, (2, 0): 0, (2, 1): 1}


def test_the_base_is_the_part_left_still_not_the_largest():
    """A small body that stays still while a large flap turns is the base; when the hand carries both
    (no part is ever still), or no pair shows the object articulated, the largest part is."""
    from types import SimpleNamespace

    def run(decision, body_moves_m):
        motions = [Motion(np.eye(4), "body", 50, body_moves_m), Motion(np.eye(4), "flap", 500, 0.02)]
        pairs = [SimpleNamespace(decision=decision, motions=motions, info=dict(threshold_m=0.004))] * 3
        return SimpleNamespace(label="articulated", pairs=pairs)

    track = {(n, m): m for n in range(3) for m in range(2)}
    size = {0: 150, 1: 1500}
    assert _still_track(run("AM", 0.001), track, size, min_pairs=2) == 0
    assert _still_track(run("AM", 0.01), track, size, min_pairs=2) == 1
    assert _still_track(run("NM", 0.001), track, size, min_pairs=2) == 1


def test_a_motion_between_two_pairs_that_saw_the_base_still_is_no_motion():
    """The base is still where the rule found no motion or a motion below its threshold, and in a
    pair whose frames the pairs from the frame before and the frame after saw it still (a one-body fit
    there blends the base with a moving part); a carried base keeps the motions of its pairs."""
    from types import SimpleNamespace

    turn = _hinge(0.1)

    def run(moved_m):
        pairs = [
            SimpleNamespace(
                i=i,
                j=i + 4,
                decision="AM",
                info=dict(threshold_m=0.004),
                motions=[Motion(turn, "object", 50, m)],
            )
            for i, m in enumerate(moved_m)
        ]
        return SimpleNamespace(pairs=pairs)

    track = {(n, 0): 0 for n in range(4)}
    still = _base_motions(run([0.001, 0.01, 0.002, 0.01]), track, 0)
    np.testing.assert_array_equal(
        [np.allclose(still[n], np.eye(4)) for n in range(4)], [True, True, True, False]
    )
    carried = _base_motions(run([0.01, 0.01, 0.01, 0.01]), track, 0)
    assert not any(np.allclose(T, np.eye(4)) for T in carried.values())


def test_chain_interleaved_ties_the_chains():
    poses = [_carry(f, True) for f in range(10)]
    pairs = [(i, i + 3, poses[i + 3] @ np.linalg.inv(poses[i])) for i in range(7)]
    out = chain_interleaved(10, pairs)
    np.testing.assert_allclose(out[::3], np.stack(poses[::3]), atol=1e-9)
    np.testing.assert_allclose(out, np.stack(poses), atol=1e-3)  # the others: interpolated, then chained


def _flap_truth() -> dict:
    """The generator's truth of the flap of :func:`run_result`."""
    return dict(
        parts=[dict(parent=-1, joint=None), dict(parent=0, joint=0)],
        joints=[
            dict(
                type="revolute",
                parent=0,
                child=1,
                state=list(STATES),
                axis_camera0=[AXIS] * N_FRAMES,
                origin_camera0_m=[HINGE] * N_FRAMES,
            )
        ],
        part_points_m=[[BASE.tolist(), LID.tolist()]],
        part_poses=[[np.eye(4).tolist()] * 2],
    )


def _true_part_images(frames) -> dict[int, np.ndarray]:
    images = {}
    for f in frames:
        cloud, part = _cloud(f, False)
        images[f] = np.zeros((K.height, K.width), np.uint8)
        images[f][cloud.pixels[:, 1], cloud.pixels[:, 0]] = part + 1
    return images


def test_score_against_the_truth(bic):
    art = find_articulation(run_result(), estimator=bic)
    truth, images = _flap_truth(), _true_part_images(art.frames)
    scores = score_articulation(art, truth, images)
    (joint,) = scores["joints"]
    assert joint["type"] == joint["true_type"] == "revolute"
    assert joint["axis_direction_error_deg"] < 1 and joint["axis_position_error_mm"] < 2
    assert joint["state_error"] < 0.5 and joint["state_unit"] == "deg"
    assert scores["part_iou"] > 0.95
    # the same joint scored against the wrong type and a tilted axis
    truth["joints"][0].update(type="prismatic", axis_camera0=[[1.0, 0.0, 0.0]] * N_FRAMES)
    (wrong,) = score_articulation(art, truth, images)["joints"]
    assert wrong["true_type"] == "prismatic" and wrong["axis_direction_error_deg"] > 85


def test_part_iou_over_every_frame_counts_the_frames_given_up(bic):
    """An estimate without part images for the second half of the video keeps its IoU over the frames
    where it found a moving part, but scores 0 on the frames it gave up over every frame."""
    art = find_articulation(run_result(), estimator=bic)
    truth, images = _flap_truth(), _true_part_images(range(N_FRAMES))
    full = score_articulation(art, truth, images)
    assert full["part_iou"] == pytest.approx(full["part_iou_all_frames"]) and full["part_iou"] > 0.95
    half = N_FRAMES // 2
    gave_up = dataclasses.replace(art, views={f: v for f, v in art.views.items() if f < half})
    scores = score_articulation(gave_up, truth, images)
    assert scores["part_iou"] > 0.95
    assert scores["part_iou_all_frames"] == pytest.approx(
        full["part_iou_all_frames"] * half / N_FRAMES, abs=0.02
    )


def test_the_urdf_of_a_found_hinge_moves_like_the_flap(bic, tmp_path):
    """The exported model, loaded by a maintained parser and set to a state seen in the video, puts
    the flap's mesh where the flap was in that frame."""
    import yourdfpy

    from artclass_plugins.joints.urdf import model_from_articulation, write_urdf

    art = find_articulation(run_result(), estimator=bic)
    robot = yourdfpy.URDF.load(
        str(write_urdf(model_from_articulation(art, name="flap"), tmp_path)),
        build_scene_graph=True,
        load_meshes=True,
    )
    (joint,) = robot.joint_map.values()
    assert (joint.parent, joint.child, joint.type) == ("base", "part1", "revolute")
    f = 15
    robot.update_cfg({joint.name: art.joints[0].estimate.states[f]})
    mesh = robot.scene.geometry["part1.ply"].vertices
    placed = (
        mesh @ robot.get_transform("part1", "base")[:3, :3].T + robot.get_transform("part1", "base")[:3, 3]
    )
    flap = LID @ _hinge(STATES[f])[:3, :3].T + _hinge(STATES[f])[:3, 3]
    np.testing.assert_allclose(np.sort(placed, axis=0)[[0, -1]], np.sort(flap, axis=0)[[0, -1]], atol=0.003)


def test_the_urdf_of_a_chain_moves_like_the_tip(bic, tmp_path):
    """The chain's URDF is a tree base - part1 - part2; set to a frame's states, the tip's mesh is
    where the tip was in that frame."""
    import yourdfpy

    from artclass_plugins.joints.urdf import model_from_articulation, write_urdf

    art = find_articulation(run_result(chain=True), estimator=bic)
    robot = yourdfpy.URDF.load(
        str(write_urdf(model_from_articulation(art, name="ruler"), tmp_path)),
        build_scene_graph=True,
        load_meshes=True,
    )
    assert {(j.parent, j.child) for j in robot.joint_map.values()} == {("base", "part1"), ("part1", "part2")}
    f = 15
    state = {f"part{joint.child}": joint.estimate.states[f] for joint in art.joints}
    robot.update_cfg({j.name: state[j.child] for j in robot.joint_map.values()})
    T = robot.get_transform("part2", "base")
    placed = robot.scene.geometry["part2.ply"].vertices @ T[:3, :3].T + T[:3, 3]
    tip = transform(TIP, _poses(f, True)[2])
    np.testing.assert_allclose(np.sort(placed, axis=0)[[0, -1]], np.sort(tip, axis=0)[[0, -1]], atol=0.003)


def test_evaluation_reports_parts_and_joints():
    """The evaluation sums the per-sequence joint scores up: over the articulated sequences where a
    part was found, and counts rigid or static sequences that wrongly got a joint."""
    from artclass_core.evaluate import Evaluation, SequenceOutcome, markdown

    def outcome(name, truth, joints, iou=0.8):
        o = SequenceOutcome(name, name.split("_")[0], truth, (truth,), truth)
        o.joints = dict(
            part_iou=iou if joints else None, part_iou_all_frames=iou / 2 if joints else None, joints=joints
        )
        return o

    hinge = dict(
        type="revolute",
        true_type="revolute",
        axis_direction_error_deg=2.0,
        axis_position_error_mm=8.0,
        state_error=1.0,
        state_unit="deg",
    )
    slide = dict(
        type="revolute",
        true_type="prismatic",
        axis_direction_error_deg=6.0,
        axis_position_error_mm=None,
        state_error=4.0,
        state_unit="mm",
    )
    outs = [
        outcome("laptop_a", "articulated", [hinge]),
        outcome("drawer_a", "articulated", [slide], iou=0.6),
        outcome("drawer_b", "articulated", []),
        outcome("mug_a", "rigid", []),
        outcome("book_a", "rigid", [dict(hinge, true_type=None)]),
    ]
    j = Evaluation("dense", outs, {}).metrics()["joints"]
    assert (
        j["n_articulated"],
        j["n_with_part"],
        j["n_not_articulated"],
        j["not_articulated_with_joint"],
    ) == (3, 2, 2, 1)
    assert j["n_joints"] == 2 and j["joint_type_accuracy"] == 0.5
    assert j["axis_direction_error_deg"] == 4.0 and j["axis_position_error_mm"] == 8.0
    assert (j["state_error_deg"], j["state_error_mm"], j["part_iou"]) == (1.0, 4.0, pytest.approx(0.7))
    assert j["part_iou_all_frames"] == pytest.approx(0.35)
    assert j["per_object"]["drawer"]["joint_type_accuracy"] == 0.0
    text = markdown([Evaluation("dense", outs, {})])
    assert "| median part IoU, every frame (0 where none was found) | 0.35 |" in text
    assert "| articulated sequences with a moving part found | 2 / 3 |" in text
    assert "| rigid or static sequences with a joint | 1 / 2 |" in text


def test_overlaps_count_the_pixels_both_labellings_label():
    """Two labellings of neighbouring frames are compared on the pixels both label, whatever order their
    points come in: each pair of motions gets the IoU of its pixels there, counted by hand."""
    rng = np.random.default_rng(2)
    grid = np.stack(np.meshgrid(np.arange(40), np.arange(30)), -1).reshape(-1, 2)
    first, second = rng.choice(len(grid), 900, replace=False), rng.choice(len(grid), 700, replace=False)
    labels = {"a": rng.integers(-1, 3, len(grid)), "b": rng.integers(-1, 2, len(grid))}

    def observation(pair, pick, name):
        return observations._Observation(
            pair, 0, grid[pick], np.zeros((len(pick), 3)), labels[name][pick], True
        )

    found = tracks._overlaps(observation(0, first, "a"), observation(1, second, "b"))
    shared = np.intersect1d(first, second)
    expected = {}
    for m in range(3):
        for n in range(2):
            in_a, in_b = (labels["a"][shared] == m).sum(), (labels["b"][shared] == n).sum()
            both = ((labels["a"][shared] == m) & (labels["b"][shared] == n)).sum()
            if both:
                expected[(m, n)] = both / (in_a + in_b - both)
    assert len(expected) == 6 and {(a[1], b[1]): iou for iou, a, b in found} == pytest.approx(expected)
    assert all(a[0] == 0 and b[0] == 1 for _, a, b in found)


@pytest.mark.parametrize("shape", [(48, 64), (2, 3), (1, 1)])
def test_intensities_where_points_land_are_smoothed_as_opencv_smooths(shape):
    """The part images compare intensities smoothed over a pixel's neighbours, computed only at the
    pixels looked at: the same values as blurring the whole image with OpenCV, edges included."""
    from artclass_plugins.parts._compiled import smoothed_at

    gray = np.random.default_rng(4).integers(0, 256, shape).astype(np.uint8)
    pixels = np.stack(np.meshgrid(np.arange(shape[1]), np.arange(shape[0])), -1).reshape(-1, 2)
    blurred = cv2.GaussianBlur(gray, (3, 3), 0)
    np.testing.assert_array_equal(smoothed_at(gray, pixels), blurred[pixels[:, 1], pixels[:, 0]])


def test_reach_measures_the_parent_points_placed_at_state_0():
    """How far a part and its parent reach from the part's centre: the parent's points of each frame
    with its placement undone, or as they are when it is placed in no frame."""
    rng = np.random.default_rng(9)
    own, centre = rng.normal(0, 0.05, (200, 3)), np.array([0.01, 0.0, 0.5])
    parent = {f: rng.normal(0, 0.1, (150, 3)) + [0.0, 0.0, 0.5] for f in range(4)}
    placement = np.stack(
        [_T(Rotation.from_rotvec([0.0, 0.3 * f, 0.0]).as_matrix(), (0.05 * f, 0, 0)) for f in range(4)]
    )
    placement[3] = np.nan
    placed = np.concatenate([own] + [transform(parent[f], np.linalg.inv(placement[f])) for f in range(3)])
    assert tree._reach(own, parent, placement, centre) == pytest.approx(
        np.linalg.norm(placed - centre, axis=1).max()
    )
    unplaced = np.concatenate([own, *parent.values()])
    assert tree._reach(own, parent, np.full_like(placement, np.nan), centre) == pytest.approx(
        np.linalg.norm(unplaced - centre, axis=1).max()
    )


def _wandering(run: RunResult, *, move_m: float, turn_rad: float) -> RunResult:
    """``run`` with each pair's second motion replaced by a patch that is there in this pair only and
    moves off the base by about ``move_m`` and ``turn_rad`` in a random direction: what real depth
    error, a calibration a few percent off or a motion too large to register makes of a rigid object,
    pair by pair (seeded)."""
    rng = np.random.default_rng(3)
    for n, p in enumerate(run.pairs):
        pixels = p.points.pixels
        column = pixels[:, 0].min() + (n * 37) % max(1, int(np.ptp(pixels[:, 0])))
        turn = Rotation.from_rotvec(rng.normal(0, turn_rad, 3)).as_matrix()
        off = _T(turn, rng.normal(0, move_m, 3)) @ p.motions[0].T_target_from_source
        p.motions = [p.motions[0], dataclasses.replace(p.motions[0], T_target_from_source=off)]
        p.labels = (np.abs(pixels[:, 0] - column) < 6).astype(int)
    return run


def test_a_video_is_articulated_only_when_a_part_moves_about_a_joint_over_it():
    registry = load_registry()
    hinge = run_result()
    for f in hinge.frames:  # the pipeline keeps each pair's labelled points, not the clouds
        f.cloud = None
    for p in hinge.pairs:
        p.evidence = None
    confirmed, why = joints_over_video(registry, hinge)
    assert confirmed and "revolute" in why, why
    for move_m, turn_rad in ((0.03, 0.1), (0.1, 0.5)):
        confirmed, why = joints_over_video(
            registry, _wandering(run_result(), move_m=move_m, turn_rad=turn_rad)
        )
        assert not confirmed and "no part moves about a joint" in why, why


def test_an_unconfirmed_articulation_labels_the_video_by_its_motion():
    pairs = [PairResult(i, i + 2, d) for i, d in enumerate(["RM", "AM", "AM", "RM", "RM"])]
    run = labelled_result(
        {}, [], pairs, w=3, params={}, plugins={}, timing={}, confirm=lambda r: (False, "no joint")
    )
    assert (run.label, run.reason, run.filtered) == ("rigid", "no joint", ["RM", "AM", "AM", "RM", "RM"])
    told = labelled_result(
        {}, [], pairs, w=3, params={}, plugins={}, timing={}, confirm=lambda r: (True, "a hinge")
    )
    assert (told.label, told.reason) == ("articulated", "a hinge")
    still = [PairResult(i, i + 2, d) for i, d in enumerate(["NM", "AM", "AM", "NM", "undecided"])]
    run = labelled_result({}, [], still, w=3, params={}, plugins={}, timing={}, confirm=lambda r: (False, ""))
    assert run.label == "rigid" and run.filtered == ["NM", "AM", "AM", "NM"]  # undecided: not filtered
