"""A whole-sequence run assembled from the pipeline's stage methods, so each stage can be cached.

:meth:`artclass_core.Pipeline.run` streams a sequence in one pass. The app instead calls the stages
one by one through caches (``frame`` -> ``register`` -> ``decide`` -> ``summarise``), so that moving
a decision slider re-decides without re-running ICP. This module holds that composition and the
*cache keys* of each stage; it has no Streamlit in it and no algorithm of its own: the result equals
``Pipeline.run`` on the same configuration (checked by ``tests/test_app.py``).
"""

from __future__ import annotations

import dataclasses
import time
from collections import Counter
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext

from artclass_core import (CellMotion, Cloud, Config, FrameResult, InputError, MotionEvidence, PairResult,
                           Pipeline, PipelineParams, RunResult, Sequence)

# Pipeline parameters a stage's output does NOT depend on. Everything else is part of the stage's
# key, so a parameter added to PipelineParams later invalidates every stage (safe, if slower).
# The register stage runs with min_fitness = 0 (no cell is skipped for low fitness); the fitness
# check is applied when deciding (:func:`decide_registered`), so moving min_fitness needs no ICP.
_NOT_FRAME = ("k", "w", "alpha", "cell_size_m", "min_fitness")
_NOT_REGISTER = ("k", "w", "alpha")
_NOT_DECIDE = ("k", "w")
_REGISTER_MIN_FITNESS = 0.0

Progress = Callable[[str, int, int], None]


def _reset(params: PipelineParams, names: tuple[str, ...]) -> PipelineParams:
    defaults = PipelineParams()
    return dataclasses.replace(params, **{n: getattr(defaults, n) for n in names if hasattr(params, n)})


def stage_config(config: Config, stage: str) -> Config:
    """The part of ``config`` the output of ``stage`` depends on; the rest is set to defaults.

    Parameters
    ----------
    config : the full configuration
    stage : ``"frame"`` (segment + preprocess one frame), ``"register"`` (one pair's cells) or
        ``"decide"`` (one pair's decision)

    Returns
    -------
    Config : frozen and hashable; ``repr`` of it is a stable cache key. Two configurations that
    differ only in what a stage ignores give the same key for that stage.
    """
    base = Config()
    keep = dict(segmenter=config.segmenter, segmenter_params=config.segmenter_params,
                preprocessor=config.preprocessor, preprocessor_params=config.preprocessor_params)
    if stage == "frame":
        return dataclasses.replace(base, **keep, pipeline=_reset(config.pipeline, _NOT_FRAME))
    keep.update(registrar=config.registrar, registrar_params=config.registrar_params)
    if stage == "register":
        pipeline = dataclasses.replace(_reset(config.pipeline, _NOT_REGISTER), min_fitness=_REGISTER_MIN_FITNESS)
        return dataclasses.replace(base, **keep, pipeline=pipeline)
    keep.update(rule=config.rule, rule_params=config.rule_params)
    if stage == "decide":
        return dataclasses.replace(base, **keep, pipeline=_reset(config.pipeline, _NOT_DECIDE))
    raise ValueError(f"unknown stage {stage!r}; expected frame, register or decide")


def decide_registered(pipeline: Pipeline, i: int, j: int, cells: list[CellMotion], source: Cloud, target: Cloud,
                      cell_size_m: float, between: tuple[Cloud | None, ...] = ()) -> PairResult:
    """Decide a pair registered by the ``register`` stage pipeline of :func:`stage_config`.

    That stage marks no cell as low-fitness; this applies ``pipeline``'s own fitness check
    (:meth:`Pipeline.checked_cells`, which copies the cells) and then :meth:`Pipeline.decide`. The
    result equals ``pipeline.decide`` on ``pipeline.register``'s cells. ``cells`` are not modified.
    """
    if isinstance(cells, MotionEvidence):      # a pair registrar's evidence: no cells, no fitness check
        return pipeline.decide_motions(i, j, cells)
    return pipeline.decide(i, j, pipeline.checked_cells(cells), source, target, cell_size_m, between)


def stage_key(config: Config, stage: str) -> str:
    """A string cache key of :func:`stage_config` (``repr`` names the Params classes, so two plugins
    whose params happen to have the same fields never share a key)."""
    return repr(stage_config(config, stage))


