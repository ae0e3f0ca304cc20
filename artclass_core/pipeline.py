"""The pipeline: frames -> masks -> clouds -> pairs (i, i + k) -> per-cell registrations -> pair
decisions -> moving max-count filter -> sequence label.

Each stage is a method of :class:`Pipeline` that can be called on its own (the app caches them one by
one); :meth:`Pipeline.run` streams a whole sequence, holding only the clouds that pending pairs need,
so memory does not grow with the sequence length.

Stages and what their results depend on
----------------------------------------
========== ============================================ ==============================================
stage      method                                       depends on
========== ============================================ ==============================================
frame      :meth:`Pipeline.frame` (read, segment,       the frame, segmenter and preprocessor (and
           preprocess)                                  their params); ``min_cell_points`` only marks
                                                        a too-small cloud as skipped
register   :meth:`Pipeline.register` (grid of cells of  the two clouds, registrar (and params),
           size x, ICP per cell)                        ``cell_size_m``, ``min_cell_points``
decide     :meth:`Pipeline.decide` (fitness and alpha   the registrations, ``min_fitness``, ``alpha``,
           checks, decision rule)                       rule (and params)
summarise  :meth:`Pipeline.summarise` (max-count        the pair decisions, ``w``
           filter, label)
========== ============================================ ==============================================

Incremental re-runs
-------------------
A :class:`StageCache` keeps each frame's cloud and each pair's registrations, keyed on exactly what
they depend on (the table above; parameters are frozen dataclasses, hence hashable keys). Pass the
same cache to successive runs::

    cache = StageCache()
    result = Pipeline(registry, config).run(sequence, cache=cache)            # reads, segments, ICP
    config2 = dataclasses.replace(config, rule_params=RuleParams(q_bar=0.2))
    result2 = Pipeline(registry, config2).run(sequence, cache=cache)          # decides only

A change of a decision parameter (rule and its params, ``alpha``, ``min_fitness``, ``w``) reuses the
cached registrations; a change of a registration parameter (registrar and its params,
``cell_size_m``, ``min_cell_points``) reuses the cached clouds; a change of ``k`` reuses the clouds
and any registered pair it still needs. :meth:`Pipeline.redecide` re-decides a finished
:class:`RunResult` directly (it needs the clouds: a run with ``keep_clouds=True``, or the cache).
Deciding never modifies the cells it is given: :meth:`Pipeline.decide` works on copies, so a cached
registration can be decided again and again without stale clusters. A rule whose own work is costly
can keep its threshold-independent evidence in :func:`pair_memo`, which lives as long as the pair's
clouds, so that re-deciding under other thresholds does not redo it.

Throughput
----------
``run(sequence, workers=N)`` spreads frames and pairs over N threads. OpenCV image decoding, SciPy
KD-trees, NumPy and Open3D ICP release the GIL; Open3D's statistical outlier removal and normal
estimation hold it, so with the ``paper`` preprocessor (whose outlier removal is most of a frame's
cost) a second worker gains little; measure with ``artclass bench``. Every frame and pair is computed by the
same deterministic function whatever thread runs it, and results are collected in frame order, so
the result is identical for any number of workers. At most about ``2 * workers + k`` frames are in
flight at once, so the peak memory does not depend on the sequence length; only the result grows, by
about 40 kB per pair (its cells' motions, clusters and point indices, measured at 640x480; dropping the
index arrays would save a fifth of that, so they are kept for the rules and the app).
"""

from __future__ import annotations

import dataclasses
import threading
import time
import weakref
from collections import Counter, OrderedDict, deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .errors import ArtclassError, InputError, ParamError
from .geometry import diameter_of_vertices, grid_cells, hull_vertices, transform
from .params import Params, PipelineParams, as_dict, describe, parse_value
from .plugins import Registry
from .types import DECISIONS, CellMotion, Cloud, FrameResult, MotionEvidence, PairResult, RunResult, Sequence

