"""Layer 2: the contract every registered plugin keeps, run once per plugin of each kind.

The plugins are taken from the registry at collection time, so a plugin added later (built-in or
third-party, installed in this environment) is covered without editing this file.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import json
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from artclass_core import (
    ArtclassError,
    CellMotion,
    Cloud,
    Config,
    Frame,
    InputError,
    Params,
    Pipeline,
    PluginError,
    RuleDecision,
    RunResult,
    Sequence,
    describe,
    hookimpl,
    load_registry,
)
from artclass_core.articulation import Articulation, JointEstimate, Part
from artclass_core.cli import classify_with_parts, plugin_table
from artclass_core.geometry import transform
from artclass_core.interfaces import KINDS, PartFinder

from conftest import INTRINSICS, make_sequence, sample_sequences

REGISTRY = load_registry()
ALL = [(kind, name) for kind in KINDS for name in REGISTRY.names(kind)]


def ids(kind: str) -> list[str]:
    return REGISTRY.names(kind)


NEURAL = {"u2net"}  # segmenters that run a neural network on the CPU: slow


def marked(names: list[str]) -> list:
    """``names`` for parametrize, those of :data:`NEURAL` marked slow."""
    return [pytest.param(n, marks=pytest.mark.slow) if n in NEURAL else n for n in names]


def cell_registrars() -> list[str]:
    return [n for n in ids("registrar") if REGISTRY.get("registrar", n).gives == "cells"]


def pair_registrars() -> list[str]:
    return [n for n in ids("registrar") if REGISTRY.get("registrar", n).gives == "motions"]


def rules(needs: str) -> list[str]:
    return [n for n in ids("rule") if REGISTRY.get("rule", n).needs == needs]


def one_line_error(err: ArtclassError) -> None:
    message = str(err)
    assert message and "\n" not in message, f"error message is not one line: {message!r}"


# -- every plugin -----------------------------------------------------------------------------------


@pytest.mark.parametrize("kind, name", ALL, ids=[f"{k}:{n}" for k, n in ALL])
class TestDeclaration:
    def test_name_description_params(self, kind, name):
        cls = REGISTRY.get(kind, name)
        assert cls.name == name and name == name.lower() and name.replace("_", "").isalnum()
        assert isinstance(cls.description, str) and cls.description.strip()
        assert "\n" not in cls.description, "description is one line"
        assert dataclasses.is_dataclass(cls.Params) and issubclass(cls.Params, Params)
        assert cls.Params.__dataclass_params__.frozen
        method = KINDS[kind][1]
        assert callable(getattr(cls, method, None)), f"{kind} {name} has no {method}()"

    def test_defaults_construct_within_bounds(self, kind, name):
        cls = REGISTRY.get(kind, name)
        params = cls.Params()  # validates itself
        hash(params)  # frozen dataclasses are cache keys
        plugin = cls(params)
        assert plugin.params == params
        assert cls().params == params, "constructing without params gives the defaults"
        for spec in describe(cls.Params):
            value = getattr(params, spec.name)
            if value is None:
                assert spec.auto, f"{spec.name} defaults to None without saying how it is derived (auto=)"
                continue
            low, high = spec.bounds
            assert low is None or value >= low, f"{spec.name} = {value} below {low}"
            assert high is None or value <= high, f"{spec.name} = {value} above {high}"
            if spec.choices:
                assert value in spec.choices

    def test_every_field_documented(self, kind, name):
        for spec in describe(REGISTRY.get(kind, name).Params):
            assert spec.help.strip(), f"{spec.name}: no help text"
            if spec.type in (int, float):
                assert len(spec.bounds) == 2 and None not in spec.bounds, (
                    f"{spec.name}: a number needs both bounds (the app builds a slider from them), got {spec.bounds}"
                )
                assert spec.bounds[0] <= spec.bounds[1], f"{spec.name}: bounds {spec.bounds} reversed"
                assert spec.unit, f"{spec.name}: a number names its unit ('1' for a pure number)"


# -- readers -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ids("reader"))
def test_reader_ignores_foreign_folder(name, tmp_path):
    (tmp_path / "notes.txt").write_text("not a dataset\n")
    assert REGISTRY.create("reader", name).sequences(tmp_path) == []


@pytest.mark.parametrize("name", ids("reader"))
@pytest.mark.parametrize("seq_dir", sample_sequences(), ids=lambda p: p.name)
def test_reader_on_sample_data(name, seq_dir):
    """Whatever a reader makes of a bundled sequence is well formed, and the same twice."""
    found = REGISTRY.create("reader", name).sequences(seq_dir)
    again = REGISTRY.create("reader", name).sequences(seq_dir)
    assert isinstance(found, list)
    assert [(s.name, len(s)) for s in found] == [(s.name, len(s)) for s in again]
    for seq in found:
        assert isinstance(seq, Sequence) and len(seq) >= 1
        frame = seq[0]
        h, w = seq.intrinsics.height, seq.intrinsics.width
        assert frame.rgb.shape == (h, w, 3) and frame.rgb.dtype == np.uint8
        assert frame.depth_m.shape == (h, w) and frame.depth_m.dtype == np.float32
        assert frame.mask is None or (frame.mask.shape == (h, w) and frame.mask.dtype == bool)
        assert seq.label in (None, "articulated", "rigid", "static")


def test_folder_reader_reads_every_sample():
    if not sample_sequences():
        pytest.fail("sample_data/ holds no sequence (it is committed with the repository)")
    for seq_dir in sample_sequences():
        assert len(REGISTRY.create("reader", "folder").sequences(seq_dir)) == 1


# -- segmenters ---------------------------------------------------------------------------------------

SEGMENT_SEQ = make_sequence("hinge", n_frames=4)


def segment(name: str, frame: Frame, seq: Sequence):
    """The segmenter's mask, or the documented error (a model file that is not there ...)."""
    try:
        return REGISTRY.create("segmenter", name).segment(frame, sequence=seq)
    except (PluginError, InputError) as err:
        one_line_error(err)
        return err


