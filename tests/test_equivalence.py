"""The optimisations change nothing but speed and memory.

Correctness only (timings are in ``artclass bench`` / ``benchmarks/``): results identical whatever the
number of workers, the stage cache reused exactly where it may be and never where it may not,
re-deciding equal to running afresh and free of stale clusters, streaming runs holding a bounded
number of clouds, and the faster geometry equal to the straightforward one.
"""

from __future__ import annotations

import dataclasses
import gc
import os
import re
import subprocess
import sys
import weakref

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from artclass_core import ArtclassError, Config, Pipeline, PipelineParams
from artclass_core.cache import StageCache
from artclass_core.config import stage_config
from artclass_core.geometry import (
    diameter_of_vertices,
    grid_cells,
    hull_vertices,
    largest_distance,
    quaternion_wxyz,
)

from conftest import make_sequence


def config(**kw) -> Config:
    base = dict(
        segmenter="mask",
        preprocessor="paper",
        registrar="icp_point_to_point",
        rule="paper",
        pipeline=PipelineParams(k=2),
    )
    base.update(kw)
    return Config(**base)


def fingerprint(result) -> list:
    """Everything a run decided, down to each cell's transform (compared bit for bit)."""
    out = [result.label, tuple(result.filtered)]
    for p in result.pairs:
        out.append((p.i, p.j, p.decision, p.reason, p.cell_size_m, p.truth))
        for c in p.cells:
            reg = c.registration
            out.append(
                (
                    c.cell,
                    c.skipped,
                    c.cluster,
                    c.key,
                    tuple(c.source_idx),
                    tuple(c.target_idx),
                    None
                    if reg is None
                    else (reg.T_target_from_source.tobytes(), reg.fitness, reg.rmse_m, reg.n_correspondences),
                )
            )
    out.append([(f.index, f.skipped, f.mask_pixels, tuple(sorted(f.info.items()))) for f in result.frames])
    return out


@pytest.fixture(scope="module")
def hinge():
    return make_sequence("hinge", n_frames=9, noise_m=0.0005, seed=3)


# -- workers -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("registrar", ["icp_point_to_point", "icp_point_to_plane"])
def test_identical_results_whatever_the_number_of_workers(registry, hinge, registrar):
    cfg = config(registrar=registrar)
    runs = [Pipeline(registry, cfg).run(hinge, workers=w) for w in (1, 2, 3)]
    assert runs[0].label == ("articulated" if registrar == "icp_point_to_point" else runs[0].label)
    assert fingerprint(runs[1]) == fingerprint(runs[0])
    assert fingerprint(runs[2]) == fingerprint(runs[0])


@pytest.mark.slow
def test_identical_results_with_the_default_config(registry, hinge):
    cfg = dataclasses.replace(Config(), pipeline=PipelineParams(k=2))
    one, two = (Pipeline(registry, cfg).run(hinge, workers=w) for w in (1, 2))
    assert fingerprint(two) == fingerprint(one)
    assert [p.info for p in two.pairs] == [p.info for p in one.pairs]


@pytest.mark.slow
def test_repeated_runs_are_identical(registry, hinge):
    """Open3D's multi-threaded point-to-plane ICP differed in the 14th digit between runs, which now
    and then changed a cluster of the robust rule; the pipeline keeps Open3D to one thread."""
    import open3d as o3d

    cfg = dataclasses.replace(Config(), pipeline=PipelineParams(k=2))
    first = fingerprint(Pipeline(registry, cfg).run(hinge))
    assert o3d.utility.get_max_threads() == 1
    for _ in range(4):
        assert fingerprint(Pipeline(registry, cfg).run(hinge)) == first