SEVERITY = {"NM": 0, "RM": 1, "AM": 2}
STAGES = ("read", "segment", "preprocess", "register", "decide")
PLUGIN_KINDS = ("segmenter", "preprocessor", "registrar", "rule")
AUTO_SEGMENTER = "auto"   # the sequence's own masks when it has them, else depth_threshold
CELL_REGISTRAR, CELL_RULE = "icp_point_to_point", "paper"   # the paper's, for a per-cell pipeline

Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class Config:
    """Which plugins run and with which parameters. Frozen and hashable: a safe cache key.

    A plugin's params left as ``None`` mean that plugin's defaults. The defaults are the dense
    pipeline (``image`` preprocessing, ``dense`` motion hypotheses for the whole pair, the ``dense``
    model-selection rule); :meth:`paper` gives the paper's pipeline as written, for comparison.
    """

    segmenter: str = AUTO_SEGMENTER
    preprocessor: str = "image"
    registrar: str = "dense"
    rule: str = "dense"
    pipeline: PipelineParams = field(default_factory=PipelineParams)
    segmenter_params: Params | None = None
    preprocessor_params: Params | None = None
    registrar_params: Params | None = None
    rule_params: Params | None = None

    @classmethod
    def paper(cls) -> "Config":
        """The paper's pipeline as written: Algorithm 1 at D/20 and 5v, per-cell ICP from the identity,
        Algorithm 2's quantise-and-hash rule."""
        return cls(preprocessor="paper", registrar=CELL_REGISTRAR, rule="paper",
                   pipeline=PipelineParams(prealign=False))

    def plugin_params(self, registry: Registry, kind: str, name: str | None = None) -> Params:
        """The params of the chosen plugin of ``kind`` (its defaults when none were set)."""
        name = name or getattr(self, kind)
        params = getattr(self, f"{kind}_params")
        cls = registry.get(kind, name).Params
        return params if isinstance(params, cls) else cls()

    def with_overrides(self, registry: Registry, overrides: dict[str, str | float | int | None]) -> "Config":
        """A copy with parameters set by name or paper symbol (``v=0.005``, ``q_bar=0.2`` ...).

        Values may be strings (parsed with the field's type; ``auto`` = automatic) or values.
        Raises :class:`ParamError` naming an unknown parameter or an out-of-bounds value.
        """
        targets = {"pipeline": self.pipeline}
        for kind in PLUGIN_KINDS:
            name = getattr(self, kind)
            if kind == "segmenter" and name == AUTO_SEGMENTER:
                continue
            targets[kind] = self.plugin_params(registry, kind)
        changes: dict[str, dict] = {kind: {} for kind in targets}
        for key, value in overrides.items():
            hits = [(kind, spec) for kind, p in targets.items() for spec in describe(type(p))
                    if key in (spec.name, spec.symbol)]
            if not hits:
                known = sorted({n for p in targets.values() for s in describe(type(p)) for n in (s.name, s.symbol) if n})
                raise ParamError(f"unknown parameter {key!r}; known: {', '.join(known)}")
            for kind, spec in hits:
                changes[kind][spec.name] = parse_value(spec, value) if isinstance(value, str) else value
        fields = {}
        for kind, p in targets.items():
            if changes[kind]:
                p = dataclasses.replace(p, **changes[kind])
            fields["pipeline" if kind == "pipeline" else f"{kind}_params"] = p
        return dataclasses.replace(self, **fields)


class StageCache:
    """Frame clouds and pair registrations kept between runs, keyed on everything they depend on.

    Used by :meth:`Pipeline.run` (``cache=``) and :meth:`Pipeline.redecide`; see the module docstring.
    Both tables are LRU-bounded (``max_frames`` clouds, ``max_pairs`` registered pairs), so a cache
    can stay alive in a long-lived app. Sequences are told apart by identity (the same
    :class:`Sequence` object), never by path, so two in-memory sequences can never share entries.
    Thread-safe.

    Parameters
    ----------
    max_frames : int
        Frames (clouds) kept; each is a preprocessed cloud, typically 50-500 kB.
    max_pairs : int
        Registered pairs kept; each holds its cells' transforms and point indices.
    """

    def __init__(self, *, max_frames: int = 512, max_pairs: int = 1024):
        self.max_frames, self.max_pairs = max_frames, max_pairs
        self._frames: OrderedDict[tuple, tuple] = OrderedDict()
        self._pairs: OrderedDict[tuple, tuple] = OrderedDict()
        self._lock = threading.Lock()
        self._tokens: dict[int, int] = {}      # id(sequence) -> token, dropped when the sequence dies
        self._next_token = 0
        self.hits = {"frame": 0, "register": 0}
        self.misses = {"frame": 0, "register": 0}

    def sequence_token(self, sequence: Sequence) -> int:
        """A number that stands for ``sequence`` (this very object) in the keys."""
        with self._lock:
            key = id(sequence)
            if key not in self._tokens:
                self._tokens[key] = self._next_token
                self._next_token += 1
                weakref.finalize(sequence, self._forget, key)
            return self._tokens[key]

    def _forget(self, key: int) -> None:
        with self._lock:
            token = self._tokens.pop(key, None)
            if token is None:
                return
            for table in (self._frames, self._pairs):
                for k in [k for k in table if k[0] == token]:
                    del table[k]

    def _get(self, table: OrderedDict, key: tuple, stage: str):
        with self._lock:
            value = table.get(key)
            if value is None:
                self.misses[stage] += 1
            else:
                table.move_to_end(key)
                self.hits[stage] += 1
            return value

    def _put(self, table: OrderedDict, key: tuple, value, limit: int) -> None:
        with self._lock:
            table[key] = value
            table.move_to_end(key)
            while len(table) > limit:
                table.popitem(last=False)

    def clear(self) -> None:
        with self._lock:
            self._frames.clear()
            self._pairs.clear()

    def stats(self) -> dict[str, Any]:
        """Entries held and hits/misses per stage."""
        with self._lock:
            return dict(frames=len(self._frames), pairs=len(self._pairs), hits=dict(self.hits),
                        misses=dict(self.misses))