@pytest.mark.parametrize("name", marked(ids("segmenter")))
def test_segmenter_returns_a_mask_of_the_frame(name):
    out = segment(name, SEGMENT_SEQ[2], SEGMENT_SEQ)
    if isinstance(out, ArtclassError):
        return  # e.g. a model-based segmenter without its model file: the documented error, asserted above
    assert out is None or (
        isinstance(out, np.ndarray)
        and out.dtype == bool
        and out.shape == (INTRINSICS.height, INTRINSICS.width)
    )
    again = segment(name, SEGMENT_SEQ[2], SEGMENT_SEQ)
    assert (out is None and again is None) or np.array_equal(out, again), "segmentation is deterministic"


@pytest.mark.parametrize("name", marked(ids("segmenter")))
def test_segmenter_on_a_frame_without_depth(name):
    """No depth reading at all: no mask (None or empty), or the documented error; never a crash."""
    blank = [
        Frame(
            i,
            f"{i:06d}",
            np.zeros((INTRINSICS.height, INTRINSICS.width, 3), np.uint8),
            np.zeros((INTRINSICS.height, INTRINSICS.width), np.float32),
            np.zeros((INTRINSICS.height, INTRINSICS.width), bool),
        )
        for i in range(3)
    ]
    from conftest import ArraySequence

    seq = ArraySequence(blank, name="blank")
    out = segment(name, seq[1], seq)
    assert (
        out is None
        or isinstance(out, ArtclassError)
        or (out.dtype == bool and out.shape == blank[0].depth_m.shape)
    )


def test_mask_segmenter_without_masks_names_the_sequence():
    seq = make_sequence("static", n_frames=2, masks=False)
    with pytest.raises(InputError, match="no masks") as err:
        REGISTRY.create("segmenter", "mask").segment(seq[0], sequence=seq)
    assert str(seq.path) in str(err.value)


@pytest.mark.parametrize("model_path", ["", "/nonexistent/MaskRCNN-12.onnx"], ids=["unset", "missing-file"])
def test_maskrcnn_without_its_model_fails_with_the_documented_error(model_path):
    """Mask R-CNN needs a file the user provides: without it, a one-line PluginError naming what to set."""
    assert "maskrcnn" in REGISTRY.names("segmenter"), "the maskrcnn segmenter is not registered"
    cls = REGISTRY.get("segmenter", "maskrcnn")
    with pytest.raises(PluginError) as err:
        cls(cls.Params(model_path=model_path)).segment(SEGMENT_SEQ[0], sequence=SEGMENT_SEQ)
    one_line_error(err.value)
    assert "model_path" in str(err.value)
    if model_path:
        assert model_path in str(err.value), "the message names the missing file"