@pytest.mark.slow
def test_importing_the_plugins_leaves_open3d_alone_and_the_pipeline_sets_one_thread():
    code = (
        "import open3d as o3d\n"
        "from artclass_core import Pipeline, load_registry\n"
        "before = o3d.utility.get_max_threads()\n"
        "registry = load_registry()\n"
        "assert before > 1 and o3d.utility.get_max_threads() == before, 'an import changed the threads'\n"
        "Pipeline(registry)\n"
        "assert o3d.utility.get_max_threads() == 1\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "OMP_NUM_THREADS": "2"},
    )
    assert done.returncode == 0, done.stderr[-2000:]


def test_point_to_plane_icp_is_reproducible(registry, hinge):
    pipe = Pipeline(registry, config(registrar="icp_point_to_plane"))
    a, b = pipe.frame(hinge, 0).cloud, pipe.frame(hinge, 2).cloud
    icp = registry.create("registrar", "icp_point_to_plane")
    runs = {
        icp.register(
            a.points, b.points, source_normals=a.normals, target_normals=b.normals, cell_size_m=0.06
        ).T_target_from_source.tobytes()
        for _ in range(30)
    }
    assert len(runs) == 1


def test_workers_with_skipped_frames_and_k1(registry):
    seq = make_sequence("hinge", n_frames=8, empty_frames=(2, 5))
    cfg = config(pipeline=PipelineParams(k=1))
    one, two = (Pipeline(registry, cfg).run(seq, workers=w) for w in (1, 2))
    assert fingerprint(one) == fingerprint(two)
    assert [p.decision for p in one.pairs].count("skipped") >= 4  # the pairs touching frames 2 and 5


def test_identical_results_with_the_depth_threshold_segmenter(registry):
    if "depth_threshold" not in registry.names("segmenter"):
        pytest.skip("no depth_threshold segmenter registered")
    seq = make_sequence("hinge", n_frames=7, masks=False)
    cfg = config(segmenter="depth_threshold")
    assert fingerprint(Pipeline(registry, cfg).run(seq, workers=2)) == fingerprint(
        Pipeline(registry, cfg).run(seq, workers=1)
    )


def test_workers_must_be_positive(registry, hinge):
    with pytest.raises(ArtclassError, match="workers"):
        Pipeline(registry, config()).run(hinge, workers=0)


def test_an_error_in_a_worker_reaches_the_caller(registry):
    seq = make_sequence("hinge", n_frames=6, masks=False)
    with pytest.raises(ArtclassError, match="no masks"):
        Pipeline(registry, config(segmenter="mask")).run(seq, workers=2)


# -- streaming --------------------------------------------------------------------------------------


class _Tracker:
    """Wraps a preprocessor: remembers (weakly) every cloud it made."""

    def __init__(self, inner):
        self.inner, self.refs = inner, []

    def process(self, frame, mask, *, intrinsics):
        cloud = self.inner.process(frame, mask, intrinsics=intrinsics)
        self.refs.append(weakref.ref(cloud))
        return cloud

    def alive(self) -> int:
        return sum(r() is not None for r in self.refs)


def _max_alive_clouds(registry, n_frames: int, workers: int, k: int = 2) -> tuple[int, int]:
    seq = make_sequence("rigid", n_frames=n_frames, step=0.002)
    pipe = Pipeline(registry, config(pipeline=PipelineParams(k=k)))
    tracker = _Tracker(pipe.preprocessor)
    pipe.preprocessor = tracker
    most = []

    def progress(stage, done, total):
        most.append(tracker.alive())

    result = pipe.run(seq, workers=workers, progress=progress)
    gc.collect()
    assert len(tracker.refs) == n_frames
    assert all(f.cloud is None for f in result.frames)
    return max(most), tracker.alive()


@pytest.mark.slow
@pytest.mark.parametrize("workers", [1, 2])
def test_streaming_holds_a_bounded_number_of_clouds(registry, workers):
    k = 2
    short_peak, _ = _max_alive_clouds(registry, 8, workers, k)
    long_peak, after = _max_alive_clouds(registry, 24, workers, k)
    # frames i+1 .. i+k wait for their pair; with workers, up to 2 per worker are read ahead and
    # up to 2 per worker pairs are in flight
    bound = k + 2 if workers == 1 else k + 2 + 4 * workers
    assert long_peak <= bound
    assert long_peak <= max(short_peak, bound)  # does not grow with the length
    assert after == 0, "a finished run keeps no cloud alive"


