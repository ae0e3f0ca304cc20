"""Layer 1: core functions on synthetic ground truth, with tolerances stated in physical units."""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass

import numpy as np
import pytest
from scipy.spatial.distance import pdist
from scipy.spatial.transform import Rotation

from artclass_core import (
    CellMotion,
    Cloud,
    Config,
    Frame,
    InputError,
    Intrinsics,
    ParamError,
    Params,
    Pipeline,
    PipelineParams,
    Registration,
    fractions,
    max_count_filter,
    param,
    sequence_label,
)
from artclass_core.geometry import (
    grid_cells,
    largest_distance,
    quaternion_wxyz,
    rotation_angle_rad,
    transform,
)

from conftest import INTRINSICS, make_sequence


def rigid(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


# -- geometry ----------------------------------------------------------------------------------------


class TestLargestDistance:
    def test_cube_corners(self):
        corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) * 0.3
        assert largest_distance(corners) == pytest.approx(0.3 * np.sqrt(3), abs=1e-12)

    def test_sphere_with_antipodes(self):
        rng = np.random.default_rng(0)
        d = rng.normal(size=(5000, 3))
        inside = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0, 0.099, (5000, 1))
        points = np.vstack([inside, [[0.1, 0, 0], [-0.1, 0, 0]]]) + [0.2, -0.1, 0.8]
        assert largest_distance(points) == pytest.approx(0.2, abs=1e-12)

    @pytest.mark.parametrize("seed", [1, 2, 3])
    def test_equals_brute_force(self, seed):
        points = np.random.default_rng(seed).normal(scale=0.05, size=(800, 3))
        assert largest_distance(points) == pytest.approx(pdist(points).max(), abs=1e-12)

    def test_flat_rectangle_shuffled(self):
        """A flat cloud (no 3-D hull) is still exact: the far corners are found among many points."""
        rng = np.random.default_rng(4)
        xy = rng.uniform([-0.1, -0.05], [0.1, 0.05], (6000, 2))
        xy[:2] = [[-0.1, -0.05], [0.1, 0.05]]  # the diagonal
        points = np.column_stack([xy, np.full(len(xy), 0.7)])[rng.permutation(len(xy))]
        assert largest_distance(points) == pytest.approx(np.hypot(0.2, 0.1), abs=1e-12)

    def test_collinear_and_tiny(self):
        line = np.outer(np.linspace(0, 1, 50), [0.1, 0.2, 0.2])[np.random.default_rng(5).permutation(50)]
        assert largest_distance(line) == pytest.approx(0.3, abs=1e-12)
        assert largest_distance(np.zeros((1, 3))) == 0.0
        assert largest_distance(np.array([[0, 0, 0], [0.3, 0.4, 0]], float)) == pytest.approx(0.5)


class TestGridCells:
    @pytest.mark.parametrize("cell_size_m", [0.01, 0.037, 0.5])
    def test_partitions_both_clouds(self, cell_size_m):
        rng = np.random.default_rng(0)
        source = rng.uniform(-0.1, 0.1, (700, 3)) + [0, 0, 0.6]
        target = rng.uniform(-0.08, 0.12, (500, 3)) + [0, 0, 0.6]
        cells = grid_cells(source, target, cell_size_m=cell_size_m)
        for cloud, column in ((source, 2), (target, 3)):
            members = np.concatenate([c[column] for c in cells])
            assert np.array_equal(np.sort(members), np.arange(len(cloud))), "every index exactly once"
        keys = [c[0] for c in cells]
        assert keys == sorted(set(keys)), "cells unique and sorted"
        for key, centre, si, ti in cells:
            assert len(si) + len(ti) > 0, f"empty cell {key} listed"
            for pts in (source[si], target[ti]):
                # each member lies in the cube of edge cell_size_m around the centre (1 nm for rounding)
                assert np.all(np.abs(pts - centre) <= cell_size_m / 2 + 1e-9), f"point outside cell {key}"

    def test_one_cell_when_large(self):
        pts = np.random.default_rng(1).uniform(0, 0.1, (50, 3))
        cells = grid_cells(pts, pts + 0.001, cell_size_m=10.0)
        assert len(cells) == 1 and len(cells[0][2]) == 50 and len(cells[0][3]) == 50


class TestIntrinsics:
    def test_backproject_inverts_projection(self):
        intr = Intrinsics(fx=525.0, fy=530.0, cx=319.5, cy=239.5, width=64, height=48)
        rng = np.random.default_rng(0)
        depth = rng.uniform(0.3, 2.0, (48, 64)).astype(np.float32)
        depth[5, 7] = 0.0
        depth[9, 11] = np.nan
        points = intr.backproject(depth)
        assert points.shape == (48 * 64 - 2, 3)
        u = intr.fx * points[:, 0] / points[:, 2] + intr.cx
        v = intr.fy * points[:, 1] / points[:, 2] + intr.cy
        vv, uu = np.nonzero(np.isfinite(depth) & (depth > 0))
        np.testing.assert_allclose(u, uu, atol=1e-9)
        np.testing.assert_allclose(v, vv, atol=1e-9)
        np.testing.assert_allclose(points[:, 2], depth[vv, uu], rtol=0)

    def test_mask_selects_pixels(self):
        depth = np.full((INTRINSICS.height, INTRINSICS.width), 0.5, np.float32)
        mask = np.zeros(depth.shape, bool)
        mask[10:20, 30:35] = True
        points = INTRINSICS.backproject(depth, mask)
        assert points.shape == (50, 3)
        assert points[:, 0].min() == pytest.approx((30 - INTRINSICS.cx) * 0.5 / INTRINSICS.fx)

    @pytest.mark.parametrize("bad", [dict(fx=0.0), dict(fy=-1.0), dict(cx=np.nan)])
    def test_invalid_intrinsics(self, bad):
        values = dict(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480) | bad
        with pytest.raises(InputError, match="invalid intrinsics"):
            Intrinsics(**values)