@dataclass(frozen=True)
class _RawFrame:
    """What segmentation and preprocessing gave for one frame, before the pipeline's own checks."""

    index: int
    name: str
    cloud: Cloud | None
    mask_pixels: int


@dataclass
class _Job:
    """A frame or pair computed (possibly in a worker thread), with its own stage timings."""

    value: Any
    timing: dict[str, float]


def _executor(workers: int):
    """Runs jobs on ``workers`` threads, or at once in the calling thread for one."""
    if not (isinstance(workers, int) and workers >= 1):
        raise ParamError(f"workers = {workers!r} must be a positive integer")
    return _Inline() if workers == 1 else ThreadPoolExecutor(workers, thread_name_prefix="artclass")


class _Inline:
    """The executor of ``workers=1``: runs each job at once, in the calling thread."""

    def submit(self, fn, *args) -> Future:
        fut: Future = Future()
        try:
            fut.set_result(fn(*args))
        except BaseException as exc:
            fut.set_exception(exc)
        return fut

    def shutdown(self, **_kw) -> None:
        pass


_PAIR_MEMOS: dict[tuple[int, int], tuple[weakref.ref, weakref.ref, dict]] = {}
_PAIR_MEMO_LOCK = threading.Lock()


def pair_memo(source: Cloud, target: Cloud) -> dict:
    """A dict that lives exactly as long as both clouds of a pair, for a decision rule's evidence.

    A rule whose work splits into evidence that its thresholds do not change (motion hypotheses, the
    residual of every point under each of them ...) and a cheap decision on that evidence can keep the
    evidence here: re-deciding the same pair under other thresholds (:meth:`Pipeline.redecide`, a
    :meth:`Pipeline.run` with a :class:`StageCache`, the app's sliders) hands the rule the very same
    cloud objects, so it finds its evidence again. Key the entries on everything the evidence depends
    on besides the two clouds, e.g. ``(params.max_points_per_cell, tuple((c.cell, id(c.registration))
    for c in cells if c.matched))`` (a cell's registration object stays the same while it is cached).
    In a streaming run the clouds, and so the memo, are dropped as soon as the pair is done.
    """
    key = (id(source), id(target))
    with _PAIR_MEMO_LOCK:
        entry = _PAIR_MEMOS.get(key)
        if entry is not None and entry[0]() is source and entry[1]() is target:
            return entry[2]
        try:
            refs = (weakref.ref(source), weakref.ref(target))
        except TypeError:              # objects that cannot be weakly referenced: a memo for this call only
            return {}
        memo: dict = {}
        _PAIR_MEMOS[key] = (*refs, memo)
    for cloud in (source, target):
        weakref.finalize(cloud, _drop_pair_memo, key, refs)
    return memo


def _drop_pair_memo(key: tuple[int, int], refs: tuple) -> None:
    with _PAIR_MEMO_LOCK:
        entry = _PAIR_MEMOS.get(key)
        if entry is not None and entry[0] is refs[0] and entry[1] is refs[1]:   # identity: Cloud.__eq__ compares arrays
            del _PAIR_MEMOS[key]


_HULLS: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def cloud_hull(cloud: Cloud) -> np.ndarray:
    """The hull vertices of ``cloud.points`` (:func:`~artclass_core.geometry.hull_vertices`), computed
    once per cloud and remembered while the cloud lives (recomputed if ``cloud.points`` is replaced)."""
    key = id(cloud)
    entry = _HULLS.get(key)
    if entry is not None and entry[0] is cloud.points:
        return entry[1]
    vertices = hull_vertices(cloud.points)
    if entry is None:
        try:
            weakref.finalize(cloud, _HULLS.pop, key, None)
        except TypeError:              # an object that cannot be weakly referenced: not remembered
            return vertices
    _HULLS[key] = (cloud.points, vertices)
    return vertices