def test_keep_clouds_keeps_every_cloud(registry, hinge):
    result = Pipeline(registry, config()).run(hinge, keep_clouds=True, workers=2)
    assert all(f.cloud is not None for f in result.frames)


# -- the stage cache ---------------------------------------------------------------------------------


def _counting(seq):
    calls = []
    load = seq.load

    def counted(i):
        calls.append(i)
        return load(i)

    seq.load = counted
    seq.frame.cache_clear()
    return calls


def test_rule_change_reuses_clouds_and_registrations(registry):
    seq = make_sequence("hinge", n_frames=8, noise_m=0.0005, seed=1)
    cache = StageCache()
    first = Pipeline(registry, config()).run(seq, cache=cache)
    calls = _counting(seq)
    changed = config(
        rule_params=registry.get("rule", "paper").Params(q_bar=0.3, t_bar=0.3),
        pipeline=PipelineParams(k=2, alpha=0.5, min_fitness=0.5, w=1),
    )
    stats0 = cache.stats()
    again = Pipeline(registry, changed).run(seq, cache=cache)
    stats1 = cache.stats()
    assert calls == [], "no frame is read again"
    assert stats1["hits"]["frame"] - stats0["hits"]["frame"] == len(seq)
    assert stats1["hits"]["register"] - stats0["hits"]["register"] == len(again.pairs)
    assert stats1["misses"] == stats0["misses"]
    fresh = Pipeline(registry, changed).run(make_sequence("hinge", n_frames=8, noise_m=0.0005, seed=1))
    assert fingerprint(again) == fingerprint(fresh)
    assert fingerprint(first) != fingerprint(again)


def test_registration_change_reuses_clouds_only(registry):
    seq = make_sequence("hinge", n_frames=6)
    cache = StageCache()
    Pipeline(registry, config()).run(seq, cache=cache)
    calls = _counting(seq)
    icp = registry.get("registrar", "icp_point_to_point").Params(max_iterations=5)
    s0 = cache.stats()
    again = Pipeline(registry, config(registrar_params=icp)).run(seq, cache=cache)
    s1 = cache.stats()
    assert calls == []
    assert s1["hits"]["register"] == s0["hits"]["register"]
    assert s1["misses"]["register"] - s0["misses"]["register"] == len(again.pairs)
    fresh = Pipeline(registry, config(registrar_params=icp)).run(make_sequence("hinge", n_frames=6))
    assert fingerprint(again) == fingerprint(fresh)


def test_k_change_reuses_the_clouds(registry):
    seq = make_sequence("hinge", n_frames=6)
    cache = StageCache()
    Pipeline(registry, config()).run(seq, cache=cache)
    calls = _counting(seq)
    again = Pipeline(registry, config(pipeline=PipelineParams(k=1))).run(seq, cache=cache)
    assert calls == []
    assert len(again.pairs) == 5


def test_preprocessor_change_misses(registry):
    seq = make_sequence("hinge", n_frames=5)
    cache = StageCache()
    Pipeline(registry, config()).run(seq, cache=cache)
    calls = _counting(seq)
    pre = registry.get("preprocessor", "paper").Params(std_ratio=2.0)
    Pipeline(registry, config(preprocessor_params=pre)).run(seq, cache=cache)
    assert sorted(set(calls)) == list(range(5))


def test_two_sequences_never_share_entries(registry):
    """Same name and path, different content: the cache tells them apart by identity."""
    still = make_sequence("hinge", n_frames=5, step=0.0)
    moving = make_sequence("hinge", n_frames=5)
    assert (still.name, still.path) == (moving.name, moving.path)
    cache = StageCache()
    a = Pipeline(registry, config()).run(still, cache=cache)
    b = Pipeline(registry, config()).run(moving, cache=cache)
    assert fingerprint(b) == fingerprint(Pipeline(registry, config()).run(make_sequence("hinge", n_frames=5)))
    assert a.label == "static" and b.label == "articulated"