class TestQuaternion:
    def test_identity(self):
        assert np.array_equal(quaternion_wxyz(np.eye(3)), [1.0, 0.0, 0.0, 0.0])

    @pytest.mark.parametrize("angle_deg", [10.0, 170.0, 190.0, 350.0, -30.0])
    def test_sign_w_non_negative_and_round_trip(self, angle_deg):
        axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
        R = Rotation.from_rotvec(np.radians(angle_deg) * axis).as_matrix()
        q = quaternion_wxyz(R)
        assert q[0] >= 0, "w >= 0 fixes the sign (q and -q are one rotation)"
        assert np.linalg.norm(q) == pytest.approx(1.0)
        np.testing.assert_allclose(Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix(), R, atol=1e-12)
        assert rotation_angle_rad(R) == pytest.approx(
            np.radians(min(abs(angle_deg) % 360, 360 - abs(angle_deg) % 360))
        )


# -- decisions over a sequence ---------------------------------------------------------------------


class TestMaxCountFilter:
    def test_w1_is_identity(self):
        d = ["AM", "NM", "RM", "AM", "RM"]
        assert max_count_filter(d, w=1) == d

    def test_isolated_decision_removed(self):
        assert max_count_filter(["RM", "RM", "AM", "RM", "RM"], w=3) == ["RM"] * 5
        assert max_count_filter(["NM", "NM", "RM", "NM"], w=3) == ["NM"] * 4

    def test_window_reach(self):
        # with w = 3 an AM pair survives a single neighbour, with w = 5 two AMs among RMs lose
        d = ["RM", "RM", "AM", "AM", "RM", "RM", "RM"]
        assert max_count_filter(d, w=3) == d
        assert max_count_filter(d, w=5) == ["RM"] * 7
        # the window is cut at the ends: at the first pair [RM, AM, AM] keeps AM, at the second the
        # tie [RM, AM, AM, RM] goes to the less severe RM
        assert max_count_filter(["RM", "AM", "AM", "RM", "RM"], w=5) == ["AM", "RM", "RM", "RM", "RM"]

    def test_tie_goes_to_the_least_severe(self):
        assert max_count_filter(["AM", "NM", "RM"], w=3)[1] == "NM"
        # also in the truncated windows at the ends: an isolated AM cannot win a tie
        assert max_count_filter(["AM", "NM"], w=3) == ["NM", "NM"]
        assert max_count_filter(["RM", "AM"], w=3) == ["RM", "RM"]
        # centre NM has one vote; RM and AM tie with two: RM (less severe than AM) wins
        assert max_count_filter(["AM", "RM", "NM", "AM", "RM"], w=5)[2] == "RM"
        assert max_count_filter(["AM", "AM", "RM", "NM", "NM"], w=5)[2] == "NM"
        assert max_count_filter(["AM", "AM", "RM", "RM"], w=4)[1] == "RM"

    def test_length_and_empty(self):
        assert max_count_filter([], w=3) == []
        assert len(max_count_filter(["AM"] * 7, w=4)) == 7


def test_sequence_label():
    assert sequence_label(["NM", "RM", "AM", "NM"]) == "articulated"
    assert sequence_label(["NM", "RM", "RM"]) == "rigid"
    assert sequence_label(["NM", "NM"]) == "static"
    assert sequence_label([]) == "static"


def test_fractions():
    f = fractions(["AM", "RM", "RM", "NM"])
    assert f == {"AM": 0.25, "RM": 0.5, "NM": 0.25}
    assert fractions([]) == {"AM": 0.0, "RM": 0.0, "NM": 0.0}


# -- parameters --------------------------------------------------------------------------------------