def run_staged(sequence: Sequence, config: Config, summary: Pipeline, *,
               frame: Callable[[int], FrameResult],
               register: Callable[[FrameResult, FrameResult], tuple[list[CellMotion], float]],
               decide: Callable[[FrameResult, FrameResult, list[CellMotion], float, tuple[FrameResult, ...]],
                                PairResult],
               progress: Progress | None = None, workers: int = 1) -> RunResult:
    """Classify ``sequence`` stage by stage through the given (cached) stage functions.

    Parameters
    ----------
    sequence : the sequence
    config : the configuration (its ``pipeline.k`` chooses the pairs (i, i + k))
    summary : a :class:`Pipeline` built on ``config``, used for :meth:`Pipeline.summarise`
    frame : ``i -> FrameResult`` with its cloud (``Pipeline.frame``)
    register : ``(frame_i, frame_j) -> (cells, x)`` (``Pipeline.register`` on the two clouds)
    decide : ``(frame_i, frame_j, cells, x, frames_between) -> PairResult`` (:func:`decide_registered` on
        the frames' clouds); it must not modify ``cells`` or the frames (neither does the core's),
        since the app hands out the very same cached objects on every re-run
    progress : called as ``progress(stage, done, total)`` for stages ``frames``, ``registration``
        and ``decision``, in the calling thread
    workers : threads that call the stage functions (frames, then pairs, are independent); the
        result is the same for any number

    Returns
    -------
    RunResult : as ``Pipeline.run`` gives it, except that the frames keep their clouds (the app
    shows them) and ``timing_s`` holds the wall time of each stage *including cache hits*.

    Raises
    ------
    InputError : fewer than k + 1 frames, or no object in any frame
    """
    k = config.pipeline.k
    n = len(sequence)
    if n < k + 1:
        raise InputError(f"sequence has {n} frames; k = {k} needs at least {k + 1}", path=sequence.path)
    t0 = time.perf_counter()
    frames: list[FrameResult] = _each(frame, range(n), workers, progress, "frames")
    if all(f.skipped for f in frames):
        reason = Counter(f.skipped for f in frames).most_common(1)[0][0]
        raise InputError(f"no object in any of the {n} frames (segmenter "
                         f"{summary.segmenter_name(sequence)!r}: {reason})", path=sequence.path)
    t1 = time.perf_counter()
    pairs = [(frames[i], frames[i + k]) for i in range(n - k)]

    def registration(pair: tuple[FrameResult, FrameResult]) -> tuple[list[CellMotion], float] | None:
        a, b = pair
        return None if a.cloud is None or b.cloud is None else register(a, b)

    registered = _each(registration, pairs, workers, progress, "registration")
    t2 = time.perf_counter()

    def decision(job: tuple[tuple[FrameResult, FrameResult], tuple[list[CellMotion], float] | None]) -> PairResult:
        (a, b), reg = job
        if reg is None:
            skipped = a if a.cloud is None else b
            pair = PairResult(a.index, b.index, "skipped", reason=f"frame {skipped.index} skipped: {skipped.skipped}")
        else:
            pair = decide(a, b, *reg, tuple(frames[a.index + 1:b.index]))
        pair.truth = sequence.pair_truth(a.index, b.index)
        return pair

    results = _each(decision, zip(pairs, registered), workers, progress, "decision")
    t3 = time.perf_counter()
    timing = dict(frames=t1 - t0, register=t2 - t1, decide=t3 - t2, total=t3 - t0)
    return summary.summarise(sequence, frames, results, timing)


def _each(fn: Callable, items: Iterable, workers: int, progress: Progress | None, stage: str) -> list:
    """``fn`` of each item, in order, on ``workers`` threads; ``progress`` in the calling thread."""
    items = list(items)
    out = []
    with ThreadPoolExecutor(workers) if workers > 1 else nullcontext() as executor:
        try:
            for done, result in enumerate(executor.map(fn, items) if executor else map(fn, items), 1):
                out.append(result)
                if progress:
                    progress(stage, done, len(items))
        except BaseException:
            if executor:                   # a bad frame: stop at once, not after every other one
                executor.shutdown(cancel_futures=True)
            raise
    return out