def test_cache_is_bounded_and_forgets_dead_sequences(registry):
    cache = StageCache(max_frames=3, max_pairs=2)
    seq = make_sequence("rigid", n_frames=6)
    Pipeline(registry, config()).run(seq, cache=cache)
    assert cache.stats()["frames"] == 3 and cache.stats()["pairs"] == 2
    del seq
    gc.collect()
    assert cache.stats()["frames"] == 0 and cache.stats()["pairs"] == 0


def test_a_dropped_cache_is_freed_while_its_sequence_lives(registry):
    """Evaluating a folder keeps every sequence open and runs each with a cache of its own: a cache
    must not live (with every frame's cloud in it) for as long as the sequences do."""
    seq = make_sequence("rigid", n_frames=4)
    cache = StageCache()
    Pipeline(registry, config()).run(seq, cache=cache)
    gone = weakref.ref(cache)
    del cache
    gc.collect()
    assert gone() is None


# -- re-deciding ---------------------------------------------------------------------------------------


def test_redecide_equals_a_fresh_run_and_leaves_the_first_result_alone(registry, hinge):
    first = Pipeline(registry, config()).run(hinge, keep_clouds=True)
    before = fingerprint(first)
    changed = config(
        rule_params=registry.get("rule", "paper").Params(q_bar=0.5, t_bar=0.5),
        pipeline=PipelineParams(k=2, w=1, alpha=0.6),
    )
    redecided = Pipeline(registry, changed).redecide(first)
    fresh = Pipeline(registry, changed).run(hinge, keep_clouds=True)
    assert fingerprint(redecided) == fingerprint(fresh)
    assert fingerprint(first) == before, "no stale clusters written into the first result"
    assert redecided.params["rule"]["q_bar"] == 0.5 and redecided.params["pipeline"]["alpha"] == 0.6


@pytest.mark.slow
def test_redecide_is_the_same_whatever_the_number_of_workers(registry, hinge):
    cfg = dataclasses.replace(Config(), pipeline=PipelineParams(k=2))
    changed = cfg.with_overrides(registry, {"noise_factor": "2.5"})  # moves every cost and threshold
    one, two = (
        Pipeline(registry, changed).redecide(Pipeline(registry, cfg).run(hinge, keep_clouds=True), workers=w)
        for w in (1, 2)
    )
    fresh = Pipeline(registry, changed).run(hinge)
    assert fingerprint(two) == fingerprint(one) == fingerprint(fresh)
    assert [p.info for p in two.pairs] == [p.info for p in one.pairs] == [p.info for p in fresh.pairs]
    with pytest.raises(ArtclassError, match="workers"):
        Pipeline(registry, changed).redecide(one, workers=0)


def test_redecide_with_another_rule_and_back(registry, hinge):
    rules = [r for r in registry.names("rule") if r != "paper"]
    if not rules:
        pytest.skip("only one decision rule is registered")
    first = Pipeline(registry, config()).run(hinge, keep_clouds=True)
    other = Pipeline(registry, config(rule=rules[0])).redecide(first)
    assert fingerprint(other) == fingerprint(Pipeline(registry, config(rule=rules[0])).run(hinge))
    back = Pipeline(registry, config()).redecide(other)
    assert fingerprint(back) == fingerprint(first)