class TestParams:
    def test_out_of_bounds_names_parameter_value_and_range(self):
        with pytest.raises(ParamError) as err:
            PipelineParams(k=0)
        assert "k" in str(err.value) and "0" in str(err.value) and "[1, 1000]" in str(err.value)
        with pytest.raises(ParamError, match=r"alpha.*1\.5.*\[0\.0, 1\.0\]"):
            PipelineParams(alpha=1.5)

    def test_choices(self, registry):
        rule_params = registry.get("rule", "paper").Params
        with pytest.raises(ParamError, match="rounding.*'ceil'.*floor, round"):
            rule_params(rounding="ceil")

    def test_auto(self):
        assert PipelineParams(cell_size_m=None).cell_size_m is None
        assert PipelineParams(cell_size_m=0.02).cell_size_m == 0.02

        @dataclass(frozen=True)
        class NoAuto(Params):
            size_m: float | None = param(None, unit="m", bounds=(0.0, 1.0), help="a value without auto")

        with pytest.raises(ParamError, match="size_m has no value and no automatic default"):
            NoAuto()

    def test_frozen_and_hashable(self):
        p = PipelineParams()
        with pytest.raises(dataclasses.FrozenInstanceError):
            p.k = 3
        assert hash(p) == hash(PipelineParams()) and p == PipelineParams()
        assert hash(Config()) == hash(Config())

    def test_overrides_by_name_and_symbol(self, registry):
        base = Config(rule="paper", preprocessor="paper")
        by_symbol = base.with_overrides(registry, {"k": "3", "v": "0.004", "q_bar": "0.2", "x": "0.05"})
        by_name = base.with_overrides(
            registry, {"k": 3, "voxel_size_m": 0.004, "q_bar": 0.2, "cell_size_m": 0.05}
        )
        assert by_symbol == by_name
        assert by_symbol.pipeline.k == 3 and by_symbol.pipeline.cell_size_m == 0.05
        assert by_symbol.preprocessor_params.voxel_size_m == 0.004
        assert by_symbol.rule_params.q_bar == 0.2
        assert base.pipeline.k == 5, "the original is unchanged"
        back = by_symbol.with_overrides(registry, {"v": "auto", "x": "auto"})
        assert back.preprocessor_params.voxel_size_m is None and back.pipeline.cell_size_m is None

    def test_overrides_unknown_lists_known(self, registry):
        with pytest.raises(ParamError) as err:
            Config.paper().with_overrides(registry, {"nonsense": "1"})
        message = str(err.value)
        assert "'nonsense'" in message
        for known in ("k", "w", "alpha", "v", "r", "s", "q_bar", "t_bar", "cell_size_m"):
            assert known in message.split("known: ")[1].split(", "), f"{known} not listed in: {message}"

    def test_overrides_bad_values(self, registry):
        with pytest.raises(ParamError, match=r"k.*0.*\[1, 1000\]"):
            Config().with_overrides(registry, {"k": "0"})
        with pytest.raises(ParamError, match="not a valid int"):
            Config().with_overrides(registry, {"k": "three"})


# -- registrars -----------------------------------------------------------------------------------


def box_corner(n: int, *, seed: int, size_m: float = 0.04) -> np.ndarray:
    """``n`` points on the three faces of a box corner (a cell that pins all six degrees of freedom)."""
    rng = np.random.default_rng(seed)
    k = n // 3
    a = rng.uniform(0.0, size_m, (3, k, 2))
    zero = np.zeros(k)
    faces = [
        np.column_stack([zero, a[0, :, 0], a[0, :, 1]]),
        np.column_stack([a[1, :, 0], zero, a[1, :, 1]]),
        np.column_stack([a[2, :, 0], a[2, :, 1], zero]),
    ]
    return np.concatenate(faces) + [0.05, -0.02, 0.6]


TOL_M, TOL_DEG = 0.001, 0.5


@pytest.mark.parametrize("name", ["icp_point_to_point", "icp_point_to_plane"])
@pytest.mark.parametrize("case", ["translation", "rotation", "both"])
def test_registrar_recovers_known_motion(registry, name, case):
    """A 4 cm box corner (300 points, 0.6 m from the camera) moved by a known small R, t."""
    source = box_corner(300, seed=0)
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    R = Rotation.from_rotvec(np.radians(3.0 if case != "translation" else 0.0) * axis).as_matrix()
    centre = source.mean(0)
    shift = np.array([0.004, -0.003, 0.002]) if case != "rotation" else np.zeros(3)
    # rotate about the cell's own centre, then shift: T_target_from_source in the camera frame
    T_true = rigid(R, centre - R @ centre + shift)
    target = transform(source, T_true)
    result = registry.create("registrar", name).register(
        source, target, source_normals=None, target_normals=None, cell_size_m=0.04
    )
    T = result.T_target_from_source
    angle_err = np.degrees(rotation_angle_rad(T[:3, :3] @ T_true[:3, :3].T))
    point_err = np.abs(transform(source, T) - target).max()
    assert angle_err < TOL_DEG, f"{name}: rotation error {angle_err:.3f} deg > {TOL_DEG} deg"
    assert point_err < TOL_M, f"{name}: point error {point_err * 1000:.3f} mm > {TOL_M * 1000} mm"
    assert result.fitness == pytest.approx(1.0) and result.n_correspondences == 300


# -- the paper rule (Algorithm 2) -------------------------------------------------------------------


def cells_with(transforms: list[np.ndarray | None]) -> list[CellMotion]:
    cells = []
    for n, T in enumerate(transforms):
        cell = CellMotion((n, 0, 0), np.array([0.02 * n, 0.0, 0.6]), np.arange(10), np.arange(10))
        if T is None:
            cell.skipped = "too few points"
        else:
            cell.registration = Registration(T, 1.0, 0.0, 10)
        cells.append(cell)
    return cells


def decide(registry, transforms, **params):
    cls = registry.get("rule", "paper")
    empty = Cloud(0, np.zeros((0, 3)))
    return cls(cls.Params(**params)).decide(cells_with(transforms), source=empty, target=empty)


