"""The pipeline: frames -> masks -> clouds -> pairs (i, i + k) -> registrations -> pair decisions ->
moving max-count filter -> sequence label.

Each step is a method of :class:`Pipeline`; :meth:`Pipeline.run` streams a whole sequence, holding
only the clouds that pending pairs need. The pieces live in their own modules: :mod:`~artclass_core.config` (what runs, and
what each stage depends on: :data:`~artclass_core.config.STAGE_DEPENDENCIES`),
:mod:`~artclass_core.cache` (:class:`StageCache`), :mod:`~artclass_core.cells` (per-cell registration),
:mod:`~artclass_core.scheduler` (worker threads) and :mod:`~artclass_core.labels` (filter and label).

Incremental re-runs
-------------------
A :class:`StageCache` keeps each frame's cloud and each pair's registrations, keyed on exactly what
they depend on; pass the same cache to successive runs, and a change of a decision setting (rule,
``alpha``, ``min_fitness``, ``w``) only re-decides::

    cache = StageCache()
    result = Pipeline(registry, config).run(sequence, cache=cache)            # reads, segments, registers
    config2 = dataclasses.replace(config, rule_params=RuleParams(q_bar=0.2))
    result2 = Pipeline(registry, config2).run(sequence, cache=cache)          # decides only
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from . import cells as _cells
from .cache import StageCache
from .config import AUTO_SEGMENTER, PLUGIN_KINDS, STAGES, Config, _fitting, stage_config, stage_dependencies
from .errors import ArtclassError, InputError, ParamError
from .labels import SEVERITY, fractions, labelled_result, max_count_filter, sequence_label
from .params import as_dict
from .plugins import Registry
from .scheduler import Progress, add_time, merge_timing, single_threaded_open3d, stream_pairs
from .types import CellMotion, Cloud, FrameResult, MotionEvidence, PairResult, RunResult, Sequence

__all__ = ["AUTO_SEGMENTER", "PLUGIN_KINDS", "SEVERITY", "STAGES", "Config", "Pipeline", "Progress", "StageCache",
           "fractions", "max_count_filter", "sequence_label", "stage_config"]


@dataclass(frozen=True)
class _RawFrame:
    """What segmentation and preprocessing gave for one frame, before the pipeline's own checks."""

    index: int
    name: str
    cloud: Cloud | None
    mask_pixels: int