# -- preprocessors -------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ids("preprocessor"))
def test_preprocessor_gives_a_cloud_in_metres(name):
    frame = SEGMENT_SEQ[1]
    cloud = REGISTRY.create("preprocessor", name).process(frame, frame.mask, intrinsics=INTRINSICS)
    assert isinstance(cloud, Cloud) and cloud.frame_index == 1
    pts = cloud.points
    assert pts.ndim == 2 and pts.shape[1] == 3 and pts.dtype == np.float64 and len(pts) >= 10
    assert np.isfinite(pts).all()
    # the panels are 0.6 m away (one turned by 5 degrees): metres, not millimetres
    assert 0.5 < pts[:, 2].min() and pts[:, 2].max() < 0.7, (
        f"depth range {pts[:, 2].min()}..{pts[:, 2].max()}"
    )
    if cloud.normals is not None:
        assert cloud.normals.shape == pts.shape
        np.testing.assert_allclose(np.linalg.norm(cloud.normals, axis=1), 1.0, atol=1e-6)
    json.dumps(cloud.info)  # recorded in results: JSON-ready
    again = REGISTRY.create("preprocessor", name).process(frame, frame.mask, intrinsics=INTRINSICS)
    assert again.points.shape == pts.shape
    np.testing.assert_allclose(again.points, pts, rtol=0, atol=1e-9, err_msg="preprocessing is deterministic")


@pytest.mark.parametrize("name", ids("preprocessor"))
def test_preprocessor_on_an_empty_mask(name):
    frame = SEGMENT_SEQ[1]
    try:
        cloud = REGISTRY.create("preprocessor", name).process(
            frame, np.zeros_like(frame.mask), intrinsics=INTRINSICS
        )
    except InputError as err:
        one_line_error(err)
    else:
        assert cloud.points.shape == (0, 3), "an empty mask gives an empty cloud (the frame is then skipped)"


# -- registrars ----------------------------------------------------------------------------------------


def corner_cell(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    a = rng.uniform(0.0, 0.04, (3, 100, 2))
    z = np.zeros(100)
    src = np.concatenate(
        [
            np.column_stack([z, a[0, :, 0], a[0, :, 1]]),
            np.column_stack([a[1, :, 0], z, a[1, :, 1]]),
            np.column_stack([a[2, :, 0], a[2, :, 1], z]),
        ]
    ) + [0.05, -0.02, 0.6]
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(2.0) * np.array([0.0, 0.6, 0.8])).as_matrix()
    c = src.mean(0)
    T[:3, 3] = c - T[:3, :3] @ c + [0.002, 0.001, -0.002]
    return src, transform(src, T)


def check_registration(reg, n_source: int) -> None:
    T = np.asarray(reg.T_target_from_source)
    assert T.shape == (4, 4) and np.isfinite(T).all()
    np.testing.assert_allclose(T[3], [0, 0, 0, 1], atol=1e-12)
    R = T[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-9), "a rotation, not a reflection"
    assert 0.0 <= reg.fitness <= 1.0
    assert reg.rmse_m >= 0.0 and np.isfinite(reg.rmse_m)
    assert isinstance(reg.n_correspondences, (int, np.integer)) and 0 <= reg.n_correspondences <= n_source


@pytest.mark.parametrize("with_normals", [False, True], ids=["no-normals", "normals"])
@pytest.mark.parametrize("name", cell_registrars())
def test_registrar_returns_a_rigid_transform(name, with_normals):
    src, tgt = corner_cell()
    normals = None
    if with_normals:
        from artclass_plugins.preprocessors import camera_facing_normals

        normals = (camera_facing_normals(src, radius_m=0.02), camera_facing_normals(tgt, radius_m=0.02))
    kwargs = dict(
        source_normals=normals and normals[0], target_normals=normals and normals[1], cell_size_m=0.04
    )
    reg = REGISTRY.create("registrar", name).register(src, tgt, **kwargs)
    check_registration(reg, len(src))
    assert reg.n_correspondences > 0 and reg.fitness > 0.5, (
        "a 2 mm / 2 degree motion of a 4 cm cell registers"
    )
    again = REGISTRY.create("registrar", name).register(src, tgt, **kwargs)
    # deterministic up to the summation order of Open3D's parallel reductions (last bits)
    np.testing.assert_allclose(
        again.T_target_from_source,
        reg.T_target_from_source,
        rtol=0,
        atol=1e-9,
        err_msg="registration is deterministic",
    )
    assert again.n_correspondences == reg.n_correspondences


