"""Deciding a finished run again under other decision settings, reusing its registrations: the
:meth:`~artclass_core.pipeline.Pipeline.redecide` step of the pipeline."""

from __future__ import annotations

import dataclasses
import time

from .cache import StageCache
from .config import AUTO_SEGMENTER, Config, depends_on
from .errors import ArtclassError
from .labels import chosen_pair
from .params import PipelineParams, as_dict
from .plugins import Registry
from .scheduler import each
from .types import FrameResult, PairResult, RunResult, Sequence


class RedecideSteps:
    """Decide a finished run again. Used by :class:`~artclass_core.pipeline.Pipeline`, which sets the
    attributes below and provides the frame and pair steps it calls."""

    registry: Registry
    config: Config
    params: PipelineParams

    def redecide(
        self,
        result: RunResult,
        *,
        sequence: Sequence | None = None,
        cache: StageCache | None = None,
        workers: int = 1,
    ) -> RunResult:
        """Decide ``result`` again under this pipeline's decision settings, reusing its registrations.

        The decision settings are what the ``decide`` stage depends on
        (:data:`~artclass_core.config.STAGE_DEPENDENCIES`) and ``w``; no frame is read and nothing is
        registered. The rule is given the pair's clouds, evidence and scratch: from ``result`` (a run with
        ``keep_clouds=True``) or, failing that, from ``cache`` (the :class:`StageCache` the run used, with
        its ``sequence``). ``workers`` threads decide the pairs; the result is identical for any number.

        Raises
        ------
        ArtclassError
            when ``result`` was produced with other registration settings (what the ``register`` stage
            depends on, or ``k``): run again instead (with the same cache, the clouds are reused), or when
            the clouds or evidence are missing.
        """
        t_start = time.perf_counter()
        self.check_same_registrations(result)
        clouds = {f.index: f.cloud for f in result.frames if f.cloud is not None}
        span = (lambda p: range(p.i, p.j + 1)) if self.rule.uses_frames_between else (lambda p: (p.i, p.j))
        skipped = {f.index for f in result.frames if f.skipped}  # as in the run, a pair goes without them
        needed = sorted({i for p in result.pairs if p.cells for i in span(p)} - clouds.keys() - skipped)
        cached = cache is not None and sequence is not None
        if needed and not cached:
            raise ArtclassError(
                f"re-deciding needs the clouds of frames {needed[:5]}{'...' if len(needed) > 5 else ''}: "
                f"run with keep_clouds=True, or pass the run's StageCache and its sequence"
            )
        for i in needed:
            clouds[i] = self.frame(sequence, i, cache=cache).cloud

        def decide(p: PairResult) -> PairResult:
            key = self.pair_key(sequence, p.i, p.j, cache) if cached and (p.cells or p.motions) else None
            scratch = p.scratch if key is None else cache.scratch(key)
            evidence = p.evidence
            if evidence is None and p.motions and key is not None:
                evidence = (cache.get("register", key) or (None,))[0]
            if p.motions and evidence is None:
                raise ArtclassError(
                    f"re-deciding pair {p.i}-{p.j} needs its motion evidence: run with "
                    f"keep_clouds=True, or pass the run's StageCache and its sequence"
                )
            if evidence is not None:
                new = self.decide_motions(p.i, p.j, evidence, scratch=scratch)
            elif not p.cells:  # a frame of the pair was skipped: nothing was registered
                return dataclasses.replace(p, other=None)
            else:
                new = self.decide(
                    p.i,
                    p.j,
                    self.checked_cells(p.cells),
                    clouds[p.i],
                    clouds[p.j],
                    p.cell_size_m,
                    tuple(clouds.get(m) for m in range(p.i + 1, p.j)),
                    scratch=scratch,
                )
            new.truth = p.truth
            return new

        k, far = self.params.k, self.params.k * self.params.slow_factor
        frames = {f.index: f for f in result.frames}

        def frame(m: int) -> FrameResult:
            if frames[m].cloud is not None or frames[m].skipped:
                return frames[m]
            if not cached:
                raise ArtclassError(
                    f"re-deciding needs the cloud of frame {m}: run with keep_clouds=True, or pass the "
                    f"run's StageCache and its sequence"
                )
            return self.frame(sequence, m, cache=cache)

        def again(p: PairResult) -> tuple[PairResult, float]:
            t0 = time.perf_counter()
            kept = {q.j - q.i: q for q in (p, p.other) if q is not None}

            def over(n: int) -> PairResult | None:
                """The pair (i, i + n): the run's, decided again, or registered now if the run did not
                need it."""
                if n in kept:
                    return decide(kept[n])
                if p.i + n not in frames:
                    return None
                between = tuple(frames[m] for m in range(p.i + 1, p.i + n))
                new = self.pair_of(sequence, frame(p.i), frame(p.i + n), between, {}, cache)
                new.truth = None if sequence is None else sequence.pair_truth(new.i, new.j)
                return new

            return chosen_pair(over, k=k, far=far), time.perf_counter() - t0

        done = each(again, result.pairs, workers)
        timing = {"decide": sum(seconds for _, seconds in done)}
        frames = [dataclasses.replace(f) for f in result.frames]
        timing["total"] = time.perf_counter() - t_start
        return self._summarise(
            dict(result.sequence), result.plugins["segmenter"], frames, [p for p, _ in done], timing
        )

    def check_same_registrations(self, result: RunResult) -> None:
        """Raise :class:`ArtclassError` naming each setting of the ``register`` stage (or ``k``) that
        differs between this pipeline and the one that produced ``result``."""
        deps = depends_on("register")
        changed = []
        for kind in deps.plugins:
            name = getattr(self.config, kind)
            if kind == "segmenter" and name == AUTO_SEGMENTER:
                name = result.plugins.get(kind)
            if result.plugins.get(kind) != name:
                changed.append(f"{kind} {result.plugins.get(kind)!r} -> {name!r}")
                continue
            before = result.params.get(kind, {})
            now = as_dict(self.config.plugin_params(self.registry, kind, name))
            changed += [
                f"{kind} {n} {before.get(n)!r} -> {v!r}" for n, v in now.items() if before.get(n) != v
            ]
        before = result.params.get("pipeline", {})
        changed += [
            f"{n} {before.get(n)!r} -> {getattr(self.params, n)!r}"
            for n in ("k", "slow_factor", *deps.params)
            if before.get(n) != getattr(self.params, n)
        ]
        if changed:
            raise ArtclassError(
                "cannot re-decide: the registrations depend on settings that changed ("
                + "; ".join(changed)
                + "); run the sequence again"
            )