def test_redecide_tries_the_shorter_pair_as_a_fresh_run_does(hinge):
    """A rule that leaves the pairs (i, i + 2) undecided: re-deciding a run under it decides the pairs
    (i, i + 1) instead, as a run under it does, and re-deciding back restores the first run."""
    from types import SimpleNamespace

    from artclass_core import hookimpl, load_registry
    from artclass_plugins.rules.paper import PaperRule

    class OneFrameAtMost(PaperRule):
        name = "one_frame_at_most"

        def decide(self, cells, *, source, target, **kw):
            out = super().decide(cells, source=source, target=target, **kw)
            if target.frame_index - source.frame_index > 1:
                out = dataclasses.replace(out, decision="undecided", reason="beyond reach")
            return out

    @hookimpl
    def register_rules(register):
        register(OneFrameAtMost)

    registry = load_registry(extra_plugins=(SimpleNamespace(register_rules=register_rules),))
    first = Pipeline(registry, config()).run(hinge, keep_clouds=True)
    limited = config(rule="one_frame_at_most")
    redecided = Pipeline(registry, limited).redecide(first)
    fresh = Pipeline(registry, limited).run(hinge, keep_clouds=True)
    assert {p.j - p.i for p in fresh.pairs} == {1}
    assert fingerprint(redecided) == fingerprint(fresh)
    assert fingerprint(Pipeline(registry, config()).redecide(fresh)) == fingerprint(first)


def test_redecide_from_the_cache(registry):
    seq = make_sequence("hinge", n_frames=6)
    cache = StageCache()
    first = Pipeline(registry, config()).run(seq, cache=cache)  # clouds dropped from the result
    changed = config(pipeline=PipelineParams(k=2, min_fitness=0.9))
    with pytest.raises(ArtclassError, match="keep_clouds"):
        Pipeline(registry, changed).redecide(first)
    calls = _counting(seq)
    again = Pipeline(registry, changed).redecide(first, sequence=seq, cache=cache)
    assert calls == []
    assert fingerprint(again) == fingerprint(
        Pipeline(registry, changed).run(make_sequence("hinge", n_frames=6))
    )


def test_redecide_goes_without_a_skipped_frame_between(registry):
    """A frame between a pair's two that was skipped (no object in it) is not needed to re-decide the
    pair with a rule that looks at the frames between: the run went without it too."""
    from artclass_plugins.rules.paper import PaperRule

    seen = []

    class Between(PaperRule):
        uses_frames_between = True  # as a rule that follows the images from frame to frame

        def decide(self, cells, *, between=(), **kw):
            seen.append(len(between))
            return super().decide(cells, **kw)

    def pipeline(cfg: Config) -> Pipeline:
        pipe = Pipeline(registry, cfg)
        pipe.rule = Between(pipe.rule.params)
        return pipe

    seq = make_sequence("hinge", n_frames=6, empty_frames=(2,))
    first = pipeline(config()).run(seq, keep_clouds=True)
    assert [f.index for f in first.frames if f.skipped] == [2]
    assert 1 in seen, "pairs whose frame between was kept get it"
    changed = config(pipeline=PipelineParams(k=2, w=1))
    assert fingerprint(pipeline(changed).redecide(first)) == fingerprint(pipeline(changed).run(seq))


@pytest.mark.parametrize(
    "change",
    [
        dict(pipeline=PipelineParams(k=1)),
        dict(pipeline=PipelineParams(k=2, cell_size_m=0.02)),
        dict(pipeline=PipelineParams(k=2, min_cell_points=20)),
        dict(registrar="icp_point_to_plane"),
        dict(preprocessor_params="std_ratio"),
    ],
)
def test_redecide_refuses_changed_registrations(registry, hinge, change):
    if change.get("preprocessor_params") == "std_ratio":
        change = dict(preprocessor_params=registry.get("preprocessor", "paper").Params(std_ratio=1.5))
    first = Pipeline(registry, config()).run(hinge, keep_clouds=True)
    with pytest.raises(ArtclassError, match="cannot re-decide"):
        Pipeline(registry, config(**change)).redecide(first)


def test_decide_does_not_modify_the_cells_it_is_given(registry, hinge):
    pipe = Pipeline(registry, config())
    a, b = pipe.frame(hinge, 0), pipe.frame(hinge, 2)
    cells, x = pipe.register(a.cloud, b.cloud)
    for c in cells:
        c.cluster, c.key = 99, "stale"
    pair = pipe.decide(0, 2, cells, a.cloud, b.cloud, x)
    assert all(c.cluster == 99 and c.key == "stale" for c in cells)
    assert all(c.cluster != 99 and c.key != "stale" for c in pair.cells)
    assert any(c.cluster is not None for c in pair.cells)