@pytest.mark.parametrize("name", cell_registrars())
def test_registrar_without_correspondence(name):
    """Clouds far apart (10 cell sizes): no correspondence is reported as n_correspondences = 0."""
    src, tgt = corner_cell()
    reg = REGISTRY.create("registrar", name).register(
        src, tgt + [0.4, 0.0, 0.0], source_normals=None, target_normals=None, cell_size_m=0.04
    )
    check_registration(reg, len(src))
    assert reg.n_correspondences == 0 and reg.fitness == 0.0


# -- rules ------------------------------------------------------------------------------------------------


def registered_pair(motion: str) -> tuple[list[CellMotion], Cloud, Cloud]:
    """The cells of the pair (0, 2) of a small sequence, registered by the paper's per-cell pipeline."""
    pipeline = Pipeline(REGISTRY, Config.paper())
    seq = make_sequence(motion, n_frames=3)
    a, b = pipeline.frame(seq, 0), pipeline.frame(seq, 2)
    cells, _ = pipeline.register(a.cloud, b.cloud)
    return cells, a.cloud, b.cloud


PAIRS = {motion: registered_pair(motion) for motion in ("static", "hinge")}


@pytest.mark.parametrize("motion", sorted(PAIRS))
@pytest.mark.parametrize("name", rules("cells"))
def test_rule_decides_every_cell(name, motion):
    cells, source, target = PAIRS[motion]
    out = REGISTRY.create("rule", name).decide(copy.deepcopy(cells), source=source, target=target)
    assert isinstance(out, RuleDecision)
    assert out.decision in ("AM", "RM", "NM", "skipped")
    assert len(out.clusters) == len(cells), "one cluster entry per cell"
    assert all(isinstance(k, str) for k in out.keys)
    for cell, k in zip(cells, out.clusters):
        assert k is None or (isinstance(k, (int, np.integer)) and k >= 0)
        if not cell.matched:
            assert k is None, f"cell {cell.cell} did not register ({cell.skipped}) but got cluster {k}"
    json.dumps(out.info)
    again = REGISTRY.create("rule", name).decide(copy.deepcopy(cells), source=source, target=target)
    assert (again.decision, again.clusters, again.keys) == (out.decision, out.clusters, out.keys), (
        "deterministic"
    )


@pytest.mark.parametrize("name", rules("cells"))
def test_rule_calls_an_unmoved_pair_nm(name):
    """Identical noise-free frames: every cell registers to the identity; no rule may see motion."""
    cells, source, target = PAIRS["static"]
    assert sum(c.matched for c in cells) >= 3
    out = REGISTRY.create("rule", name).decide(copy.deepcopy(cells), source=source, target=target)
    assert out.decision == "NM", out.reason


@pytest.mark.parametrize("name", rules("cells"))
def test_rule_with_no_matched_cell(name):
    cells, source, target = PAIRS["hinge"]
    unmatched = copy.deepcopy(cells)
    for c in unmatched:
        c.skipped = c.skipped or "low fitness 0.00"
    out = REGISTRY.create("rule", name).decide(unmatched, source=source, target=target)
    assert out.decision == "skipped" and out.clusters == [None] * len(cells)


# -- registrars and rules that work on whole pairs ------------------------------------------------------


def pair_clouds(motion: str, **kw) -> tuple[Cloud, Cloud]:
    """The clouds of frames 0 and 2 of a small sequence, preprocessed by the default pipeline."""
    pipeline = Pipeline(REGISTRY, Config())
    seq = make_sequence(motion, n_frames=3, **kw)
    return pipeline.frame(seq, 0).cloud, pipeline.frame(seq, 2).cloud


@pytest.mark.parametrize("name", pair_registrars())
def test_pair_registrar_gives_evidence_for_every_point(name):
    source, target = pair_clouds("hinge")
    ev = REGISTRY.create("registrar", name).register_pair(source, target)
    H, N = len(ev.motions), len(ev.points)
    assert N > 0 and H >= 2
    np.testing.assert_allclose(ev.motions[0], np.eye(4), err_msg="the first hypothesis is the identity")
    for T in ev.motions:
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
        assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-9)
    assert len(ev.names) == H and ev.residual_m.shape == ev.status.shape == ev.flow_px.shape == (H, N)
    assert ev.pixels.shape == (N, 2) and ev.noise_m > 0 and ev.pixel_m > 0
    assert set(np.unique(ev.status)) <= set(range(5))
    again = REGISTRY.create("registrar", name).register_pair(source, target)
    np.testing.assert_array_equal(again.motions, ev.motions, err_msg="registration is deterministic")
    np.testing.assert_array_equal(again.status, ev.status)