class TestPaperRule:
    # a motion well inside its quantisation bins: 30 degrees about z, t = (0.25, 0.35, -0.15) m
    MOVE = rigid(Rotation.from_euler("z", 30, degrees=True).as_matrix(), [0.25, 0.35, -0.15])
    OTHER = rigid(np.eye(3), [0.25, 0.35, -0.35])

    def test_one_motion_is_rm(self, registry):
        out = decide(registry, [self.MOVE] * 5)
        assert out.decision == "RM" and out.clusters == [0] * 5

    def test_identity_is_nm(self, registry):
        out = decide(registry, [np.eye(4)] * 4)
        assert out.decision == "NM" and out.clusters == [0] * 4

    def test_two_motions_is_am(self, registry):
        out = decide(registry, [np.eye(4), np.eye(4), self.MOVE, self.MOVE, self.OTHER])
        assert out.decision == "AM"
        assert out.clusters == [0, 0, 1, 1, 2] and len(out.keys) == 3

    def test_skipped_cells_get_no_cluster(self, registry):
        out = decide(registry, [self.MOVE, None, self.MOVE])
        assert out.decision == "RM" and out.clusters == [0, None, 0]
        assert decide(registry, [None, None]).decision == "skipped"

    def test_exact_multiples_stay_in_their_bin(self, registry):
        # 0.3 / 0.1 = 2.9999999999999996 in floating point: 0.3 must share the bin of 0.3 + 1 um
        exact = rigid(np.eye(3), [0.3, 0.2, 0.6])
        above = rigid(np.eye(3), [0.3 + 1e-6, 0.2 + 1e-6, 0.6 + 1e-6])
        out = decide(registry, [exact, above])
        assert out.decision == "RM" and len(out.keys) == 1, out.keys

    def test_negative_zero(self, registry):
        minus = rigid(np.eye(3), [-0.0, -0.0, -0.0])
        assert decide(registry, [np.eye(4), minus]).decision == "NM"

    def test_floor_bins_split_at_zero(self, registry):
        # as written (floor), a hair of motion either side of 0 lands in different bins; round does not
        a, b = rigid(np.eye(3), [0.0, 0.0, 1e-3]), rigid(np.eye(3), [0.0, 0.0, -1e-3])
        assert decide(registry, [a, b]).decision == "AM"
        assert decide(registry, [a, b], rounding="round").decision == "NM"

    def test_step_sizes(self, registry):
        near = rigid(np.eye(3), [0.0, 0.0, 0.03])
        # t_bar = 0.1 m: 3 cm is in the zero bin; t_bar = 0.02 m: it is not
        assert decide(registry, [near, near]).decision == "NM"
        assert decide(registry, [near, near], t_bar=0.02).decision == "RM"


# -- the paper preprocessor (Algorithm 1) --------------------------------------------------------------


def plane_frame(*, noise_m: float = 0.0, outliers: int = 0, seed: int = 0) -> tuple[Frame, np.ndarray]:
    """A fronto-parallel plate 0.6 m away filling a 60 x 40 pixel box of the test camera."""
    rng = np.random.default_rng(seed)
    h, w = INTRINSICS.height, INTRINSICS.width
    depth = np.zeros((h, w), np.float32)
    mask = np.zeros((h, w), bool)
    mask[40:80, 50:110] = True
    depth[mask] = 0.6 + rng.normal(0.0, noise_m, mask.sum()) if noise_m else 0.6
    if outliers:
        v, u = np.nonzero(mask)
        pick = rng.choice(len(v), outliers, replace=False)
        depth[v[pick], u[pick]] = 0.45  # flying pixels 15 cm in front of the plate
    return Frame(0, "plate", np.zeros((h, w, 3), np.uint8), depth, mask), mask


class TestPaperPreprocessor:
    def test_auto_v_and_r_recorded(self, registry):
        frame, mask = plane_frame()
        cloud = registry.create("preprocessor", "paper").process(frame, mask, intrinsics=INTRINSICS)
        info = cloud.info
        true_diameter = np.hypot(59, 39) * 0.6 / INTRINSICS.fx  # pixel centres of the corners
        # the diameter is taken after outlier removal, which trims the plate's corners a little
        assert 0.9 * true_diameter < info["diameter_m"] <= true_diameter + 1e-9
        assert info["v_m"] == pytest.approx(info["diameter_m"] / 20)
        assert info["r_m"] == pytest.approx(5 * info["v_m"])
        assert info["n_raw"] == mask.sum() and info["n_points"] == len(cloud.points)
        assert cloud.points.shape[1] == 3 and cloud.points.dtype == np.float64
        assert len(cloud.points) < info["n_raw"], "voxel downsampling reduces the cloud"

    def test_fixed_v_and_r(self, registry):
        frame, mask = plane_frame()
        cls = registry.get("preprocessor", "paper")
        cloud = cls(cls.Params(voxel_size_m=0.01, smoothing_radius_m=0.0)).process(
            frame, mask, intrinsics=INTRINSICS
        )
        assert cloud.info["v_m"] == 0.01 and cloud.info["r_m"] == 0.0
        # no two points of the downsampled cloud share a 1 cm voxel: neighbours are at least ~v apart
        gaps = pdist(cloud.points)
        assert gaps.min() > 0.004

    def test_outliers_removed(self, registry):
        frame, mask = plane_frame(outliers=20, seed=1)
        cls = registry.get("preprocessor", "paper")
        cloud = cls(cls.Params(smoothing_radius_m=0.0)).process(frame, mask, intrinsics=INTRINSICS)
        assert cloud.info["n_inliers"] <= cloud.info["n_raw"] - 20
        off = np.abs(cloud.points[:, 2] - 0.6).max()
        assert off < 0.005, f"a point is {off * 1000:.1f} mm off the plate after outlier removal"

    def test_smoothing_reduces_noise(self, registry):
        frame, mask = plane_frame(noise_m=0.003, seed=2)
        cls = registry.get("preprocessor", "paper")
        v = 0.004
        rough = cls(cls.Params(voxel_size_m=v, smoothing_radius_m=0.0)).process(
            frame, mask, intrinsics=INTRINSICS
        )
        smooth = cls(cls.Params(voxel_size_m=v)).process(frame, mask, intrinsics=INTRINSICS)  # r = 5 v
        before, after = rough.points[:, 2].std(), smooth.points[:, 2].std()
        assert smooth.info["r_m"] == pytest.approx(5 * v)
        assert after < 0.5 * before, f"depth noise {before * 1000:.2f} mm -> {after * 1000:.2f} mm"

    def test_empty_mask_gives_empty_cloud(self, registry):
        frame, mask = plane_frame()
        cloud = registry.create("preprocessor", "paper").process(
            frame, np.zeros_like(mask), intrinsics=INTRINSICS
        )
        assert cloud.points.shape == (0, 3)