class Pipeline:
    """The configured plugins, ready to run step by step or on a whole sequence."""

    def __init__(self, registry: Registry, config: Config | None = None, *, segmenters: dict | None = None):
        """``segmenters``: segmenters by name, shared with pipelines of the same segmentation settings."""
        single_threaded_open3d()
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
        self._segmenters: dict[str, object] = {} if segmenters is None else segmenters
        self._lock = threading.Lock()

    # -- the whole sequence ---------------------------------------------------------------------
    def run(self, sequence: Sequence, *, progress: Progress | None = None, keep_clouds: bool = False,
            workers: int = 1, cache: StageCache | None = None) -> RunResult:
        """Classify a sequence: read, segment and preprocess each frame once; register and decide each
        pair (i, i + k); filter the decisions and label the sequence.

        Parameters
        ----------
        sequence : the sequence
        progress : called as ``progress("pairs", done, total)`` as pairs complete, in order
        keep_clouds : keep every frame's cloud (and each pair's evidence) in the result, for display or
            :meth:`redecide`; otherwise a cloud is dropped as soon as the pairs that use it are done
        workers : threads that process frames and pairs; the result is identical for any number
        cache : a :class:`StageCache` to take clouds and registrations from and to fill

        Raises
        ------
        InputError
            when the sequence has fewer than k + 1 frames, or no frame holds an object.
        """
        k, n = self.params.k, len(sequence)
        if n < k + 1:
            raise InputError(f"sequence has {n} frames; k = {k} needs at least {k + 1}", path=sequence.path)
        t_start = time.perf_counter()
        timing = {s: 0.0 for s in STAGES}
        pairs: list[PairResult] = []

        def done(first: FrameResult, pair: PairResult) -> None:
            pair.truth = sequence.pair_truth(pair.i, pair.j)
            pairs.append(pair)
            if not keep_clouds:
                first.cloud, pair.evidence, pair.scratch = None, None, {}
            if progress:
                progress("pairs", len(pairs), n - k)

        frames = stream_pairs(n, k, workers=workers, timing=timing, done=done,
                              frame=lambda i, t: self._raw_frame(sequence, i, t, cache),      # steps 1, 2
                              finish=self._finish_frame,
                              pair=lambda a, b, between, t: self._pair(sequence, a, b, between, t, cache))  # 3, 4
        if all(f.skipped for f in frames):
            reason = Counter(f.skipped for f in frames).most_common(1)[0][0]
            raise InputError(f"no object in any of the {n} frames (segmenter "
                             f"{self.segmenter_name(sequence)!r}: {reason})", path=sequence.path)
        if not keep_clouds:
            for f in frames:
                f.cloud = None
        timing["total"] = time.perf_counter() - t_start
        return self.summarise(sequence, frames, pairs, timing)

    # -- steps 1 and 2: one frame -> cloud -------------------------------------------------------
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
        """Read, segment and preprocess frame ``i`` (taken from ``cache`` when it holds it). A frame with
        no object is returned as skipped."""
        return self._finish_frame(self._raw_frame(sequence, i, timing if timing is not None else {}, cache))

    def frame_key(self, sequence: Sequence, i: int, cache: StageCache) -> tuple:
        """The cache key of frame ``i``: the sequence, the frame and what the ``preprocess`` stage depends on."""
        return (cache.sequence_token(sequence), i, *self.depends(sequence, "preprocess"))

    def depends(self, sequence: Sequence, stage: str) -> tuple:
        """What the output of ``stage`` on ``sequence`` depends on (:func:`~artclass_core.config.stage_dependencies`)."""
        return stage_dependencies(self.config, self.registry, stage, segmenter=self.segmenter_name(sequence))

    def _raw_frame(self, sequence: Sequence, i: int, timing: dict[str, float], cache: StageCache | None) -> _RawFrame:
        key = None if cache is None else self.frame_key(sequence, i, cache)
        if (hit := None if key is None else cache.get("frame", key)) is not None:
            return hit
        t0 = time.perf_counter()
        frame = sequence[i]
        t1 = time.perf_counter()
        mask = self.segmenter(sequence).segment(frame, sequence=sequence)
        t2 = time.perf_counter()
        merge_timing(timing, {"read": t1 - t0, "segment": t2 - t1})
        n_mask = 0 if mask is None else int(np.count_nonzero(mask))
        raw = _RawFrame(i, frame.name, None, 0)
        if n_mask:
            raw = _RawFrame(i, frame.name, self.preprocessor.process(frame, mask, intrinsics=sequence.intrinsics), n_mask)
            add_time(timing, "preprocess", time.perf_counter() - t2)
        if key is not None:
            cache.put("frame", key, raw)
        return raw

    def _finish_frame(self, raw: _RawFrame) -> FrameResult:
        if raw.cloud is None:
            return FrameResult(raw.index, raw.name, None, skipped="no object found")
        cloud = raw.cloud
        if len(cloud) < self.params.min_cell_points:
            return FrameResult(raw.index, raw.name, None, skipped=f"only {len(cloud)} object points",
                               mask_pixels=raw.mask_pixels, info=dict(cloud.info))
        return FrameResult(raw.index, raw.name, cloud, mask_pixels=raw.mask_pixels, info=dict(cloud.info))

    # -- step 3: a pair of clouds -> registrations -----------------------------------------------
    def cell_size(self, source: Cloud, target: Cloud) -> float:
        """The cell size x (m) of the pair (:func:`artclass_core.cells.cell_size`)."""
        return _cells.cell_size(source, target, cell_size_m=self.params.cell_size_m)

    def register(self, source: Cloud, target: Cloud) -> tuple[list[CellMotion] | MotionEvidence, float | None]:
        """The pair's cells registered on one grid of size x, with the fitness check applied, and x; or a
        pair registrar's :class:`MotionEvidence` and no cell size."""
        cells, x = self._register_raw(source, target)
        return (cells, x) if isinstance(cells, MotionEvidence) else (self.checked_cells(cells), x)

    def _register_raw(self, source: Cloud, target: Cloud) -> tuple[tuple[CellMotion, ...] | MotionEvidence, float | None]:
        """:meth:`register` without the fitness check (which depends on ``min_fitness`` only)."""
        if self.registrar.gives == "motions":
            return self.registrar.register_pair(source, target), None
        return _cells.register_cells(source, target, self.registrar, params=self.params)

    def checked_cells(self, cells: Iterable[CellMotion]) -> list[CellMotion]:
        """Copies of ``cells`` checked against ``min_fitness`` (:func:`artclass_core.cells.checked_cells`)."""
        return _cells.checked_cells(cells, min_fitness=self.params.min_fitness)

    def pair_key(self, sequence: Sequence, i: int, j: int, cache: StageCache) -> tuple:
        """The cache key of the registrations of pair (i, j): the sequence, the frames and what the
        ``register`` stage depends on."""
        return (cache.sequence_token(sequence), i, j, *self.depends(sequence, "register"))

    # -- step 4: registrations -> pair decision ---------------------------------------------------
    def decide(self, i: int, j: int, cells: list[CellMotion], source: Cloud, target: Cloud,
               cell_size_m: float, between: Iterable[Cloud | None] = (), *, scratch: dict | None = None) -> PairResult:
        """Apply the alpha check and the decision rule to a registered pair.

        The cells are copied first (the returned pair holds the copies, with their clusters), so the
        same registered cells can be decided again, under another rule, without stale clusters.
        ``between`` are the clouds of frames i + 1 .. j - 1, for a rule that uses them
        (:attr:`DecisionRule.uses_frames_between`); it gets none when one of them is missing.
        ``scratch`` is the pair's scratch dict, for a rule that keeps evidence in it.
        """
        scratch = {} if scratch is None else scratch
        cells = [dataclasses.replace(c, cluster=None, key=None) for c in cells]
        pair = PairResult(i, j, "skipped", cells=cells, cell_size_m=cell_size_m, scratch=scratch)
        n_matched = sum(c.matched for c in cells)
        if not cells or n_matched == 0 or n_matched < self.params.alpha * len(cells):
            pair.reason = f"only {n_matched} of {len(cells)} cells matched (alpha = {self.params.alpha:g})"
            return pair
        between = tuple(between)
        extra = {"between": between} if self.rule.uses_frames_between and None not in between else {}
        out = self.rule.decide(cells, source=source, target=target, **extra, **self._scratch_arg(scratch))
        if len(out.clusters) != len(cells):
            raise ArtclassError(f"rule {self.rule.name!r} returned {len(out.clusters)} clusters for {len(cells)} cells")
        for c, k in zip(cells, out.clusters):
            c.cluster = k
            c.key = out.keys[k] if k is not None and k < len(out.keys) else None
        pair.decision, pair.reason, pair.info = out.decision, out.reason, out.info
        return pair

    def decide_motions(self, i: int, j: int, evidence: MotionEvidence, *, scratch: dict | None = None) -> PairResult:
        """Apply the decision rule to a pair's motion evidence (from a pair registrar)."""
        scratch = {} if scratch is None else scratch
        out = self.rule.decide(evidence, **self._scratch_arg(scratch))
        return PairResult(i, j, out.decision, out.reason, info=out.info, motions=out.motions, labels=out.labels,
                          evidence=evidence, scratch=scratch)

    def _scratch_arg(self, scratch: dict) -> dict[str, dict]:
        return {"scratch": scratch} if getattr(self.rule, "uses_scratch", False) else {}

    def _pair(self, sequence: Sequence, a: FrameResult, b: FrameResult, between: tuple[FrameResult, ...],
              timing: dict[str, float], cache: StageCache | None) -> PairResult:
        """Register (or take from ``cache``) and decide the pair of two frames."""
        if a.cloud is None or b.cloud is None:
            skipped = a if a.cloud is None else b
            return PairResult(a.index, b.index, "skipped", reason=f"frame {skipped.index} skipped: {skipped.skipped}")
        t0 = time.perf_counter()
        key = None if cache is None else self.pair_key(sequence, a.index, b.index, cache)
        if (hit := None if key is None else cache.get("register", key)) is None:
            hit = self._register_raw(a.cloud, b.cloud)
            if key is not None:
                cache.put("register", key, hit)
        raw, x = hit
        scratch = {} if key is None else cache.scratch(key)
        t1 = time.perf_counter()
        if isinstance(raw, MotionEvidence):
            pair = self.decide_motions(a.index, b.index, raw, scratch=scratch)
        else:
            pair = self.decide(a.index, b.index, self.checked_cells(raw), a.cloud, b.cloud, x,
                               tuple(f.cloud for f in between), scratch=scratch)
        add_time(timing, "register", t1 - t0)
        add_time(timing, "decide", time.perf_counter() - t1)
        return pair

    # -- re-deciding a finished run ---------------------------------------------------------------
    def redecide(self, result: RunResult, *, sequence: Sequence | None = None,
                 cache: StageCache | None = None, workers: int = 1) -> RunResult:
        """Decide a finished run again under this pipeline's decision settings, reusing its registrations
        (:func:`artclass_core.redecide.redecide`, which documents the parameters and errors)."""
        from .redecide import redecide

        return redecide(self, result, sequence=sequence, cache=cache, workers=workers)

    # -- steps 5 and 6: max-count filter and label -------------------------------------------------
    def summarise(self, sequence: Sequence, frames: list[FrameResult], pairs: list[PairResult],
                  timing: dict[str, float]) -> RunResult:
        """Filter the pair decisions, label the sequence and record how it was obtained."""
        info = dict(name=sequence.name, path=str(sequence.path), object=sequence.object_name,
                    n_frames=len(sequence), truth=sequence.label)
        return self._summarise(info, self.segmenter_name(sequence), frames, pairs, timing)

    def _summarise(self, sequence_info: dict[str, Any], segmenter: str, frames: list[FrameResult],
                   pairs: list[PairResult], timing: dict[str, float]) -> RunResult:
        plugins = {kind: getattr(self.config, kind) for kind in PLUGIN_KINDS}
        plugins["segmenter"] = segmenter
        params = {"pipeline": as_dict(self.params)}
        params.update((kind, as_dict(self.config.plugin_params(self.registry, kind, plugins[kind])))
                      for kind in PLUGIN_KINDS)
        return labelled_result(sequence_info, frames, pairs, w=self.params.w, params=params, plugins=plugins,
                               timing=timing)