@pytest.mark.parametrize("motion, expected", [("static", "NM"), ("rigid", "RM"), ("hinge", "AM")])
@pytest.mark.parametrize("registrar", pair_registrars())
@pytest.mark.parametrize("name", rules("motions"))
def test_motion_rule_tells_the_three_motions_apart(name, registrar, motion, expected):
    """Two panels that stand still, move away together by 2 cm, or turn about their shared edge by 10
    degrees, with 1 mm of depth noise."""
    ev = REGISTRY.create("registrar", registrar).register_pair(*pair_clouds(motion, noise_m=0.001))
    out = REGISTRY.create("rule", name).decide(ev)
    assert out.decision == expected, out.reason
    assert out.labels is not None and out.labels.shape == (len(ev.points),)
    assert out.labels.max() == len(out.motions) - 1 and out.labels.min() >= -1
    json.dumps(out.info)
    if expected == "AM":
        assert len(out.motions) >= 2 and all(m.n_points > 0 for m in out.motions)


@pytest.mark.parametrize("name", rules("motions"))
def test_a_default_partner_fits_the_chosen_plugin_and_two_chosen_misfits_are_refused(name):
    assert Pipeline(REGISTRY, Config(registrar=cell_registrars()[0], rule=name)).config.rule == "paper"
    assert Pipeline(REGISTRY, Config(rule="paper")).config.registrar == "icp_point_to_point"

    class OtherPairs(REGISTRY.get("registrar", pair_registrars()[0])):
        name = "other_pairs"

    plugin = SimpleNamespace(register_registrars=hookimpl(lambda register: register(OtherPairs)))
    registry = load_registry(extra_plugins=(plugin,))
    with pytest.raises(ArtclassError, match="decides from cells"):
        Pipeline(registry, Config(registrar="other_pairs", rule="paper"))


# -- joint estimators ------------------------------------------------------------------------------------