# -- the streaming pipeline ------------------------------------------------------------------------------


def run(registry, seq, **overrides):
    config = Config().with_overrides(registry, {k: str(v) for k, v in overrides.items()})
    return Pipeline(registry, config).run(seq)


def assert_same(a, b, where: str = "result") -> None:
    """Nested results equal: strings, ints, None and structure exactly, floats within 1e-9."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), where
        for k in a:
            assert_same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert isinstance(b, (list, tuple)) and len(a) == len(b), where
        for n, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{where}[{n}]")
    elif isinstance(a, float) and not isinstance(b, bool):
        assert b == pytest.approx(a, rel=1e-9, abs=1e-9), f"{where}: {a} != {b}"
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


class TestPipelineRun:
    def test_pairs_are_i_i_plus_k(self, registry):
        result = run(registry, make_sequence("hinge", n_frames=7), k=2)
        assert [(p.i, p.j) for p in result.pairs] == [(i, i + 2) for i in range(5)]
        assert len(result.frames) == 7 and [f.index for f in result.frames] == list(range(7))
        assert all(f.cloud is None for f in result.frames), "streaming drops the clouds"
        assert result.plugins["segmenter"] == "mask", "auto uses the sequence's own masks"

    def test_a_slow_motion_shows_over_the_longer_pair(self, registry):
        """A panel turning 1.6 degrees a frame on its hinge moves by less than the noise threshold over
        k = 3 frames and by more over 6: each pair (i, i + 3) shows no motion, and (i, i + 6) shows the
        articulation where the sequence is long enough. The same for any number of workers, and when
        the kept run is decided again, under the same thresholds or under others."""
        seq = make_sequence("hinge", n_frames=10, step=np.radians(1.6), noise_m=0.0005, seed=3)
        alone = run(registry, seq, k=3, slow_factor=1)
        assert alone.label == "static" and {p.decision for p in alone.pairs} == {"NM"}
        config = Config().with_overrides(registry, {"k": "3"})
        one, two = (Pipeline(registry, config).run(seq, workers=w, keep_clouds=True) for w in (1, 2))
        assert one.label == "articulated"
        assert [(p.i, p.j, p.decision) for p in one.pairs] == [(i, i + 6, "AM") for i in range(4)] + [
            (i, i + 3, "NM") for i in range(4, 7)
        ]
        assert all(
            p.other.decision == "NM" and (p.other.i, p.other.j) == (p.i, p.i + 3) for p in one.pairs[:4]
        )
        assert all(p.other is None for p in one.pairs[4:]), "frame i + 6 is past the end"
        assert one.pairs[0].reason.startswith("no motion over 3 frames; over 6: ")
        for a, b in ((one, two), (one, Pipeline(registry, config).redecide(one))):
            assert_same([p.to_dict(cells=False) for p in a.pairs], [p.to_dict(cells=False) for p in b.pairs])
        # A lower threshold: the pairs (i, i + 3) show the motion themselves, and the longer pairs go.
        low = config.with_overrides(registry, {"noise_factor": "1"})
        again, fresh = (
            Pipeline(registry, low).redecide(one),
            Pipeline(registry, low).run(seq, keep_clouds=True),
        )
        assert any(p.j - p.i == 3 and p.decision != "NM" for p in again.pairs)
        # ... and back: the pairs that show no motion again are registered over 6 frames then.
        back = Pipeline(registry, config).redecide(fresh)
        for a, b in ((again, fresh), (back, one)):
            assert_same([p.to_dict(cells=False) for p in a.pairs], [p.to_dict(cells=False) for p in b.pairs])

    def test_empty_mask_frames_are_skipped(self, registry):
        result = run(registry, make_sequence("hinge", n_frames=7, empty_frames=(3,)), k=2)
        assert result.frames[3].skipped == "no object found"
        assert [f.index for f in result.frames if f.skipped] == [3]
        skipped = {(p.i, p.j): p.reason for p in result.pairs if p.decision == "skipped"}
        assert set(skipped) == {(1, 3), (3, 5)}
        assert all("frame 3" in reason for reason in skipped.values())
        assert len(result.filtered) == 3, "the filter runs over the decided pairs only"

    def test_too_short(self, registry):
        seq = make_sequence("static", n_frames=3)
        with pytest.raises(InputError, match="3 frames; k = 5 needs at least 6") as err:
            run(registry, seq)
        assert str(seq.path) in str(err.value), "the error names the sequence's path"

    def test_pixel_stride_uses_every_nth_pixel_and_keeps_the_full_image_for_flow(self, registry):
        seq = make_sequence("static", n_frames=1)
        fine = dataclasses.replace(Config.paper(), preprocessor="fine", preprocessor_params=None)
        full, strided = (
            Pipeline(registry, fine.with_overrides(registry, {"pixel_stride": n})).frame(seq, 0)
            for n in ("1", "2")
        )
        assert 0.2 < strided.cloud.info["n_raw"] / full.cloud.info["n_raw"] < 0.3
        assert np.array_equal(strided.cloud.view.depth_m, full.cloud.view.depth_m)

    def test_image_preprocessor_keeps_the_point_budget_and_each_points_pixel(self, registry):
        seq = make_sequence("static", n_frames=1)
        frame = seq[0]
        for budget in (200, 100000):
            cloud = (
                Pipeline(registry, Config().with_overrides(registry, {"max_points": budget}))
                .frame(seq, 0)
                .cloud
            )
            assert len(cloud) <= budget and cloud.pixels.shape == (len(cloud), 2)
            u, v = cloud.pixels.T
            assert frame.mask[v, u].all(), "every point comes from a pixel of the object"
            np.testing.assert_allclose(cloud.points[:, 2], cloud.view.depth_m[v, u], rtol=1e-6)
            assert (
                np.allclose(np.linalg.norm(cloud.normals, axis=1), 1.0)
                and (np.sum(cloud.normals * cloud.points, axis=1) < 0).all()
            )
        assert len(cloud) > 1000, "without a budget every usable pixel is a point"

    def test_no_object_anywhere(self, registry):
        seq = make_sequence("static", n_frames=3, empty_frames=(0, 1, 2))
        with pytest.raises(InputError, match="no object in any of the 3 frames"):
            run(registry, seq, k=1)

    def test_frames_a_segmenter_reads_ahead_are_timed_as_reading(self, registry):
        """``depth_threshold`` compares each frame with one 3 frames later, which it reads first: with
        every read taking 0.2 s, the reads are in "read", and "segment" is what it is from memory."""

        class SlowDisk(type(make_sequence())):
            def load(self, i):
                time.sleep(0.2)
                return super().load(i)

        frames = [make_sequence("static", n_frames=6, masks=False).load(i) for i in range(6)]
        pipeline = Pipeline(registry, dataclasses.replace(Config(), segmenter="depth_threshold"))
        fast = pipeline.run(type(make_sequence())(frames, name="memory")).timing_s
        slow = pipeline.run(SlowDisk(frames, name="slow disk")).timing_s
        assert slow["read"] >= 6 * 0.2  # every frame read once (the sequence keeps the last 8)
        assert slow["segment"] < fast["segment"] + 0.3  # not the 3 frames read ahead (0.6 s)

    def test_result_records_params_plugins_timing_and_is_json(self, registry):
        result = run(registry, make_sequence("hinge", n_frames=5), k=2, w=1, max_points=500)
        d = json.loads(json.dumps(result.to_dict()))
        assert d["label"] in ("articulated", "rigid", "static")
        assert d["params"]["pipeline"]["k"] == 2 and d["params"]["pipeline"]["w"] == 1
        assert d["params"]["preprocessor"]["max_points"] == 500
        assert set(d["plugins"]) == {"segmenter", "preprocessor", "registrar", "rule"}
        assert {"read", "segment", "preprocess", "register", "decide", "total"} <= set(d["timing_s"])
        assert d["timing_s"]["total"] >= d["timing_s"]["register"] >= 0
        assert sum(d["fractions"].values()) == pytest.approx(1.0)
        assert d["frames"][0]["n_points"] <= 500 and d["frames"][0]["noise_m"] >= 0
        motions = d["pairs"][0]["motions"]
        assert motions and all(len(m["T_target_from_source"]) == 4 and m["n_points"] >= 0 for m in motions)
        paper = Pipeline(registry, Config.paper().with_overrides(registry, {"k": "2", "v": "0.006"}))
        d = json.loads(json.dumps(paper.run(make_sequence("hinge", n_frames=5)).to_dict()))
        assert d["frames"][0]["v_m"] == 0.006
        assert d["pairs"][0]["n_cells"] == len(d["pairs"][0]["cells"]) > 0
        cell = next(c for c in d["pairs"][0]["cells"] if c["skipped"] is None)
        assert len(cell["quaternion_wxyz"]) == 4 and len(cell["translation_m"]) == 3

    @pytest.mark.slow
    def test_deterministic(self, registry):
        """Two runs give the same decisions and clusters; numbers agree to the last few bits (Open3D's
        parallel reductions may sum in a different order)."""
        seq = make_sequence("hinge", n_frames=6, noise_m=0.001, seed=3)
        a, b = (run(registry, seq, k=2).to_dict() for _ in range(2))
        for d in (a, b):
            d.pop("timing_s")
        assert_same(a, b)

    @pytest.mark.parametrize(
        "motion, label", [("static", "static"), ("rigid", "rigid"), ("hinge", "articulated")]
    )
    def test_default_config_labels(self, registry, motion, label):
        """Noise-free panels: nothing moves -> static; both move 1 cm away from the camera per pair ->
        rigid; one turns 10 degrees per pair about the edge it shares with the other -> articulated."""
        seq = make_sequence(motion, n_frames=6, step=0.005 if motion == "rigid" else None)
        result = run(registry, seq, k=2)
        assert result.label == label, [p.decision for p in result.pairs]
        decided = [p.decision for p in result.pairs if p.decision != "skipped"]
        assert len(decided) >= 3, "most pairs are decided"

    @pytest.mark.parametrize("motion, label", [("static", "static"), ("hinge", "articulated")])
    def test_paper_config_labels(self, registry, motion, label):
        """The paper's pipeline as written. (Its floor-quantised rule splits a rigid translation of
        flat panels over several keys, because ICP slides in the plane of a flat cell: see
        ``TestPaperRule.test_floor_bins_split_at_zero``; so no rigid case here.)"""
        config = Config.paper().with_overrides(registry, {"k": "2"})
        assert (config.preprocessor, config.rule, config.pipeline.prealign) == ("paper", "paper", False)
        result = Pipeline(registry, config).run(make_sequence(motion, n_frames=6))
        assert result.label == label, [p.decision for p in result.pairs]


def test_evaluation_counts_articulation_that_some_pair_shows(registry, rendered):
    """An articulated sequence counts as observable when some pair's truth is AM; the summary gives
    the accuracy over those beside the plain one."""
    from artclass_core import open_sequences
    from artclass_core.evaluate import Evaluation, SequenceOutcome, evaluate, markdown

    laptop = open_sequences(registry, rendered("laptop", "articulate", n_frames=12))[0]
    evaluation = evaluate(registry, [laptop], Config())
    (seen,) = evaluation.outcomes
    assert seen.observable is True and any(p == "AM" for p in (laptop.pair_truth(i, i + 5) for i in range(7)))
    hidden = SequenceOutcome("pliers_a", "pliers", "articulated", ("articulated",), "rigid", observable=False)
    rigid = SequenceOutcome("mug_a", "mug", "rigid", ("rigid",), "rigid", observable=False)
    both = Evaluation("dense", [seen, hidden, rigid], {})
    m = both.metrics()["articulated_observable"]
    assert (m["n"], m["of"], m["accuracy"]) == (1, 2, float(seen.correct))
    assert "where some pair shows the articulation" in markdown([both])
    assert "(1 of 2 sequences)" in markdown([both])


class _Hands:
    """A segmenter that finds given hand masks and gives given object masks, frame by frame."""

    def __init__(self, hands, objects):
        self.hands, self.objects = hands, objects

    def hand_mask(self, frame, *, sequence):
        return self.hands[frame.index]

    def segment(self, frame, *, sequence):
        return self.objects[frame.index]


def test_hand_masks_are_scored_against_the_hand_truth(tmp_path):
    """Pixels of the found and true hands are pooled over the frames with a hand; the arm counts in the
    object's mask where it takes more than 1 % of it; a hand found where the truth has none is a
    false alarm; frames without a truth file are not scored."""
    from types import SimpleNamespace

    import cv2

    from artclass_core.evaluate import hand_summary, score_hands

    def box(y0, y1, x0, x1):
        m = np.zeros((20, 20), bool)
        m[y0:y1, x0:x1] = True
        return m

    truths = [box(0, 10, 0, 4), box(0, 10, 0, 4), box(0, 0, 0, 0), None]  # 40, 40, no hand, no file
    (tmp_path / "hand").mkdir()
    for i, t in enumerate(truths):
        if t is not None:
            cv2.imwrite(str(tmp_path / "hand" / f"{i:06d}.png"), t.astype(np.uint8) * 255)
    frames = [SimpleNamespace(index=i, name=f"{i:06d}") for i in range(len(truths))]
    seq = type("Seq", (), {"path": tmp_path, "__len__": lambda s: 4, "__getitem__": lambda s, i: frames[i]})()
    hands = [box(0, 10, 0, 2), box(0, 10, 0, 4), box(5, 6, 5, 6), box(0, 20, 0, 20)]
    objects = [box(0, 10, 3, 20), box(0, 10, 4, 20), box(10, 20, 0, 20), None]  # arm: 10 of 170 px, 0
    counts = score_hands(_Hands(hands, objects), seq)
    assert counts == dict(
        intersection=20 + 40,
        union=40 + 40,
        frames_with_hand=2,
        arm_in_mask=1,
        frames_without_hand=1,
        found_without_hand=1,
    )
    summary = hand_summary([counts, counts])
    assert summary["hand_iou"] == pytest.approx(60 / 80) and summary["arm_in_mask"] == 0.5
    assert score_hands(_Hands([None] * 4, objects), seq) is None  # a segmenter that seeks no hands
    (tmp_path / "hand").rename(tmp_path / "elsewhere")
    assert score_hands(_Hands(hands, objects), seq) is None  # no hand truth


def test_evaluation_names_what_it_called_articulated_wrongly():
    """A rigid or static sequence called articulated is named in the summary; one whose label allows
    it (a static scene the truth also accepts as rigid) is not, nor is an articulated one."""
    from artclass_core.evaluate import Evaluation, SequenceOutcome, markdown

    outs = [
        SequenceOutcome("mug_carry", "mug", "rigid", ("rigid",), "articulated", moved_against="hand"),
        SequenceOutcome("box_static", "box", "static", ("static", "articulated"), "articulated"),
        SequenceOutcome("laptop_open", "laptop", "articulated", ("articulated",), "articulated"),
        SequenceOutcome("can_static", "can", "static", ("static",), "static"),
    ]
    evaluation = Evaluation("dense", outs, {})
    assert evaluation.metrics()["false_articulated"] == ["mug_carry"]
    assert evaluation.metrics()["false_articulated_against"] == {"mug_carry": "hand"}
    assert "| rigid or static called articulated | 1 (mug_carry: a hand or arm) |" in markdown([evaluation])
    assert "hand-and-arm mask IoU" not in markdown([evaluation])  # no segmenter sought hands


def test_evaluation_records_the_versions_its_numbers_depend_on():
    """The numpy the run imported, among the others, in the JSON and at the report's top."""
    from artclass_core.evaluate import SequenceOutcome, evaluation, markdown

    done = evaluation(Config(), [SequenceOutcome("can", "can", "static", ("static",), "static")])
    assert done.config["environment"]["numpy"] == np.__version__
    assert f"numpy {np.__version__}" in markdown([done]).splitlines()[2]