# -- geometry shortcuts ---------------------------------------------------------------------------------


def _reference_grid_cells(source, target, *, cell_size_m):
    """The straightforward grid (np.unique over rows), as it was written first."""
    origin = np.minimum(source.min(0), target.min(0))
    keys = np.floor((np.concatenate([source, target]) - origin) / cell_size_m).astype(np.int64)
    cells, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(len(cells) + 1))
    n_s = len(source)
    return [
        (
            tuple(int(v) for v in cell),
            origin + (cell + 0.5) * cell_size_m,
            order[bounds[c] : bounds[c + 1]][order[bounds[c] : bounds[c + 1]] < n_s],
            order[bounds[c] : bounds[c + 1]][order[bounds[c] : bounds[c + 1]] >= n_s] - n_s,
        )
        for c, cell in enumerate(cells)
    ]


@pytest.mark.parametrize("seed", range(5))
def test_grid_cells_equal_the_reference(seed):
    rng = np.random.default_rng(seed)
    source = rng.normal(scale=0.05, size=(rng.integers(1, 2000), 3)) + [0, 0, 0.7]
    target = rng.normal(scale=0.05, size=(rng.integers(1, 2000), 3)) + [0.01, 0, 0.7]
    x = rng.uniform(0.003, 0.08)
    got, want = (
        grid_cells(source, target, cell_size_m=x),
        _reference_grid_cells(source, target, cell_size_m=x),
    )
    assert len(got) == len(want)
    for g, w in zip(got, want):
        assert g[0] == w[0] and np.array_equal(g[1], w[1])
        assert np.array_equal(g[2], w[2]) and np.array_equal(g[3], w[3])


@pytest.mark.parametrize("seed", range(5))
def test_pair_diameter_from_hull_vertices_is_exact(registry, seed):
    rng = np.random.default_rng(seed)
    a = rng.normal(scale=0.04, size=(1500, 3))
    b = rng.normal(scale=0.04, size=(900, 3)) + rng.normal(scale=0.03, size=3)
    both = diameter_of_vertices(np.concatenate([hull_vertices(a), hull_vertices(b)]))
    assert both == largest_distance(np.concatenate([a, b]))  # bit for bit


def test_cell_size_is_a_fifth_of_the_pair_diameter(registry, hinge):
    pipe = Pipeline(registry, config())
    a, b = pipe.frame(hinge, 0).cloud, pipe.frame(hinge, 2).cloud
    assert pipe.cell_size(a, b) == max(largest_distance(np.concatenate([a.points, b.points])) / 5, 1e-4)
    a.points = a.points + [0.5, 0.0, 0.0]  # moved: the hull follows the points
    assert pipe.cell_size(a, b) == max(largest_distance(np.concatenate([a.points, b.points])) / 5, 1e-4)