def _hinge_poses(n: int = 20) -> np.ndarray:
    """A part 20 cm from a vertical hinge, turned 0-60 degrees, noise-free; frame 3 unknown."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    angles = np.linspace(0.0, np.radians(60), n)
    poses[:, :3, :3] = Rotation.from_rotvec(np.outer(angles, [0, 0, 1])).as_matrix()
    poses[:, :3, 3] = poses[:, :3, :3] @ [0.2, 0.0, 0.0] + [0.0, 0.0, 0.8]
    poses[3] = np.nan
    return poses


@pytest.mark.parametrize("name", ids("joint_estimator"))
def test_joint_estimator_returns_a_joint_estimate(name):
    from artclass_core.interfaces import JOINT_TYPES, JointEstimate

    poses = _hinge_poses()
    out = REGISTRY.create("joint_estimator", name).estimate(poses)
    assert isinstance(out, JointEstimate) and out.type in JOINT_TYPES
    assert (
        out.states.shape == (len(poses),) and out.inliers.shape == (len(poses),) and out.inliers.dtype == bool
    )
    assert np.isnan(out.states[3]) and not out.inliers[3], "an unknown pose has no state"
    if out.axis_direction is not None:
        assert out.axis_direction.shape == (3,) and np.linalg.norm(out.axis_direction) == pytest.approx(1.0)
    json.dumps(out.scores), json.dumps(out.info)
    assert out.summary(up=np.array([0.0, 0.0, 1.0])).strip() and "\n" not in out.summary(
        up=np.array([0.0, 0.0, 1.0])
    )
    again = REGISTRY.create("joint_estimator", name).estimate(poses)
    assert again.type == out.type and np.array_equal(again.states, out.states, equal_nan=True), (
        "deterministic"
    )


@pytest.mark.parametrize("name", ids("joint_estimator"))
def test_joint_estimator_refuses_poses_of_the_wrong_shape(name):
    with pytest.raises(InputError) as err:
        REGISTRY.create("joint_estimator", name).estimate(np.zeros((4, 3, 4)))
    one_line_error(err.value)


# -- part finders ------------------------------------------------------------------------------------


@functools.cache
def _hinge_run(needs: str, *, keep_clouds: bool = True) -> RunResult:
    """A run of a small hinge (8 frames, k = 2) under a rule that gives what a part finder needs."""
    config = (Config.paper() if needs == "cells" else Config()).with_overrides(REGISTRY, {"k": "2"})
    return Pipeline(REGISTRY, config).run(make_sequence("hinge", n_frames=8), keep_clouds=keep_clouds)


def check_articulation(art: Articulation, result: RunResult) -> None:
    """What every part finder returns: parts (the base first, parents before children), joints
    between them, the base's poses and part images of the frames' shape."""
    assert isinstance(art, Articulation) and art.parts, "at least the base"
    for n, part in enumerate(art.parts):
        assert part.index == n and part.parent < n and (part.parent >= 0) == (n > 0)
        assert part.points_m.ndim == 2 and part.points_m.shape[1] == 3
    for joint in art.joints:
        assert 0 <= joint.parent < len(art.parts) and 0 < joint.child < len(art.parts)
        assert isinstance(joint.estimate, JointEstimate)
        assert joint.estimate.states.shape == (len(result.frames),)
    assert art.base_poses.shape == (len(result.frames), 4, 4)
    for f in art.frames:
        image = art.label_image(f)
        assert image.dtype == np.uint8 and image.shape == (INTRINSICS.height, INTRINSICS.width)
        assert image.max() <= len(art.parts)
    json.dumps(art.to_dict())
    assert art.summary().strip() and "\n" not in art.summary()


@pytest.mark.parametrize("name", ids("part_finder"))
def test_part_finder_returns_parts_joints_and_part_images(name):
    finder = REGISTRY.create("part_finder", name)
    result = _hinge_run(finder.needs)
    art = finder.find(result, estimator=REGISTRY.create("joint_estimator", "bic"))
    check_articulation(art, result)
    again = REGISTRY.create("part_finder", name).find(
        result, estimator=REGISTRY.create("joint_estimator", "bic")
    )
    assert again.to_dict() == art.to_dict(), "deterministic"


@pytest.mark.parametrize("name", ids("part_finder"))
def test_part_finder_without_the_clouds_names_the_fix(name):
    finder = REGISTRY.create("part_finder", name)
    result = _hinge_run(finder.needs, keep_clouds=False)
    with pytest.raises(ArtclassError, match="keep_clouds") as err:
        finder.find(result, estimator=REGISTRY.create("joint_estimator", "bic"))
    one_line_error(err.value)


class OneBodyFinder(PartFinder):
    """A second part finder, from outside the core: the whole object as one part, from any rule."""

    name = "one_body"
    description = "the whole object as one part, with no joint"
    needs = "any"

    def find(self, result: RunResult, *, estimator, images: bool = True) -> Articulation:
        clouds = {f.index: f.cloud for f in result.frames if f.cloud is not None}
        if not clouds:
            raise ArtclassError("finding parts needs the frames' clouds: run with keep_clouds=True")
        first = min(clouds)
        base = Part(0, "base", -1, clouds[first].points, sorted(clouds), sum(map(len, clouds.values())))
        views = {
            f: (c.pixels, np.zeros(len(c), int), c.view.mask, 1)
            for f, c in clouds.items()
            if c.pixels is not None
        }
        return Articulation([base], [], np.full((len(result.frames), 4, 4), np.nan), views)


@hookimpl
def register_part_finders(register):
    register(OneBodyFinder)


def test_hook_register_part_finders_takes_a_second_finder():
    """A part finder registered through the hook is listed, keeps the contract and is the one that
    ``classify_with_parts`` uses when chosen, under a rule the built-in one cannot work with."""
    registry = load_registry(extra_plugins=(SimpleNamespace(register_part_finders=register_part_finders),))
    assert {"one_body", "tracks"} <= set(registry.names("part_finder"))
    assert "one_body" in [row["name"] for row in plugin_table(registry)["part_finder"]]
    finder = registry.create("part_finder", "one_body")
    check_articulation(finder.find(_hinge_run("cells"), estimator=None), _hinge_run("cells"))
    config = Config.paper().with_overrides(registry, {"k": "2"})
    seq = make_sequence("hinge", n_frames=4)
    _, none = classify_with_parts(registry, config, seq, workers=1)
    assert none is None, "the built-in finder needs a rule that decides from motions"
    result, art = classify_with_parts(registry, config, seq, workers=1, part_finder="one_body")
    assert (
        [p.name for p in art.parts] == ["base"] and art.joints == [] and art.parts[0].frames == list(range(4))
    )
    assert all(f.cloud is None for f in result.frames), "the clouds kept for the parts are dropped"