def _halves(hand_cols: int, object_cols: tuple[int, int]):
    """An articulation of a 20 x 20 picture whose left half is the base and right half the part, on a
    joint, with a hand over the ``hand_cols`` rightmost columns and the object over ``object_cols``."""
    from artclass_core.articulation import Articulation, JointEstimate, Part, PartJoint

    states = np.linspace(0.0, 0.5, 2)
    joint = PartJoint(0, 1, JointEstimate("revolute", np.ones(3), np.zeros(3), states, np.ones(2, bool)), 5)
    parts = [
        Part(0, "base", -1, np.zeros((1, 3)), [0, 1], 1),
        Part(1, "part1", 0, np.zeros((1, 3)), [0, 1], 1),
    ]
    view = (np.array([[2, 10], [17, 10]]), np.array([0, 1]), np.ones((20, 20), bool), 1)
    articulation = Articulation(parts, [joint], np.tile(np.eye(4), (2, 1, 1)), {0: view, 1: view})
    hand, obj = np.zeros((2, 20, 20), bool)
    hand[:, 20 - hand_cols :] = True
    obj[:, object_cols[0] : object_cols[1]] = True
    return articulation, {0: obj, 1: obj}, {0: hand, 1: hand}


@pytest.mark.parametrize(
    "hand_cols, object_cols, against",
    [
        (10, (0, 10), "hand"),  # the part is the hand
        (0, (10, 20), "beside"),  # the base is the stand the part was lifted from
        (0, (0, 20), "itself"),  # the object split in two
        (2, (0, 20), "itself"),  # a fifth of the part is the hand: the object split, all the same
    ],
)
def test_a_false_articulation_is_told_what_it_moved_against(hand_cols, object_cols, against):
    """The joint's part or base counts as the hand, or as beside the object, when a third of its
    pixels are; else the object moved against itself."""
    from artclass_core.evaluate import moved_against

    assert moved_against(*_halves(hand_cols, object_cols)) == against


