"""The pipeline: frames -> masks -> clouds -> pairs (i, i + k) -> registrations -> pair decisions ->
moving max-count filter -> the video's label (:mod:`~artclass_core.video`). A pair that shows no
motion is compared again over slow_factor k frames, one that no model explains over k/2 frames.

Each step is a method of :class:`Pipeline`; :meth:`Pipeline.run` streams a whole sequence, holding
only the clouds that pending pairs need. The pieces live in their own modules:
:mod:`~artclass_core.config` (what runs, and what each stage depends on), :mod:`~artclass_core.frames`
(steps 1 and 2), :mod:`~artclass_core.cells` (per-cell registration), :mod:`~artclass_core.cache`
(:class:`StageCache`: give one to successive runs to redo only what a changed setting touches),
:mod:`~artclass_core.scheduler` (worker threads) and :mod:`~artclass_core.labels` (filter and label).
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Iterable
from functools import partial

from . import cells as _cells
from .cache import StageCache
from .config import PART_FINDER, STAGES, Config, _fitting
from .errors import InputError, ParamError
from .frames import FrameSteps
from .labels import chosen_pair, fractions, labelled_result, max_count_filter, sequence_label
from .plugins import Registry
from .redecide import RedecideSteps
from .scheduler import Progress, add_time, single_threaded_open3d, stream_pairs
from .types import CellMotion, Cloud, FrameResult, MotionEvidence, PairResult, RunResult, Sequence
from .video import joints_over_video

__all__ = ["Config", "Pipeline", "StageCache", "fractions", "max_count_filter", "sequence_label"]


class Pipeline(FrameSteps, RedecideSteps):
    """The configured plugins, ready to run step by step or on a whole sequence (steps 1 and 2, one
    frame to its cloud, are :class:`~artclass_core.frames.FrameSteps`; deciding a finished run again
    is :class:`~artclass_core.redecide.RedecideSteps`)."""

    def __init__(self, registry: Registry, config: Config | None = None, *, segmenters: dict | None = None):
        """``segmenters``: segmenters by name, shared with pipelines of the same segmentation settings."""
        single_threaded_open3d()
        self.registry = registry
        self.config = _fitting(registry, config or Config())
        self.params = self.config.pipeline
        for kind in ("preprocessor", "registrar", "rule"):
            plugin = registry.create(
                kind, getattr(self.config, kind), self.config.plugin_params(registry, kind)
            )
            setattr(self, kind, plugin)
        if self.registrar.gives != self.rule.needs:
            raise ParamError(
                f"rule {self.rule.name!r} decides from {self.rule.needs}, but registrar "
                f"{self.registrar.name!r} gives {self.registrar.gives}: choose a matching pair "
                f"(artclass plugins lists them)"
            )
        self._segmenters: dict[str, object] = {} if segmenters is None else segmenters
        self._lock = threading.Lock()

    # -- the whole sequence ---------------------------------------------------------------------
    def run(
        self,
        sequence: Sequence,
        *,
        progress: Progress | None = None,
        keep_clouds: bool = False,
        workers: int = 1,
        cache: StageCache | None = None,
    ) -> RunResult:
        """Classify a sequence: read, segment and preprocess each frame once; register and decide each
        pair (i, i + k), and again over slow_factor k frames when it shows no motion; filter the
        decisions and label the sequence.

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
            for p in (pair, pair.other) if pair.other else (pair,):
                p.truth = sequence.pair_truth(p.i, p.j)
            if not keep_clouds:
                pair.release()
            pairs.append(pair)
            if not keep_clouds:
                first.cloud = None
            if progress:
                progress("pairs", len(pairs), n - k)

        frames = stream_pairs(
            n,
            k,
            workers=workers,
            timing=timing,
            done=done,
            frame=lambda i, t: self._raw_frame(sequence, i, t, cache),  # steps 1, 2
            finish=self._finish_frame,
            pair=lambda a, after, t: self.pair_for(sequence, a, after, t, cache),
            reach=k * self.params.slow_factor,
        )  # 3, 4
        if all(f.skipped for f in frames):
            reason = Counter(f.skipped for f in frames).most_common(1)[0][0]
            raise InputError(
                f"no object in any of the {n} frames (segmenter {self.segmenter_name(sequence)!r}: {reason})",
                path=sequence.path,
            )
        if not keep_clouds:
            for f in frames:
                f.cloud = None
        timing["total"] = time.perf_counter() - t_start
        return self.summarise(sequence, frames, pairs, timing)

    # -- step 3: a pair of clouds -> registrations -----------------------------------------------
    def cell_size(self, source: Cloud, target: Cloud) -> float:
        """The cell size x (m) of the pair (:func:`artclass_core.cells.cell_size`)."""
        return _cells.cell_size(source, target, cell_size_m=self.params.cell_size_m)

    def register(
        self, source: Cloud, target: Cloud
    ) -> tuple[list[CellMotion] | MotionEvidence, float | None]:
        """The pair's cells registered on one grid of size x, with the fitness check applied, and x; or a
        pair registrar's :class:`MotionEvidence` and no cell size."""
        cells, x = self._register_raw(source, target)
        return (cells, x) if isinstance(cells, MotionEvidence) else (self.checked_cells(cells), x)

    def _register_raw(
        self, source: Cloud, target: Cloud
    ) -> tuple[tuple[CellMotion, ...] | MotionEvidence, float | None]:
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
    def decide(
        self,
        i: int,
        j: int,
        cells: list[CellMotion],
        source: Cloud,
        target: Cloud,
        cell_size_m: float,
        between: Iterable[Cloud | None] = (),
        *,
        scratch: dict | None = None,
    ) -> PairResult:
        """Apply the alpha check and the decision rule to a registered pair.

        The cells are copied first (the returned pair holds the copies, with their clusters), so the
        same registered cells can be decided again, under another rule, without stale clusters.
        ``between`` are the clouds of frames i + 1 .. j - 1, for a rule that uses them
        (:attr:`DecisionRule.uses_frames_between`); it gets none when one of them is missing.
        ``scratch`` is the pair's scratch dict, for a rule that keeps evidence in it.
        """
        return _cells.decide_cells(
            self.rule,
            i,
            j,
            cells,
            source,
            target,
            cell_size_m,
            tuple(between),
            alpha=self.params.alpha,
            scratch={} if scratch is None else scratch,
        )

    def decide_motions(
        self, i: int, j: int, evidence: MotionEvidence, *, scratch: dict | None = None
    ) -> PairResult:
        """Apply the decision rule to a pair's motion evidence (from a pair registrar)."""
        scratch = {} if scratch is None else scratch
        out = self.rule.decide(evidence, **_cells.scratch_kwargs(self.rule, scratch))
        return PairResult(
            i,
            j,
            out.decision,
            out.reason,
            info=out.info,
            motions=out.motions,
            labels=out.labels,
            evidence=evidence,
            scratch=scratch,
        )

    def pair_for(
        self,
        sequence: Sequence,
        a: FrameResult,
        after: tuple[FrameResult, ...],
        timing: dict[str, float],
        cache: StageCache | None = None,
    ) -> PairResult:
        """The pair (i, i + k) of frame ``a`` (frame i), given the frames ``after`` it; or, when that pair
        shows no motion and the frames reach, the pair (i, i + slow_factor k) if it shows one; or, when
        no model explains it, the pair (i, i + k/2) if one does."""
        k, far = self.params.k, self.params.k * self.params.slow_factor

        def over(n: int) -> PairResult | None:
            if len(after) < n:
                return None
            return self.pair_of(sequence, a, after[n - 1], after[: n - 1], timing, cache)

        return chosen_pair(over, k=k, far=far)

    def pair_of(
        self,
        sequence: Sequence,
        a: FrameResult,
        b: FrameResult,
        between: tuple[FrameResult, ...],
        timing: dict[str, float],
        cache: StageCache | None,
    ) -> PairResult:
        """Register (or take from ``cache``) and decide the pair of two frames ``a`` and ``b`` of
        ``sequence`` (frame results with their clouds; ``between`` are the frames in between, for a
        rule that uses them), adding the stages' seconds to ``timing``."""
        if a.cloud is None or b.cloud is None:
            skipped = a if a.cloud is None else b
            return PairResult(
                a.index, b.index, "skipped", reason=f"frame {skipped.index} skipped: {skipped.skipped}"
            )
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
            pair = self.decide(
                a.index,
                b.index,
                self.checked_cells(raw),
                a.cloud,
                b.cloud,
                x,
                tuple(f.cloud for f in between),
                scratch=scratch,
            )
        add_time(timing, "register", t1 - t0)
        add_time(timing, "decide", time.perf_counter() - t1)
        return pair

    # -- steps 5 and 6: max-count filter and label -------------------------------------------------
    def summarise(
        self, sequence: Sequence, frames: list[FrameResult], pairs: list[PairResult], timing: dict[str, float]
    ) -> RunResult:
        """Filter the pair decisions, label the sequence and record how it was obtained."""
        info = dict(
            name=sequence.name,
            path=str(sequence.path),
            object=sequence.object_name,
            n_frames=len(frames),
            truth=sequence.label,
        )
        return self._summarise(info, self.segmenter_name(sequence), frames, pairs, timing)

    def _summarise(self, info: dict, segmenter: str, frames: list, pairs: list, timing: dict) -> RunResult:
        plugins, params = self.config.record(self.registry, segmenter=segmenter)
        finder = self.registry.create("part_finder", PART_FINDER)
        joints = self.params.video_joints and finder.works_on(self.rule)
        confirm = partial(joints_over_video, self.registry) if joints else None
        record = dict(params=params, plugins=plugins, timing=timing, confirm=confirm)
        return labelled_result(info, frames, pairs, w=self.params.w, **record)