def test_quaternion_equals_scipy():
    rng = np.random.default_rng(0)
    for t in range(300):
        R = Rotation.random(random_state=t).as_matrix()
        if t % 2:
            R = R + rng.normal(scale=1e-8, size=(3, 3))  # not orthonormal: projected first
        x, y, z, w = Rotation.from_matrix(R).as_quat()
        want = np.array([w, x, y, z]) * (1 if w >= 0 else -1)
        assert np.allclose(quaternion_wxyz(R), want, rtol=0, atol=1e-15)
    assert np.array_equal(quaternion_wxyz(np.eye(3)), [1.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError):
        quaternion_wxyz(np.diag([1.0, 1.0, -1.0]))


@pytest.mark.parametrize("seed", range(3))
def test_statistical_inliers_equal_open3d(seed):
    import open3d as o3d

    from artclass_core.geometry import statistical_inliers

    rng = np.random.default_rng(seed)
    surface = np.column_stack([rng.uniform(-0.1, 0.1, (3000, 2)), np.full(3000, 0.7)])
    surface[:, 2] += rng.normal(scale=0.001, size=3000)
    flying = rng.uniform([-0.1, -0.1, 0.5], [0.1, 0.1, 0.9], (60, 3))
    points = np.concatenate([surface, flying, surface[:5]])  # duplicates too
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    for neighbours, ratio in ((20, 0.5), (8, 2.0), (1, 1.0)):
        _, want = pcd.remove_statistical_outlier(nb_neighbors=neighbours, std_ratio=ratio)
        got = statistical_inliers(points, neighbours=neighbours, std_ratio=ratio)
        assert np.array_equal(got, np.asarray(want)), (neighbours, ratio)
    assert len(statistical_inliers(points, neighbours=20, std_ratio=0.5)) < len(points) - 40  # flyers go


# -- the benchmark command (its numbers are printed, not judged; here only that it runs and reports) ---


def test_cycled_sequence_plays_back_and_forth(sample_dir, registry):
    from artclass_core import open_sequences
    from artclass_plugins.bench import CycledSequence

    base = open_sequences(registry, sample_dir / "drawer_carry_articulate")[0]
    n = len(base)
    long = CycledSequence(base, 5 * n)
    order = [long.base_index(i) for i in range(len(long))]
    assert order[:n] == list(range(n)) and order[n : 2 * n - 1] == list(range(n - 2, -1, -1))
    assert all(abs(a - b) == 1 for a, b in zip(order, order[1:])), "neighbours stay neighbours"
    f = long[n + 1]
    assert f.index == n + 1 and np.array_equal(f.depth_m, base[n - 3].depth_m)
    assert f.depth_m is not base[n - 3].depth_m, "copies, so the base's cache is not pinned"


@pytest.mark.slow
def test_bench_command_reports_every_stage(sample_dir, tmp_path, capsys):
    import json

    from artclass_core.cli import main

    out = tmp_path / "bench.json"
    status = main(
        [
            "bench",
            "--sequence",
            str(sample_dir / "drawer_carry_articulate"),
            "--segmenters",
            "mask",
            "--workers",
            "1,2",
            "--long-frames",
            "40",
            "--json",
            str(out),
        ]
    )
    text = capsys.readouterr().out
    assert status == 0
    for stage in ("read", "segment", "preprocess", "register", "decide", "total"):
        assert text.count(f"\n  {stage} ") == 3, f"stage {stage} missing from {text}"
    assert "the paper's pipeline: segmenter=mask workers=1" in text
    ratio = re.search(r"= (\d+\.\d+) of its wall time", text)
    assert ratio and float(ratio.group(1)) > 0, text
    assert "re-decide after a rule change" in text and "long sequence (40 frames" in text
    data = json.loads(out.read_text())
    assert [r["spec"]["workers"] for r in data["runs"]] == [1, 2]
    assert all(
        "error" not in r and r["n_pairs"] > 0 and r["wall_s"] > 0 and r["peak_rss_mb"] > 0
        for r in data["runs"]
    )
    assert data["runs"][0]["label"] == data["runs"][1]["label"]
    assert data["paper"]["spec"]["paper"] is True and data["paper"]["n_pairs"] == data["runs"][0]["n_pairs"]
    assert data["redecide"]["redecide_equals_cached_rerun"] is True
    assert data["long"]["n_pairs"] == 40 - 5


# -- the pair's scratch space (a rule's threshold-independent evidence) ----------------------------------


def test_pair_scratch_lives_with_the_cached_registration(registry, hinge):
    cache = StageCache(max_frames=64, max_pairs=1)
    pipe = Pipeline(registry, config())
    one = pipe.run(hinge, cache=cache)
    key = pipe.pair_key(hinge, one.pairs[-1].i, one.pairs[-1].j, cache)
    scratch = cache.scratch(key)
    scratch["evidence"] = 42
    assert cache.scratch(key) is scratch
    assert cache.scratch(pipe.pair_key(hinge, 0, pipe.params.k, cache)) is not scratch, "another pair"
    cache.put("register", pipe.pair_key(hinge, 0, pipe.params.k, cache), ((), 0.01))  # drops the first entry
    assert "evidence" not in cache.scratch(key), "dropped with its registration"


def test_rule_evidence_in_the_memo_is_reused_when_redeciding(registry, hinge):
    """A rule that keeps its costly part in the pair's scratch does it once per pair, however often it
    re-decides, from a kept result or from the stage cache."""
    from artclass_core import DecisionRule, RuleDecision

    calls = []

    class Memoising(DecisionRule):
        name, description = "memo_test", "test rule"
        Params = registry.get("rule", "paper").Params
        uses_scratch = True

        def decide(self, cells, *, source, target, scratch):
            memo = scratch
            key = tuple((c.cell, id(c.registration)) for c in cells if c.matched)
            if key not in memo:
                calls.append(1)
                memo[key] = sum(c.registration.fitness for c in cells if c.matched)
            decision = "AM" if memo[key] > self.params.q_bar * 10 else "NM"
            return RuleDecision(decision, [0 if c.matched else None for c in cells], ["all"])

    # One pair per frame (no longer pairs of slow motions, which would be new evidence).
    same_pairs = config(pipeline=PipelineParams(k=2, slow_factor=1))
    first = Pipeline(registry, same_pairs).run(hinge, keep_clouds=True)
    pipe = Pipeline(registry, same_pairs)
    pipe.rule = Memoising(Memoising.Params(q_bar=0.1))
    one = pipe.redecide(first)
    n_calls = len(calls)
    assert n_calls == sum(bool(p.cells) and p.decision != "skipped" for p in one.pairs) > 0
    pipe.rule = Memoising(Memoising.Params(q_bar=1.9))
    two = pipe.redecide(first)
    assert len(calls) == n_calls, "the evidence was found again"
    assert [p.decision for p in one.pairs] != [p.decision for p in two.pairs]
    cache = StageCache()
    streamed = Pipeline(registry, same_pairs).run(hinge, cache=cache)  # no clouds kept in the result
    pipe.redecide(streamed, sequence=hinge, cache=cache)
    n_calls = len(calls)
    assert fingerprint(pipe.redecide(streamed, sequence=hinge, cache=cache)) == fingerprint(two)
    assert len(calls) == n_calls, "the evidence was found again in the cache"


def test_stage_configs_depend_on_what_the_stage_uses():
    stages = ("segment", "preprocess", "register", "decide")
    base = Config(rule="paper")
    keys = {s: stage_config(base, s) for s in stages}

    def changed(config):
        return {s for s in stages if stage_config(config, s) != keys[s]}

    from artclass_plugins.rules.paper import PaperRuleParams

    later = {"register", "decide"}
    assert changed(Config(rule="paper", rule_params=PaperRuleParams(q_bar=0.5))) == {"decide"}
    assert changed(Config(rule="paper", pipeline=PipelineParams(alpha=0.9))) == {"decide"}
    assert changed(Config(rule="paper", pipeline=PipelineParams(min_fitness=0.9))) == {"decide"}
    assert changed(Config(rule="paper", pipeline=PipelineParams(w=7))) == set()
    assert changed(Config(rule="paper", pipeline=PipelineParams(k=2))) == set()
    assert changed(Config(rule="paper", pipeline=PipelineParams(cell_size_m=0.02))) == later
    assert changed(Config(rule="paper", registrar="icp_point_to_plane")) == later
    assert changed(Config(rule="paper", pipeline=PipelineParams(min_cell_points=20))) == later
    assert changed(Config(rule="paper", preprocessor="paper")) == {"preprocess", *later}
    assert changed(Config(rule="paper", segmenter="mask")) == set(stages)