def test_evaluation_says_what_a_false_articulation_moved_against(registry, held_laptop):
    """A run that calls a sequence articulated against its truth is told, from its parts and the
    object's and hand's truth beside the frames, what it moved against: this laptop, taken as rigid,
    opens its own lid."""
    from artclass_core import open_sequences
    from artclass_core.evaluate import evaluate

    laptop = open_sequences(registry, held_laptop)[0]
    laptop.label, laptop.accepted_labels = "rigid", ("rigid",)
    metrics = evaluate(registry, [laptop], Config(segmenter="mask")).metrics()
    assert metrics["false_articulated_against"] == {laptop.name: "itself"}


@pytest.fixture(scope="module")
def held_laptop(tmp_path_factory):
    """A laptop opened by a hand, with the hand's truth beside its frames."""
    from artclass_plugins.synth import generate_sequence

    folder = tmp_path_factory.mktemp("held") / "laptop"
    generate_sequence(
        folder,
        object_name="laptop",
        motion="articulate",
        noise="low",
        hand="hand",
        n_frames=12,
        seed=0,
        width=320,
        height=240,
    )
    return folder


def test_evaluation_scores_the_hands_a_segmenter_finds(registry, held_laptop):
    """``artclass evaluate`` with a segmenter that seeks hands reports its hand masks against the
    sequence's hand truth, and how long segmenting took."""
    from artclass_core import open_sequences
    from artclass_core.evaluate import HAND_COUNTS, evaluate, markdown

    laptop = open_sequences(registry, held_laptop)[0]
    evaluation = evaluate(registry, [laptop], Config(segmenter="depth_threshold"))
    (outcome,) = evaluation.outcomes
    assert set(outcome.hands) == set(HAND_COUNTS) and outcome.hands["frames_with_hand"] > 0
    hands = evaluation.metrics()["hands"]
    assert 0.0 < hands["hand_iou"] <= 1.0 and 0.0 <= hands["arm_in_mask"] <= 1.0
    assert evaluation.metrics()["segment_ms_per_frame"] > 0
    assert "hand-and-arm mask IoU, pooled over the frames with a hand" in markdown([evaluation])
    assert evaluate(registry, [laptop], Config(segmenter="mask")).metrics()["hands"] is None


def test_settings_that_share_masks_share_the_hand_scores(registry, held_laptop, monkeypatch):
    """Two settings of the rule run on the same masks: the hands are scored once, for both."""
    import artclass_core.evaluate as evaluate_module
    from artclass_core import open_sequences
    from artclass_core.sweep import grid_settings, sequence_rows

    scored = []
    score = evaluate_module.score_hands
    monkeypatch.setattr(evaluate_module, "score_hands", lambda *a, **kw: scored.append(1) or score(*a, **kw))
    laptop = open_sequences(registry, held_laptop)[0]
    settings = grid_settings(registry, {"noise_factor": ["2", "4"]}, segmenter="depth_threshold")
    outcomes = [o for _, _, o in sequence_rows(registry, laptop, settings)]
    assert outcomes[0].hands and outcomes[0].hands == outcomes[1].hands
    assert len(scored) == 1