class Pipeline:
    """The configured plugins, ready to run stage by stage or on a whole sequence."""

    def __init__(self, registry: Registry, config: Config | None = None):
        self.registry = registry
        self.config = _fitting(registry, config or Config())
        self.params = self.config.pipeline
        for kind in ("preprocessor", "registrar", "rule"):
            setattr(self, kind, registry.create(kind, getattr(self.config, kind),
                                                self.config.plugin_params(registry, kind)))
        if self.registrar.gives != self.rule.needs:
            raise ParamError(f"rule {self.rule.name!r} decides from {self.rule.needs}, but registrar "
                             f"{self.registrar.name!r} gives {self.registrar.gives}: choose a matching pair "
                             f"(artclass plugins lists them)")
        self._segmenters: dict[str, object] = {}
        self._lock = threading.Lock()

    # -- stage 1 and 2: one frame -> cloud -------------------------------------------------------
    def segmenter_name(self, sequence: Sequence) -> str:
        name = self.config.segmenter
        if name == AUTO_SEGMENTER:
            name = "mask" if sequence.has_masks else "depth_threshold"
        return name

    def segmenter(self, sequence: Sequence):
        name = self.segmenter_name(sequence)
        with self._lock:
            if name not in self._segmenters:
                self._segmenters[name] = self.registry.create(
                    "segmenter", name, self.config.plugin_params(self.registry, "segmenter", name))
            return self._segmenters[name]

    def frame(self, sequence: Sequence, i: int, *, timing: dict[str, float] | None = None,
              cache: StageCache | None = None) -> FrameResult:
        """Read, segment and preprocess frame ``i``. A frame with no object is returned as skipped.

        With a ``cache``, a frame already processed with the same segmenter and preprocessor (and
        params) is taken from it.
        """
        return self._finish_frame(self._raw_frame(sequence, i, timing if timing is not None else {}, cache))

    def frame_key(self, sequence: Sequence, i: int, cache: StageCache) -> tuple:
        """The cache key of frame ``i``: the sequence, the frame, the segmenter and the preprocessor."""
        seg = self.segmenter_name(sequence)
        return (cache.sequence_token(sequence), i, seg, self.config.plugin_params(self.registry, "segmenter", seg),
                self.config.preprocessor, self.config.plugin_params(self.registry, "preprocessor"))

    def _raw_frame(self, sequence: Sequence, i: int, timing: dict[str, float], cache: StageCache | None) -> _RawFrame:
        key = None
        if cache is not None:
            key = self.frame_key(sequence, i, cache)
            hit = cache._get(cache._frames, key, "frame")
            if hit is not None:
                return hit
        t0 = time.perf_counter()
        frame = sequence[i]
        t1 = time.perf_counter()
        mask = self.segmenter(sequence).segment(frame, sequence=sequence)
        t2 = time.perf_counter()
        _add(timing, "read", t1 - t0)
        _add(timing, "segment", t2 - t1)
        n_mask = 0 if mask is None else int(np.count_nonzero(mask))
        if n_mask == 0:
            raw = _RawFrame(i, frame.name, None, 0)
        else:
            cloud = self.preprocessor.process(frame, mask, intrinsics=sequence.intrinsics)
            _add(timing, "preprocess", time.perf_counter() - t2)
            raw = _RawFrame(i, frame.name, cloud, n_mask)
        if cache is not None:
            cache._put(cache._frames, key, raw, cache.max_frames)
        return raw

    def _finish_frame(self, raw: _RawFrame) -> FrameResult:
        if raw.cloud is None:
            return FrameResult(raw.index, raw.name, None, skipped="no object found")
        cloud = raw.cloud
        if len(cloud) < self.params.min_cell_points:
            return FrameResult(raw.index, raw.name, None, skipped=f"only {len(cloud)} object points",
                               mask_pixels=raw.mask_pixels, info=dict(cloud.info))
        return FrameResult(raw.index, raw.name, cloud, mask_pixels=raw.mask_pixels, info=dict(cloud.info))

    # -- stage 3: a pair of clouds -> per-cell registrations -----------------------------------
    def cell_size(self, source: Cloud, target: Cloud) -> float:
        """The cell size x: ``cell_size_m``, or 1/5 of the largest distance between points of the pair.

        The largest distance is taken over the two clouds' hull vertices (computed once per cloud),
        which gives exactly the diameter of the two clouds together.
        """
        if self.params.cell_size_m is not None:
            return self.params.cell_size_m
        return max(diameter_of_vertices(np.concatenate([cloud_hull(source), cloud_hull(target)])) / 5.0, 1e-4)

    def register(self, source: Cloud, target: Cloud) -> tuple[list[CellMotion] | MotionEvidence, float | None]:
        """Split both clouds over one grid of cells of size x and register each cell with ICP (or, with
        a pair registrar, its :class:`MotionEvidence` and no cell size).

        Cells with fewer than ``min_cell_points`` points in either cloud are not registered; cells
        without a correspondence or with a fitness below ``min_fitness`` are marked skipped.
        """
        cells, x = self._register_raw(source, target)
        return (cells, x) if isinstance(cells, MotionEvidence) else (self.checked_cells(cells), x)

    def prealign(self, source: Cloud, target: Cloud) -> np.ndarray:
        """Whole-cloud motion ``T_target_from_source`` found with the chosen registrar, coarse to fine,
        from the identity and from the centroid shift (the better fit wins); identity if disabled."""
        if not self.params.prealign:
            return np.eye(4)
        extent = float(np.linalg.norm(np.ptp(np.concatenate([source.points, target.points]), axis=0)))
        shift = np.eye(4)
        shift[:3, 3] = target.points.mean(0) - source.points.mean(0)
        best, best_key = np.eye(4), (-1.0, 0.0)
        for T in (np.eye(4), shift):
            for scale in (extent / 2.5, extent / 5, extent / 10):
                reg = self.registrar.register(
                    transform(source.points, T), target.points,
                    source_normals=None if source.normals is None else source.normals @ T[:3, :3].T,
                    target_normals=target.normals, cell_size_m=scale)
                T = reg.T_target_from_source @ T
            if (reg.fitness, -reg.rmse_m) > best_key:
                best, best_key = T, (reg.fitness, -reg.rmse_m)
        return best

    def _register_raw(self, source: Cloud, target: Cloud) -> tuple[tuple[CellMotion, ...] | MotionEvidence, float | None]:
        """Per-cell ICP, without the fitness check (which depends on ``min_fitness`` only), or the
        whole pair's :class:`MotionEvidence` from a pair registrar (then no cell size).

        With ``prealign`` the source is first moved by the whole-cloud motion, so each cell's ICP,
        which starts from the identity, only has to find the residual; the cell's transform is the
        composition, and its centre is given in the source frame.
        """
        if self.registrar.gives == "motions":
            return self.registrar.register_pair(source, target), None
        x = self.cell_size(source, target)
        p = self.params
        T0 = self.prealign(source, target)
        moved = transform(source.points, T0)
        normals = None if source.normals is None else source.normals @ T0[:3, :3].T
        T0_inv = np.linalg.inv(T0)
        cells = []
        for key, centre, si, ti in grid_cells(moved, target.points, cell_size_m=x):
            cell = CellMotion(key, transform(centre[None], T0_inv)[0], si, ti)
            if min(len(si), len(ti)) < p.min_cell_points:
                cell.skipped = f"too few points ({len(si)} source, {len(ti)} target)"
            else:
                reg = self.registrar.register(
                    moved[si], target.points[ti], source_normals=None if normals is None else normals[si],
                    target_normals=None if target.normals is None else target.normals[ti], cell_size_m=x)
                reg.T_target_from_source = reg.T_target_from_source @ T0
                cell.registration = reg
            cells.append(cell)
        return tuple(cells), x

    def checked_cells(self, cells: Iterable[CellMotion]) -> list[CellMotion]:
        """Copies of registered ``cells`` with the skip reasons of this pipeline's ``min_fitness``, and
        no cluster (a cell that was not registered keeps its reason)."""
        out = []
        for c in cells:
            reg, skipped = c.registration, c.skipped
            if reg is not None:
                skipped = ("no correspondence" if reg.n_correspondences == 0 else
                           f"low fitness {reg.fitness:.2f}" if reg.fitness < self.params.min_fitness else None)
            out.append(dataclasses.replace(c, skipped=skipped, cluster=None, key=None))
        return out

    # -- stage 4: registrations -> pair decision ----------------------------------------------
    def decide(self, i: int, j: int, cells: list[CellMotion], source: Cloud, target: Cloud,
               cell_size_m: float, between: Iterable[Cloud | None] = ()) -> PairResult:
        """Apply the alpha check and the decision rule to a registered pair.

        The cells are copied first (the returned pair holds the copies, with their clusters), so the
        same registered cells can be decided again, under another rule, without stale clusters.
        ``between`` are the clouds of frames i + 1 .. j - 1, for a rule that uses them
        (:attr:`DecisionRule.uses_frames_between`); it gets none when one of them is missing.
        """
        cells = [dataclasses.replace(c, cluster=None, key=None) for c in cells]
        pair = PairResult(i, j, "skipped", cells=cells, cell_size_m=cell_size_m)
        n_matched = sum(c.matched for c in cells)
        if not cells or n_matched == 0 or n_matched < self.params.alpha * len(cells):
            pair.reason = f"only {n_matched} of {len(cells)} cells matched (alpha = {self.params.alpha:g})"
            return pair
        between = tuple(between)
        extra = {"between": between} if self.rule.uses_frames_between and None not in between else {}
        out = self.rule.decide(cells, source=source, target=target, **extra)
        if len(out.clusters) != len(cells):
            raise ArtclassError(f"rule {self.rule.name!r} returned {len(out.clusters)} clusters for {len(cells)} cells")
        for c, k in zip(cells, out.clusters):
            c.cluster = k
            c.key = out.keys[k] if k is not None and k < len(out.keys) else None
        pair.decision, pair.reason, pair.info = out.decision, out.reason, out.info
        return pair

    def decide_motions(self, i: int, j: int, evidence: MotionEvidence) -> PairResult:
        """Apply the decision rule to a pair's motion evidence (from a pair registrar)."""
        out = self.rule.decide(evidence)
        return PairResult(i, j, out.decision, out.reason, info=out.info, motions=out.motions, labels=out.labels,
                          evidence=evidence)

    def pair(self, a: FrameResult, b: FrameResult, *, timing: dict[str, float] | None = None,
             between: Iterable[FrameResult] = ()) -> PairResult:
        """Register and decide the pair of two preprocessed frames (``between``: the frames between them)."""
        return self._pair(a, b, timing if timing is not None else {}, None, None, _clouds(between))

    def pair_key(self, sequence: Sequence, i: int, j: int, cache: StageCache) -> tuple:
        """The cache key of the registrations of pair (i, j): both frames' keys, the registrar and
        the grid (``cell_size_m``, ``min_cell_points``, ``prealign``)."""
        fi, fj = self.frame_key(sequence, i, cache), self.frame_key(sequence, j, cache)
        return (fi[0], fi[1:], fj[1:], self.config.registrar, self.config.plugin_params(self.registry, "registrar"),
                self.params.cell_size_m, self.params.min_cell_points, self.params.prealign)

    def _pair(self, a: FrameResult, b: FrameResult, timing: dict[str, float], cache: StageCache | None,
              key: tuple | None, between: tuple[Cloud | None, ...] = ()) -> PairResult:
        if a.cloud is None or b.cloud is None:
            skipped = a if a.cloud is None else b
            return PairResult(a.index, b.index, "skipped", reason=f"frame {skipped.index} skipped: {skipped.skipped}")
        t0 = time.perf_counter()
        hit = cache._get(cache._pairs, key, "register") if cache is not None and key is not None else None
        if hit is None:
            raw, x = self._register_raw(a.cloud, b.cloud)
            if cache is not None and key is not None:
                cache._put(cache._pairs, key, (raw, x), cache.max_pairs)
        else:
            raw, x = hit
        t1 = time.perf_counter()
        if isinstance(raw, MotionEvidence):
            pair = self.decide_motions(a.index, b.index, raw)
        else:
            pair = self.decide(a.index, b.index, self.checked_cells(raw), a.cloud, b.cloud, x, between)
        _add(timing, "register", t1 - t0)
        _add(timing, "decide", time.perf_counter() - t1)
        return pair

    def _frame_job(self, sequence: Sequence, i: int, cache: StageCache | None) -> _Job:
        timing: dict[str, float] = {}
        return _Job(self._raw_frame(sequence, i, timing, cache), timing)

    def _pair_job(self, a: FrameResult, b: FrameResult, cache: StageCache | None, key: tuple | None,
                  between: tuple[Cloud | None, ...]) -> _Job:
        timing: dict[str, float] = {}
        return _Job(self._pair(a, b, timing, cache, key, between), timing)

    # -- the whole sequence ---------------------------------------------------------------------
    def run(self, sequence: Sequence, *, progress: Progress | None = None, keep_clouds: bool = False,
            workers: int = 1, cache: StageCache | None = None) -> RunResult:
        """Classify a sequence. Streams: each frame is read and preprocessed once, and only the
        clouds of pending pairs are held.

        Parameters
        ----------
        sequence : the sequence
        progress : called as ``progress("pairs", done, total)`` as pairs complete, in order
        keep_clouds : keep every frame's cloud in the result (for display or :meth:`redecide`);
            otherwise a cloud is dropped as soon as the pairs that use it are done
        workers : threads that process frames and pairs; the result is identical for any number
        cache : a :class:`StageCache` to take clouds and registrations from and to fill

        Raises
        ------
        InputError
            when the sequence has fewer than k + 1 frames, or no frame holds an object.
        """
        k = self.params.k
        n = len(sequence)
        if n < k + 1:
            raise InputError(f"sequence has {n} frames; k = {k} needs at least {k + 1}", path=sequence.path)
        t_start = time.perf_counter()
        timing = {s: 0.0 for s in STAGES}
        frames: list[FrameResult] = []
        pairs: list[PairResult] = []
        pending: dict[int, FrameResult] = {}
        self.segmenter(sequence)                      # created once, before any worker asks for it
        executor = _executor(workers)
        ahead = 0 if workers == 1 else 2 * workers    # frames read ahead of the one being collected
        frame_jobs: dict[int, Future] = {}
        pair_jobs: deque[tuple[FrameResult, Future]] = deque()
        submitted = 0

        def collect(block: bool) -> None:
            while pair_jobs and (block or pair_jobs[0][1].done()):
                first, fut = pair_jobs.popleft()
                job = fut.result()
                _merge(timing, job.timing)
                pair = job.value
                pair.truth = sequence.pair_truth(pair.i, pair.j)
                pairs.append(pair)
                if not keep_clouds:
                    first.cloud = None
                    pair.evidence = None
                if progress:
                    progress("pairs", len(pairs), n - k)
                block = block and len(pair_jobs) > 2 * workers

        try:
            for j in range(n):
                while submitted < min(n, j + ahead + 1):
                    frame_jobs[submitted] = executor.submit(self._frame_job, sequence, submitted, cache)
                    submitted += 1
                job = frame_jobs.pop(j).result()
                _merge(timing, job.timing)
                fr = self._finish_frame(job.value)
                frames.append(fr)
                pending[j] = fr
                if j >= k:
                    first = pending.pop(j - k)
                    key = (self.pair_key(sequence, j - k, j, cache)
                           if cache is not None and first.cloud is not None and fr.cloud is not None else None)
                    between = _clouds(pending[m] for m in range(j - k + 1, j))
                    pair_jobs.append((first, executor.submit(self._pair_job, first, fr, cache, key, between)))
                collect(block=len(pair_jobs) > 2 * workers)
            while pair_jobs:
                collect(block=True)
        finally:
            executor.shutdown(wait=True, cancel_futures=True)
        if all(f.skipped for f in frames):
            reasons = Counter(f.skipped for f in frames).most_common(1)[0][0]
            raise InputError(f"no object in any of the {n} frames (segmenter "
                             f"{self.segmenter_name(sequence)!r}: {reasons})", path=sequence.path)
        if not keep_clouds:
            for f in frames:
                f.cloud = None
        timing["total"] = time.perf_counter() - t_start
        return self.summarise(sequence, frames, pairs, timing)

    def redecide(self, result: RunResult, *, sequence: Sequence | None = None,
                 cache: StageCache | None = None, workers: int = 1) -> RunResult:
        """Decide a finished run again under this pipeline's decision settings, reusing its registrations.

        The decision settings are the rule and its params, ``alpha``, ``min_fitness`` and ``w``; no
        frame is read and no ICP runs. The rule is given the pair's clouds: they come from
        ``result.frames`` (a run with ``keep_clouds=True``) or, failing that, from ``cache`` (the
        :class:`StageCache` the run used, with its ``sequence``). ``workers`` threads decide the pairs;
        the result is identical for any number.

        Raises
        ------
        ArtclassError
            when ``result`` was produced with other frame or registration settings (segmenter,
            preprocessor, registrar, their params, ``k``, ``cell_size_m``, ``min_cell_points``): run
            again instead (with the same cache, the clouds are reused), or when the clouds are missing.
        """
        t_start = time.perf_counter()
        self._check_same_registrations(result)
        executor = _executor(workers)
        clouds = {f.index: f.cloud for f in result.frames if f.cloud is not None}
        span = (lambda p: range(p.i, p.j + 1)) if self.rule.uses_frames_between else (lambda p: (p.i, p.j))
        skipped = {f.index for f in result.frames if f.skipped}     # as in the run, a pair goes without them
        needed = sorted({i for p in result.pairs if p.cells for i in span(p)} - clouds.keys() - skipped)
        if needed:
            if cache is None or sequence is None:
                raise ArtclassError(f"re-deciding needs the clouds of frames {needed[:5]}{'...' if len(needed) > 5 else ''}: "
                                    f"run with keep_clouds=True, or pass the run's StageCache and its sequence")
            for i in needed:
                clouds[i] = self.frame(sequence, i, cache=cache).cloud

        def again(p: PairResult) -> tuple[PairResult, float]:
            t0 = time.perf_counter()
            evidence = p.evidence
            if evidence is None and p.motions and cache is not None and sequence is not None:
                hit = cache._get(cache._pairs, self.pair_key(sequence, p.i, p.j, cache), "register")
                evidence = None if hit is None else hit[0]
            if evidence is not None:
                new = self.decide_motions(p.i, p.j, evidence)
                new.truth = p.truth
                return new, time.perf_counter() - t0
            if p.motions:
                raise ArtclassError(f"re-deciding pair {p.i}-{p.j} needs its motion evidence: run with "
                                    f"keep_clouds=True, or pass the run's StageCache and its sequence")
            if not p.cells:   # a frame of the pair was skipped: nothing was registered
                return dataclasses.replace(p), 0.0
            new = self.decide(p.i, p.j, self.checked_cells(p.cells), clouds[p.i], clouds[p.j], p.cell_size_m,
                              tuple(clouds.get(m) for m in range(p.i + 1, p.j)))
            new.truth = p.truth
            return new, time.perf_counter() - t0

        try:
            done = [f.result() for f in [executor.submit(again, p) for p in result.pairs]]
        finally:
            executor.shutdown(wait=True, cancel_futures=True)
        pairs = [p for p, _ in done]
        timing = {"decide": sum(seconds for _, seconds in done)}
        frames = [dataclasses.replace(f) for f in result.frames]
        timing["total"] = time.perf_counter() - t_start
        return self._summarise(dict(result.sequence), result.plugins["segmenter"], frames, pairs, timing)

    def _check_same_registrations(self, result: RunResult) -> None:
        mine = {kind: getattr(self.config, kind) for kind in ("segmenter", "preprocessor", "registrar")}
        if mine["segmenter"] == AUTO_SEGMENTER:
            mine["segmenter"] = result.plugins.get("segmenter")
        changed = [f"{kind} {result.plugins.get(kind)!r} -> {name!r}" for kind, name in mine.items()
                   if result.plugins.get(kind) != name]
        if not changed:
            for kind, name in mine.items():
                now = as_dict(self.config.plugin_params(self.registry, kind, name))
                before = result.params.get(kind, {})
                changed += [f"{kind} {n} {before.get(n)!r} -> {v!r}" for n, v in now.items() if before.get(n) != v]
        before = result.params.get("pipeline", {})
        changed += [f"{n} {before.get(n)!r} -> {getattr(self.params, n)!r}" for n in ("k", "cell_size_m", "min_cell_points", "prealign")
                    if before.get(n) != getattr(self.params, n)]
        if changed:
            raise ArtclassError("cannot re-decide: the registrations depend on settings that changed ("
                                + "; ".join(changed) + "); run the sequence again")

    def summarise(self, sequence: Sequence, frames: list[FrameResult], pairs: list[PairResult],
                  timing: dict[str, float]) -> RunResult:
        """Filter the pair decisions, label the sequence and record how it was obtained."""
        info = dict(name=sequence.name, path=str(sequence.path), object=sequence.object_name,
                    n_frames=len(sequence), truth=sequence.label)
        return self._summarise(info, self.segmenter_name(sequence), frames, pairs, timing)

    def _summarise(self, sequence_info: dict[str, Any], segmenter: str, frames: list[FrameResult],
                   pairs: list[PairResult], timing: dict[str, float]) -> RunResult:
        decided = [p.decision for p in pairs if p.decision != "skipped"]
        filtered = max_count_filter(decided, w=self.params.w)
        plugins = {kind: getattr(self.config, kind) for kind in PLUGIN_KINDS}
        plugins["segmenter"] = segmenter
        params = {"pipeline": as_dict(self.params)}
        for kind in PLUGIN_KINDS:
            params[kind] = as_dict(self.config.plugin_params(self.registry, kind, plugins[kind]))
        return RunResult(
            sequence=sequence_info, label=sequence_label(filtered), fractions=fractions(decided), pairs=pairs,
            filtered=filtered, frames=frames, params=params, plugins=plugins,
            timing_s={k: round(v, 4) for k, v in timing.items()}, version=_version())


