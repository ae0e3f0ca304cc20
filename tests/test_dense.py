"""The dense pipeline's parts on scenes whose answer is known: projective look-ups, the motion
hypotheses of the registrar, and the rule's model selection.

The scenes are textured flat pieces rendered here (a z-buffer that keeps each pixel's surface point,
so the colour image carries a texture that moves with the surface, as optical flow needs).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from artclass_core import Cloud, Frame, Intrinsics, MotionEvidence
from artclass_core.types import FREE_SPACE, OCCLUDED, OFF_OBJECT, SURFACE, UNSEEN, View
from artclass_plugins.dense.flow import Landings
from artclass_plugins.dense.image import ImagePreprocessor, depth_step, filter_depth
from artclass_plugins.dense.projective import Target, kabsch, look_all, robust_kabsch
from artclass_plugins.dense.registrar import DenseRegistrar
from artclass_plugins.dense.rule import DenseRule, DenseRuleParams

from conftest import panel_points

K = Intrinsics(fx=320.0, fy=320.0, cx=159.5, cy=119.5, width=320, height=240)
DEPTH_M = 0.5


def rotation(axis, angle_deg: float) -> np.ndarray:
    return cv2.Rodrigues(np.radians(angle_deg) * np.asarray(axis, float))[0]


def pose(R: np.ndarray | None = None, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = np.eye(3) if R is None else R, t
    return T


_NOISE = cv2.GaussianBlur(np.random.default_rng(7).normal(0, 1, (1024, 1024)).astype(np.float32), (0, 0), 3)
_NOISE = np.clip(128 + 60 * _NOISE / _NOISE.std(), 0, 255).astype(np.uint8)


def texture(surface_xy: np.ndarray) -> np.ndarray:
    """Grey levels of a texture fixed to the surface (so that it moves with it): white noise blurred
    to 3 mm, sampled at 1 mm, so that it is neither periodic nor aliased by the pixels."""
    cell = np.floor(surface_xy / 0.001).astype(np.int64) % len(_NOISE)
    return _NOISE[cell[:, 1], cell[:, 0]]


def frame(pieces: list[tuple[np.ndarray, np.ndarray, int]], index: int = 0) -> Frame:
    """Render pieces ``(points in the piece's own frame (N, 3), T_camera_from_piece, id)``: the
    object is every piece with id >= 1; a table (id 0) may lie behind it. ``frame.owner`` is the id
    seen at each pixel (-1: nothing)."""
    cam, surf, ids = [], [], []
    for points, T, ident in pieces:
        cam.append(points @ T[:3, :3].T + T[:3, 3])
        surf.append(points[:, :2] + 0.3 * ident)  # each piece its own patch
        ids.append(np.full(len(points), ident))
    cam, surf, ids = np.concatenate(cam), np.concatenate(surf), np.concatenate(ids)
    u = np.round(K.fx * cam[:, 0] / cam[:, 2] + K.cx).astype(int)
    v = np.round(K.fy * cam[:, 1] / cam[:, 2] + K.cy).astype(int)
    ok = (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
    pix = (v * K.width + u)[ok]
    order = np.lexsort((cam[ok, 2], pix))
    first = order[np.unique(pix[order], return_index=True)[1]]
    depth = np.zeros(K.width * K.height, np.float32)
    grey = np.zeros(K.width * K.height, np.uint8)
    owner = np.full(K.width * K.height, -1)
    depth[pix[first]] = cam[ok][first, 2]
    grey[pix[first]] = texture(surf[ok][first])
    owner[pix[first]] = ids[ok][first]
    shape = (K.height, K.width)
    rgb = np.repeat(grey.reshape(shape)[..., None], 3, axis=2)
    out = Frame(index, f"{index:06d}", rgb, depth.reshape(shape), owner.reshape(shape) >= 1)
    out.owner = owner.reshape(shape)
    return out


def cloud(f: Frame):
    return ImagePreprocessor().process(f, f.mask, intrinsics=K)


TABLE = (panel_points(0.5, 0.4, spacing_m=0.0008) - [0.25, 0.0, 0.0], pose(t=(0.0, 0.0, DEPTH_M + 0.03)), 0)
BASE = panel_points(0.16, 0.10, spacing_m=0.0004) - [0.08, 0.0, 0.0]  # 16 x 10 cm plate
LEVER = panel_points(0.10, 0.02, spacing_m=0.0004)  # 10 x 2 cm, pivot at x = 0


def plate_with_lever(
    angle_deg: float, carry: np.ndarray | None = None, index: int = 0, *, axis=(0, 1, 0)
) -> Frame:
    """A plate facing the camera with a lever on it (5 mm proud), turned by ``angle_deg`` about a
    line through the plate's centre: vertical (``axis`` y, the lever lifts) or along the view (z, the
    lever turns in the plate's plane); the whole object moved by ``carry``."""
    plate = (np.eye(4) if carry is None else carry) @ pose(t=(0.0, 0.0, DEPTH_M))
    lever = plate @ pose(rotation(axis, angle_deg), t=(0.0, 0.0, -0.005))
    return frame([(BASE, plate, 1), (LEVER, lever, 2), TABLE], index)


# -- outlier removal ------------------------------------------------------------------------------


def test_outlier_removal_keeps_a_surface_the_sensor_sees_sparsely():
    """At a grazing angle a sensor loses about half of a surface's pixels; the rest are good depth."""
    rows, cols = np.mgrid[0:60, 0:80]
    depth = (0.8 + 0.004 * rows).astype(np.float32)  # a floor seen obliquely: 4 mm deeper per row
    valid = np.random.default_rng(3).random(depth.shape) < 0.45
    kept = filter_depth(depth, valid, tolerance_m=np.full(depth.shape, 0.006), smoothing_px=0) > 0
    assert kept[valid].mean() > 0.95


def test_outlier_removal_drops_a_flying_pixel_between_two_surfaces():
    depth = np.full((40, 40), 1.0, np.float32)
    depth[:, 20:] = 1.2
    valid = np.random.default_rng(4).random(depth.shape) < 0.6
    valid[20, 21] = True
    depth[20, 21] = 1.1  # next to the edge, the sensor mixed the two surfaces
    kept = filter_depth(depth, valid, tolerance_m=np.full(depth.shape, 0.01), smoothing_px=0) > 0
    assert not kept[20, 21]
    assert kept[valid].mean() > 0.9


# -- projective look-ups --------------------------------------------------------------------------


def test_look_tells_surface_occluded_free_space_off_object_and_unseen():
    """A plate 0.5 m away in front of a table 3 cm behind it: what a point finds at its pixel."""
    f = frame([(BASE, pose(t=(0.0, 0.0, DEPTH_M)), 1), TABLE])
    target = Target.of(cloud(f))
    points = np.array(
        [
            [0.0, 0.0, DEPTH_M + 0.001],  # on the plate, 1 mm behind it
            [0.0, 0.0, DEPTH_M + 0.02],  # hidden behind the plate
            [0.0, 0.0, DEPTH_M - 0.02],  # in front of the plate: the camera sees past it
            [0.2, 0.0, DEPTH_M + 0.03],  # on the table, far from the object
            [5.0, 0.0, DEPTH_M],
        ]
    )  # outside the image
    status, residual = look_all(np.eye(4)[None], points, target, reach_m=np.full(5, 0.005), off_object_px=3.0)
    assert status[0].tolist() == [SURFACE, OCCLUDED, FREE_SPACE, OFF_OBJECT, UNSEEN]
    assert abs(residual[0, 0]) == pytest.approx(0.001, abs=2e-4)
    assert np.isnan(residual[0, 1:]).all()


def test_a_point_landing_where_a_hand_may_cover_the_object_is_hidden_not_off_it():
    """A segmenter leaves a hand's pixels (and its outline's) out of the object's mask: it cannot
    tell whether the object is under them. A point landing there beside the mask is no evidence
    against its motion; a point the camera sees past is still free space."""
    f = frame([(BASE, pose(t=(0.0, 0.0, DEPTH_M)), 1), TABLE])
    c = cloud(f)
    points = np.array([[0.12, 0.0, DEPTH_M + 0.03], [0.12, 0.0, DEPTH_M - 0.02]])  # on the table; before it

    def look():
        return look_all(np.eye(4)[None], points, Target.of(c), reach_m=np.full(2, 0.005), off_object_px=3.0)

    assert look()[0][0].tolist() == [OFF_OBJECT, FREE_SPACE]
    c.view.covered = np.zeros_like(f.mask)
    right = round(K.cx + K.fx * 0.09 / DEPTH_M)
    c.view.covered[:, right:] = True  # a hand over the table right of the plate
    status, residual = look()
    assert status[0].tolist() == [OCCLUDED, FREE_SPACE]
    assert np.isnan(residual).all()


def test_robust_kabsch_recovers_a_motion_despite_wrong_matches():
    rng = np.random.default_rng(0)
    source = rng.uniform(-0.1, 0.1, (200, 3)) + [0, 0, DEPTH_M]
    T = pose(rotation((0, 0, 1), 12.0), t=(0.02, -0.01, 0.03))
    target = source @ T[:3, :3].T + T[:3, 3]
    target[:40] += rng.uniform(-0.05, 0.05, (40, 3))  # 20 % wrong matches
    assert not np.allclose(kabsch(source, target), T, atol=1e-3)
    np.testing.assert_allclose(robust_kabsch(source, target, inlier_m=0.002), T, atol=1e-6)


# -- the registrar and the rule on rendered pairs ----------------------------------------------


def decide(a: Frame, b: Frame, **params):
    source, target = cloud(a), cloud(b)
    evidence = DenseRegistrar().register_pair(source, target)
    return evidence, DenseRule(DenseRuleParams(**params)).decide(evidence), source


def angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


@pytest.mark.parametrize("angle", [8.0, 15.0])
def test_a_lifted_lever_is_articulated_and_segmented(angle):
    """A thin part (2 cm wide, 14 % of the points) lifted about its hinge: two motions, each the
    true one, and the pair's labels are the parts."""
    _, out, source = decide(plate_with_lever(0.0), plate_with_lever(angle, index=1))
    assert out.decision == "AM", out.reason
    base, part = out.motions[0], out.motions[1]
    assert angle_deg(base.T_target_from_source[:3, :3]) < 1.0
    assert angle_deg(part.T_target_from_source[:3, :3]) == pytest.approx(angle, abs=0.5)
    # The pair's labels are the parts: lever pixels take the lever's motion.
    on_lever = plate_with_lever(0.0).owner[source.pixels[:, 1], source.pixels[:, 0]] == 2
    labels = out.labels[: len(source.points)]
    seen = labels >= 0
    assert seen.mean() > 0.8
    assert ((labels == 1) == on_lever)[seen].mean() > 0.9


def test_a_lever_turning_in_the_plane_of_its_plate_is_seen_by_its_texture():
    """Turning 16 degrees in the plate's plane, the lever keeps its depth but for its edges; the
    optical flow on its texture sees it. Once the lever has its own motion, the plate keeps its own
    (none), not the compromise that fits the whole object best."""
    _, out, source = decide(
        plate_with_lever(0.0, axis=(0, 0, 1)), plate_with_lever(16.0, index=1, axis=(0, 0, 1))
    )
    assert out.decision == "AM", out.reason
    assert angle_deg(out.motions[0].T_target_from_source[:3, :3]) < 0.5
    assert angle_deg(out.motions[1].T_target_from_source[:3, :3]) > 5.0
    on_lever = plate_with_lever(0.0).owner[source.pixels[:, 1], source.pixels[:, 0]] == 2
    labels = out.labels[: len(source.points)]
    assert ((labels == 1) == on_lever)[labels >= 0].mean() > 0.85


def test_carried_plate_with_a_fixed_lever_is_one_motion():
    """The same object carried (turned 3 degrees and moved 1 cm: 2 to 3 cm, 15 to 20 px, on the
    object) with the lever still: rigid."""
    carry = pose(cv2.Rodrigues(np.array([0.02, 0.03, 0.03]))[0], t=(0.01, -0.005, 0.005))
    _, out, _ = decide(plate_with_lever(20.0), plate_with_lever(20.0, carry, index=1))
    assert out.decision == "RM", out.reason
    assert len(out.motions) == 1


@pytest.mark.parametrize("error_px", [12.0, 25.0])
def test_optical_flow_that_misleads_everywhere_makes_no_part(monkeypatch, error_px):
    """Stripes can mislead optical flow over a whole object (a helical stripe on a turning can seems
    to travel along it): every point's flow lands ``error_px`` off where the carry took it. The fits
    that use the flow are pulled off with it, but the object's motion fitted to depth alone is still
    a hypothesis: one motion, not a part."""
    import artclass_plugins.dense.registrar as registrar

    carry = pose(cv2.Rodrigues(np.array([0.02, 0.03, 0.03]))[0], t=(0.01, -0.005, 0.005))

    def misled(source, target, **_):
        moved = source.points @ carry[:3, :3].T + carry[:3, 3]
        u = K.fx * moved[:, 0] / moved[:, 2] + K.cx + error_px
        v = K.fy * moved[:, 1] / moved[:, 2] + K.cy
        return np.column_stack([u, v]), np.full((len(u), 2), np.nan)

    monkeypatch.setattr(registrar, "flow_targets", misled)
    _, out, _ = decide(plate_with_lever(20.0), plate_with_lever(20.0, carry, index=1))
    assert out.decision == "RM", out.reason


def test_flat_plate_sliding_in_its_own_plane_is_one_motion_not_a_static_scene():
    """A texture-rich flat plate slides 1 cm along itself: depth alone cannot see it, flow does."""
    slide = pose(t=(0.01, 0.0, 0.0))
    a = frame([(BASE, pose(t=(0.0, 0.0, DEPTH_M)), 1), TABLE])
    b = frame([(BASE, slide @ pose(t=(0.0, 0.0, DEPTH_M)), 1), TABLE], 1)
    _, out, _ = decide(a, b)
    assert out.decision == "RM", out.reason
    np.testing.assert_allclose(out.motions[0].T_target_from_source[:3, 3], [0.01, 0.0, 0.0], atol=0.002)


def tube(spacing_m: float = 0.0004) -> np.ndarray:
    """The half of a 16 cm tube of radius 3 cm that faces the camera, its axis along x."""
    around = np.arange(-np.pi / 2, np.pi / 2, spacing_m / 0.03)
    along = np.arange(-0.08, 0.08, spacing_m)
    a, x = np.meshgrid(around, along)
    return np.column_stack([x.ravel(), 0.03 * np.sin(a.ravel()), -0.03 * np.cos(a.ravel())])


def test_depth_quantisation_is_not_a_second_motion():
    """A structured-light sensor delivers depth in steps (3 mm at about 1 m): smoothing leaves whole
    patches half a step off, which a carried rigid tube must not turn into a part."""
    carry = pose(cv2.Rodrigues(np.array([0.02, 0.03, 0.03]))[0], t=(0.01, -0.005, 0.005))
    a = frame([(tube(), pose(t=(0.0, 0.0, DEPTH_M)), 1), TABLE])
    b = frame([(tube(), carry @ pose(t=(0.0, 0.0, DEPTH_M)), 1), TABLE], 1)
    for f in (a, b):
        f.depth_m[:] = np.round(f.depth_m / 0.003) * 0.003
    evidence, out, _ = decide(a, b)
    assert out.decision == "RM", out.reason
    assert evidence.noise_m == pytest.approx(0.003 / np.sqrt(6), rel=0.01)


def test_depth_step_is_measured_on_the_image():
    rows, cols = np.mgrid[0:50, 0:60]
    ramp = 0.9 + 0.0007 * cols + 0.0004 * rows  # a tilted surface
    valid = np.ones(ramp.shape, bool)
    assert depth_step(np.round(ramp / 0.003) * 0.003, valid) == pytest.approx(0.003, rel=0.01)
    assert depth_step(ramp + np.random.default_rng(5).normal(0, 0.001, ramp.shape), valid) < 0.0005


def test_nothing_moving_is_no_motion():
    _, out, _ = decide(plate_with_lever(10.0), plate_with_lever(10.0, index=1))
    assert out.decision == "NM", out.reason


HAND = panel_points(0.06, 0.08, spacing_m=0.0008)


def still_plate_with_a_hand(index: int, hand_at, *, shift_m: float = 0.0) -> Frame:
    """A still plate on the table, a hand 15 cm in front of the plate (not the object), and the
    whole scene shifted by ``shift_m`` sideways (the camera moved)."""
    scene = pose(t=(shift_m, 0.0, 0.0))
    plate = (BASE, scene @ pose(t=(0.0, 0.0, DEPTH_M)), 1)
    table = (TABLE[0], scene @ TABLE[1], 0)
    return frame([plate, table, (HAND, scene @ pose(t=(*hand_at, DEPTH_M - 0.15)), 0)], index)


def plain(monkeypatch) -> None:
    """Every surface drawn from now on is plain: one grey, which no optical flow can follow."""
    monkeypatch.setattr("test_dense.texture", lambda surface_xy: np.full(len(surface_xy), 128, np.uint8))


def still_plate_read_farther_near_a_hand() -> tuple[Frame, Frame]:
    """A time-of-flight camera reads surfaces near a hand farther (light the hand scatters): here by
    up to 8 mm, falling off over a fifth of the image, on the still plate and the table alike."""
    a = still_plate_with_a_hand(0, (0.03, -0.02))
    b = still_plate_with_a_hand(1, (0.06, -0.02))
    v, u = np.indices(b.depth_m.shape)
    centre_u, sigma_px = K.cx + 0.08 * K.fx / DEPTH_M, 60.0
    bias = 0.008 * np.exp(-((u - centre_u) ** 2 + (v - K.cy) ** 2) / (2 * sigma_px**2))
    hand = (b.owner == 0) & (b.depth_m < DEPTH_M)
    b.depth_m = np.where((b.depth_m > 0) & ~hand, b.depth_m + bias, b.depth_m).astype(np.float32)
    return a, b


def test_a_depth_error_that_a_hand_brings_is_no_motion_where_the_still_scene_shows_it():
    """The plate read farther near a hand fits a small motion better than staying still; the table
    beside it, which the optical flow shows still, shows the same change, so the pair shows no
    motion. Measured without the table (the evidence's ``scene_error_m`` dropped), the same depth
    makes the plate move."""
    evidence, out, _ = decide(*still_plate_read_farther_near_a_hand())
    assert out.decision == "NM", out.reason
    assert np.median(evidence.scene_error_m) > 0.002
    blind = DenseRule().decide(dataclasses.replace(evidence, scene_error_m=None))
    assert blind.decision != "NM", blind.reason


def test_a_plain_table_shows_the_depth_error_unless_a_hand_may_cover_it(monkeypatch):
    """On a plain table the flow finds no motion, as on a still textured one: the depth change there
    is the sensor's (the bias peaks at 8 mm by the plate's side). Where the segmenter says a hand
    may cover the scene, a plain surface that the flow finds still may be the hand's skin moving
    towards the camera: it measures no error."""
    plain(monkeypatch)
    source, target = (cloud(f) for f in still_plate_read_farther_near_a_hand())
    error = DenseRegistrar().register_pair(source, target).scene_error_m
    assert error is not None and np.median(error) > 0.002
    for c in (source, target):
        c.view.covered = ~c.view.mask
    assert DenseRegistrar().register_pair(source, target).scene_error_m is None


def test_a_moving_camera_leaves_no_still_scene_to_measure():
    evidence, _, _ = decide(
        still_plate_with_a_hand(0, (0.03, -0.02)), still_plate_with_a_hand(1, (0.03, -0.02), shift_m=0.015)
    )
    assert evidence.scene_error_m is None


# -- model selection on drawn evidence -----------------------------------------------------------


def drawn_evidence(second_explains: np.ndarray, *, shift_m: float = 0.02) -> MotionEvidence:
    """A 40 x 40 grid of points; hypothesis 0 is the identity (it sends every point into free space),
    hypothesis 1 explains the points outside ``second_explains`` (1 mm residual), hypothesis 2 those
    inside; each misses the other's points by 3 cm."""
    rows, cols = np.mgrid[0:40, 0:40]
    pixels = np.column_stack([cols.ravel(), rows.ravel()])
    points = np.column_stack([(pixels - 20) * 0.002, np.full(len(pixels), DEPTH_M)])
    n = len(points)
    rng = np.random.default_rng(1)
    small = rng.uniform(-0.001, 0.001, n)
    residual = np.stack(
        [np.full(n, np.nan), np.where(second_explains, 0.03, small), np.where(second_explains, small, 0.03)]
    ).astype(np.float32)
    status = np.stack([np.full(n, FREE_SPACE), np.full(n, SURFACE), np.full(n, SURFACE)]).astype(np.int8)
    motions = np.stack([np.eye(4), pose(t=(shift_m, 0, 0)), pose(t=(0, shift_m, 0))])
    return MotionEvidence(
        motions,
        ["identity", "a", "b"],
        residual,
        status,
        np.full((3, n), np.nan, np.float32),
        0.001,
        points,
        pixels,
        DEPTH_M / 570,
        dict(stride_px=1),
    )


GRID = np.mgrid[0:40, 0:40]


@pytest.mark.parametrize(
    "region, decision",
    [
        (GRID[1].ravel() >= 28, "AM"),  # a coherent 30 % region
        (((GRID[0] + GRID[1]) % 2 == 0).ravel(), "not AM"),  # a checkerboard: a scatter, not a part
        ((GRID[1] >= 39).ravel() & (GRID[0] < 20).ravel(), "RM"),  # 20 points, 1 %: below min_part_share
    ],
)
def test_a_second_motion_must_explain_a_coherent_region(region, decision):
    out = DenseRule().decide(drawn_evidence(region))
    assert out.decision == decision or decision == "not AM" != out.decision, out.reason
    if decision == "AM":
        assert (out.labels == 1).sum() == region.sum() and (out.labels[region] == 1).all()


def test_texture_alone_makes_no_part():
    """Both motions fit the depth everywhere, and only the optical flow on a coherent region prefers
    the second (stripes that repeat, shading that moves over a turning surface): one motion. The same
    region failed in depth by the first motion is a part."""
    region = GRID[1].ravel() >= 28
    evidence = drawn_evidence(region)
    flow_only = dataclasses.replace(
        evidence,
        residual_m=np.where(np.isnan(evidence.residual_m), np.nan, 0.0005).astype(np.float32),
        flow_px=np.stack(
            [np.full(len(region), np.nan), np.where(region, 20.0, 0.0), np.where(region, 0.0, 20.0)]
        ).astype(np.float32),
    )
    assert DenseRule().decide(flow_only).decision == "RM"
    assert DenseRule().decide(evidence).decision == "AM"


def test_a_fit_that_slides_along_a_still_surface_is_no_motion():
    """A still object's depth fits a 2 cm slide along its surface slightly better than staying still
    (noise, flying pixels beside a hand): the slide moves the points, but shows no motion in depth."""
    evidence = drawn_evidence(np.zeros(1600, bool))
    rng = np.random.default_rng(2)
    still = dataclasses.replace(
        evidence,
        residual_m=np.stack(
            [rng.uniform(-0.001, 0.001, 1600), rng.uniform(-0.0005, 0.0005, 1600), np.full(1600, 0.03)]
        ).astype(np.float32),
        status=np.full((3, 1600), SURFACE, np.int8),
    )
    out = DenseRule().decide(still)
    assert out.decision == "NM" and "staying still" in out.reason, out.reason
    assert DenseRule().decide(evidence).decision == "RM"  # where staying still fails, the slide is motion


def test_misses_within_noise_and_half_a_pixel_make_no_part():
    """A still object on a camera that shakes by a millimetre, half of it behind a moving hand: its
    other half fits a slide along its surface a little better than staying still. Each misses the
    other's points by 1.8 mm: more than 3 sigma of the smoothed depth (0.5 mm), but within 3 sigma
    plus half a pixel (0.9 mm), what the look-up's rounding to a pixel can give. No part; the same
    misses at 5 mm are."""
    region = GRID[1].ravel() >= 20
    evidence = drawn_evidence(region)
    rng = np.random.default_rng(3)
    small = rng.uniform(-0.0004, 0.0004, len(region))

    def missed_by(miss_m: float) -> MotionEvidence:
        residual = np.stack(
            [np.where(region, miss_m, small), np.where(region, small, miss_m), np.full(len(region), 0.03)]
        ).astype(np.float32)
        return dataclasses.replace(
            evidence, residual_m=residual, status=np.full((3, len(region)), SURFACE, np.int8), noise_m=0.0005
        )

    assert DenseRule().decide(missed_by(0.0018)).decision != "AM"
    assert DenseRule().decide(missed_by(0.005)).decision == "AM"


def test_a_part_that_slides_along_its_base_shows_by_texture_unless_it_is_a_fit_of_the_whole():
    """A drawer slides along its carcass: the carcass's motion fits the drawer in depth, and only
    the flow on the drawer's texture says it moved; the drawer's motion fails the carcass in depth. A
    part. The same evidence with the second motion fitted to the whole object (flow on stripes can
    pull such a fit off the object's motion everywhere) is one motion."""
    region = GRID[1].ravel() >= 28
    evidence = drawn_evidence(region)
    residual = evidence.residual_m.copy()
    residual[1, region] = 0.0005  # the base explains the drawer's depth
    slide = dataclasses.replace(
        evidence,
        residual_m=residual,
        flow_px=np.stack(
            [np.full(len(region), np.nan), np.where(region, 20.0, 0.0), np.zeros(len(region))]
        ).astype(np.float32),
    )
    assert DenseRule().decide(slide).decision == "AM"
    whole = dataclasses.replace(slide, names=["identity", "a", "object (flow)"])
    assert DenseRule().decide(whole).decision == "RM"

    def landing(grey: float) -> MotionEvidence:
        """The slide, with the base's motion landing the drawer's points on texture ``grey`` grey
        levels unlike theirs, where the flow's own matches are 4 +- 1 unlike."""
        on_drawer = np.where(region, grey, np.nan)
        return dataclasses.replace(
            slide,
            landing_grey=np.stack([np.full(len(region), np.nan), on_drawer, on_drawer]).astype(np.float32),
            info=dict(slide.info, flow_grey=[4.0, 1.0]),
        )

    # Stripes a period off: the flow cannot tell the two motions apart there. One motion.
    assert DenseRule().decide(landing(6.5)).decision == "RM"
    assert DenseRule().decide(landing(7.5)).decision == "AM"


def test_motions_closer_than_the_noise_are_one():
    """Two hypotheses that each explain their own region, but move the points by less than the
    threshold apart (3 sigma plus a pixel): the same motion, twice."""
    out = DenseRule().decide(drawn_evidence(GRID[1].ravel() >= 28, shift_m=0.001))
    assert out.decision in ("RM", "NM") and len(out.motions) == 1, out.reason


def test_min_part_share_is_a_real_threshold():
    region = GRID[1].ravel() >= 36  # a 10 % region
    evidence = drawn_evidence(region)
    assert DenseRule().decide(evidence).decision == "AM"
    assert DenseRule(DenseRuleParams(min_part_share=0.2)).decide(evidence).decision == "RM"


def test_staying_still_needs_fewer_points_than_a_fitted_motion():
    """A still carcass seen as a thin strip (22 points, 1.4 %) beside its drawer, which slides in
    the strip's own plane: the drawer's motion fails the strip at its edges only. Staying still is no
    fit, so the strip makes the pair articulated; the same strip explained only by a fitted motion is
    below ``min_part_share`` (two fits of one body each explain a few points the other misses)."""
    strip = (GRID[1] >= 38).ravel() & (GRID[0] < 11).ravel()
    evidence = drawn_evidence(strip)
    residual, status = evidence.residual_m.copy(), evidence.status.copy()
    residual[0], status[0] = np.where(strip, 0.0005, np.nan), np.where(strip, SURFACE, FREE_SPACE)
    residual[2], status[2] = np.nan, FREE_SPACE
    still = dataclasses.replace(evidence, residual_m=residual, status=status)
    out = DenseRule().decide(still)
    assert out.decision == "AM" and (out.labels[strip] == 1).all(), out.reason
    assert DenseRule().decide(evidence).decision == "RM"


@pytest.mark.parametrize(
    "pattern, off_px, alike",
    [
        ("stripes", 12.0, True),  # a whole period off: the same texture
        ("stripes", 18.0, False),  # one and a half: light where it was dark
        ("noise", 12.0, False),  # texture that does not repeat
    ],
)
def test_a_motion_a_period_off_on_stripes_looks_like_the_flow(pattern, off_px, alike):
    """Vertical stripes 12 px apart move 4 px right, and the flow sees it. A motion that lands the
    points a whole period further lands them on texture as like the source's as the flow's own
    matches are (within 3 robust sigmas); half a period further, or on texture that does not repeat,
    it does not."""
    rng = np.random.default_rng(5)
    columns = np.arange(K.width + 40)
    if pattern == "stripes":
        image = np.repeat(np.where(columns % 12 < 6, 60.0, 190.0)[None], K.height, axis=0)
    else:
        image = cv2.resize(_NOISE, (K.width + 40, K.height)).astype(float)
    source_gray, target_gray = (  # the target moved 4 px right; each frame has its own noise
        np.clip(image[:, c : c + K.width] + rng.normal(0, 2, (K.height, K.width)), 0, 255).astype(np.uint8)
        for c in (20, 16)
    )
    v, u = np.mgrid[60:180:4, 60:260:4]
    pixels = np.column_stack([u.ravel(), v.ravel()])

    def cloud_of(gray):
        return Cloud(
            0, np.zeros((len(pixels), 3)), view=View(gray, np.zeros(gray.shape, np.float32), K), pixels=pixels
        )

    flow = pixels + [4.0, 0.0]
    landings = Landings(cloud_of(source_gray), cloud_of(target_gray), flow, beyond_px=2.5)
    misfit = np.full((2, len(pixels)), [[1.0], [off_px]], np.float32)
    grey = landings(misfit, lambda h, i: flow[i] + np.column_stack([misfit[h, i], np.zeros(len(i))]))
    assert np.isnan(grey[0]).all()  # within the flow's typical error nothing is measured
    median, spread = landings.flow_grey
    assert np.mean(grey[1] <= median + 3 * spread) == pytest.approx(float(alike), abs=0.05)


def test_flow_a_stripe_period_off_makes_no_part(monkeypatch):
    """A plate with stripes 2 cm apart slides 1 cm along itself. Over its right third the optical
    flow locks on the neighbouring stripe (it says that third slid 1 cm the other way), as flow does
    when a motion nears half a stripe period. The true slide lands those points on stripes as like
    theirs as the flow's: one motion, not a part. Taking the flow at its word makes a part."""
    import artclass_plugins.dense.registrar as registrar

    slide = pose(t=(0.01, 0.0, 0.0))

    def aliased(source, target, **_):
        moved = source.points @ slide[:3, :3].T + slide[:3, 3]
        right = source.points[:, 0] > np.quantile(source.points[:, 0], 2 / 3)
        moved[right, 0] -= 0.02
        u, v = K.fx * moved[:, 0] / moved[:, 2] + K.cx, K.fy * moved[:, 1] / moved[:, 2] + K.cy
        return np.column_stack([u, v]), np.full((len(u), 2), np.nan)

    monkeypatch.setattr(registrar, "flow_targets", aliased)
    monkeypatch.setitem(globals(), "texture", lambda xy: 125 + 65 * np.sin(np.pi * xy[:, 0] / 0.01))
    a = frame([(BASE, pose(t=(0.0, 0.0, DEPTH_M)), 1), TABLE])
    b = frame([(BASE, slide @ pose(t=(0.0, 0.0, DEPTH_M)), 1), TABLE], 1)
    rng = np.random.default_rng(4)
    for f in (a, b):  # each frame its own sensor noise
        f.rgb[:] = np.clip(f.rgb + rng.normal(0, 3, f.rgb.shape[:2])[..., None], 0, 255)
    assert decide(a, b)[1].decision == "RM"
    monkeypatch.setattr(
        registrar.Landings, "__call__", lambda self, misfit, landing: np.full(misfit.shape, np.nan)
    )
    assert decide(a, b)[1].decision == "AM"


def test_a_striped_banana_carried_along_its_length_is_one_motion(monkeypatch):
    """A rendered pair (time of flight, 0.68 m): a banana with stripes about 12 px apart, carried
    2-3 cm along its length in 5 frames. The flow locks on the next stripe over its far end, which
    pulls every fit with the flow off the true motion there, and depth barely fixes a slide along
    the banana. Refitted on depth alone from each selected motion, the whole banana takes one
    motion; without that refit, its far end is a "part"."""
    import artclass_plugins.dense.registrar as registrar

    pair = np.load(Path(__file__).parent / "data" / "striped_banana_pair.npz")
    fx, fy, cx, cy = pair["intrinsics"]
    camera = Intrinsics(fx, fy, cx, cy, 640, 480)
    (r0, c0), (h, w) = pair["origin"], pair["mask"].shape[1:]

    def cloud_of(k: int):
        rgb, depth, mask = (
            np.zeros((480, 640, 3), np.uint8),
            np.zeros((480, 640), np.float32),
            np.zeros((480, 640), bool),
        )
        rgb[r0 : r0 + h, c0 : c0 + w] = pair["rgb"][k]
        depth[r0 : r0 + h, c0 : c0 + w] = pair["depth_mm"][k] / 1000
        mask[r0 : r0 + h, c0 : c0 + w] = pair["mask"][k]
        return ImagePreprocessor().process(Frame(k, str(k), rgb, depth, mask), mask, intrinsics=camera)

    source, target = cloud_of(0), cloud_of(1)
    assert DenseRule().decide(DenseRegistrar().register_pair(source, target)).decision == "RM"
    each = registrar._Fit.each
    monkeypatch.setattr(  # the refit on depth alone is the one given ``among``
        registrar._Fit,
        "each",
        lambda fit, *a, among=None: np.empty((0, 4, 4)) if among is not None else each(fit, *a),
    )
    assert DenseRule().decide(DenseRegistrar().register_pair(source, target)).decision == "AM"