def _fitting(registry: Registry, config: Config) -> Config:
    """``config`` with a default registrar or rule replaced, when the other was chosen and they do not
    fit: a rule that decides from cells gets the paper's per-cell ICP, a per-cell registrar the paper's
    rule. Anything chosen is kept (a misfit of two chosen plugins is an error)."""
    names = {kind: registry.names(kind) for kind in ("registrar", "rule")}
    if config.registrar not in names["registrar"] or config.rule not in names["rule"]:
        return config
    gives = registry.get("registrar", config.registrar).gives
    needs = registry.get("rule", config.rule).needs
    if gives == needs:
        return config
    if config.registrar == Config.registrar and CELL_REGISTRAR in names["registrar"] and needs == "cells":
        return dataclasses.replace(config, registrar=CELL_REGISTRAR, registrar_params=None)
    if config.rule == Config.rule and CELL_RULE in names["rule"] and gives == "cells":
        return dataclasses.replace(config, rule=CELL_RULE, rule_params=None)
    return config


def _clouds(frames: Iterable[FrameResult]) -> tuple[Cloud | None, ...]:
    return tuple(f.cloud for f in frames)


def max_count_filter(decisions: list[str], *, w: int) -> list[str]:
    """Moving max-count (mode) filter with a centred window of ``w`` decisions.

    A tie goes to the least severe of the tied (NM < RM < AM), so an isolated AM cannot win a tie,
    not even in the truncated windows at the ends of the sequence.
    """
    out = []
    before = (w - 1) // 2
    for t in range(len(decisions)):
        window = decisions[max(0, t - before): t - before + w]
        counts = Counter(window)
        top = max(counts.values())
        tied = [d for d in counts if counts[d] == top]
        out.append(min(tied, key=SEVERITY.__getitem__))
    return out


def sequence_label(filtered: Iterable[str]) -> str:
    """``articulated`` if any filtered decision is AM, else ``rigid`` if any is RM, else ``static``."""
    seen = set(filtered)
    return "articulated" if "AM" in seen else "rigid" if "RM" in seen else "static"


def fractions(decided: list[str]) -> dict[str, float]:
    """Share of the decided pairs in each class (the paper's per-sequence "probabilities")."""
    n = len(decided)
    return {d: (decided.count(d) / n if n else 0.0) for d in DECISIONS}


def _merge(timing: dict[str, float], more: dict[str, float]) -> None:
    for stage, seconds in more.items():
        _add(timing, stage, seconds)


def _add(timing: dict[str, float], stage: str, seconds: float) -> None:
    timing[stage] = timing.get(stage, 0.0) + seconds


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("artclass")
    except PackageNotFoundError:
        return "unknown"
