"""The pipeline: frames -> masks -> clouds -> pairs (i, i + k) -> per-cell registrations -> pair
decisions -> moving max-count filter -> sequence label.

Each stage is a method of :class:`Pipeline` that can be called on its own (the app caches them one by
one); :meth:`Pipeline.run` streams a whole sequence, holding only the k + 1 clouds that pending pairs
need, so memory does not grow with the sequence length.
"""

from __future__ import annotations

import dataclasses
import time
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from .errors import ArtclassError, InputError, ParamError
from .geometry import grid_cells, largest_distance
from .params import Params, PipelineParams, as_dict, describe, parse_value
from .plugins import Registry
from .types import DECISIONS, CellMotion, Cloud, FrameResult, PairResult, RunResult, Sequence

SEVERITY = {"NM": 0, "RM": 1, "AM": 2}
STAGES = ("read", "segment", "preprocess", "register", "decide")
PLUGIN_KINDS = ("segmenter", "preprocessor", "registrar", "rule")
AUTO_SEGMENTER = "auto"   # the sequence's own masks when it has them, else depth_threshold

Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class Config:
    """Which plugins run and with which parameters. Frozen and hashable: a safe cache key.

    A plugin's params left as ``None`` mean that plugin's defaults.
    """

    segmenter: str = AUTO_SEGMENTER
    preprocessor: str = "paper"
    registrar: str = "icp_point_to_point"
    rule: str = "paper"
    pipeline: PipelineParams = field(default_factory=PipelineParams)
    segmenter_params: Params | None = None
    preprocessor_params: Params | None = None
    registrar_params: Params | None = None
    rule_params: Params | None = None

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


class Pipeline:
    """The configured plugins, ready to run stage by stage or on a whole sequence."""

    def __init__(self, registry: Registry, config: Config | None = None):
        self.registry = registry
        self.config = config or Config()
        self.params = self.config.pipeline
        for kind in ("preprocessor", "registrar", "rule"):
            setattr(self, kind, registry.create(kind, getattr(self.config, kind),
                                                self.config.plugin_params(registry, kind)))
        self._segmenters: dict[str, object] = {}

    # -- stage 1 and 2: one frame -> cloud -------------------------------------------------------
    def segmenter_name(self, sequence: Sequence) -> str:
        name = self.config.segmenter
        if name == AUTO_SEGMENTER:
            name = "mask" if sequence.has_masks else "depth_threshold"
        return name

    def segmenter(self, sequence: Sequence):
        name = self.segmenter_name(sequence)
        if name not in self._segmenters:
            self._segmenters[name] = self.registry.create(
                "segmenter", name, self.config.plugin_params(self.registry, "segmenter", name))
        return self._segmenters[name]

    def frame(self, sequence: Sequence, i: int, *, timing: dict[str, float] | None = None) -> FrameResult:
        """Read, segment and preprocess frame ``i``. A frame with no object is returned as skipped."""
        timing = timing if timing is not None else {}
        t0 = time.perf_counter()
        frame = sequence[i]
        t1 = time.perf_counter()
        mask = self.segmenter(sequence).segment(frame, sequence=sequence)
        t2 = time.perf_counter()
        _add(timing, "read", t1 - t0)
        _add(timing, "segment", t2 - t1)
        n_mask = 0 if mask is None else int(np.count_nonzero(mask))
        if n_mask == 0:
            return FrameResult(i, frame.name, None, skipped="no object found")
        cloud = self.preprocessor.process(frame, mask, intrinsics=sequence.intrinsics)
        _add(timing, "preprocess", time.perf_counter() - t2)
        if len(cloud) < self.params.min_cell_points:
            return FrameResult(i, frame.name, None, skipped=f"only {len(cloud)} object points",
                               mask_pixels=n_mask, info=dict(cloud.info))
        return FrameResult(i, frame.name, cloud, mask_pixels=n_mask, info=dict(cloud.info))

    # -- stage 3: a pair of clouds -> per-cell registrations -----------------------------------
    def cell_size(self, source: Cloud, target: Cloud) -> float:
        if self.params.cell_size_m is not None:
            return self.params.cell_size_m
        return max(largest_distance(np.concatenate([source.points, target.points])) / 5.0, 1e-4)

    def register(self, source: Cloud, target: Cloud) -> tuple[list[CellMotion], float]:
        """Split both clouds over one grid of cells of size x and register each cell with ICP."""
        x = self.cell_size(source, target)
        p = self.params
        cells = []
        for key, centre, si, ti in grid_cells(source.points, target.points, cell_size_m=x):
            cell = CellMotion(key, centre, si, ti)
            if min(len(si), len(ti)) < p.min_cell_points:
                cell.skipped = f"too few points ({len(si)} source, {len(ti)} target)"
            else:
                reg = self.registrar.register(
                    source.points[si], target.points[ti],
                    source_normals=None if source.normals is None else source.normals[si],
                    target_normals=None if target.normals is None else target.normals[ti], cell_size_m=x)
                cell.registration = reg
                if reg.n_correspondences == 0:
                    cell.skipped = "no correspondence"
                elif reg.fitness < p.min_fitness:
                    cell.skipped = f"low fitness {reg.fitness:.2f}"
            cells.append(cell)
        return cells, x

    # -- stage 4: registrations -> pair decision ----------------------------------------------
    def decide(self, i: int, j: int, cells: list[CellMotion], source: Cloud, target: Cloud,
               cell_size_m: float) -> PairResult:
        """Apply the alpha check and the decision rule to a registered pair."""
        for c in cells:
            c.cluster = c.key = None
        pair = PairResult(i, j, "skipped", cells=cells, cell_size_m=cell_size_m)
        n_matched = sum(c.matched for c in cells)
        if not cells or n_matched == 0 or n_matched < self.params.alpha * len(cells):
            pair.reason = f"only {n_matched} of {len(cells)} cells matched (alpha = {self.params.alpha:g})"
            return pair
        out = self.rule.decide(cells, source=source, target=target)
        if len(out.clusters) != len(cells):
            raise ArtclassError(f"rule {self.rule.name!r} returned {len(out.clusters)} clusters for {len(cells)} cells")
        for c, k in zip(cells, out.clusters):
            c.cluster = k
            c.key = out.keys[k] if k is not None and k < len(out.keys) else None
        pair.decision, pair.reason, pair.info = out.decision, out.reason, out.info
        return pair

    def pair(self, a: FrameResult, b: FrameResult, *, timing: dict[str, float] | None = None) -> PairResult:
        """Register and decide the pair of two preprocessed frames."""
        timing = timing if timing is not None else {}
        if a.cloud is None or b.cloud is None:
            skipped = a if a.cloud is None else b
            return PairResult(a.index, b.index, "skipped", reason=f"frame {skipped.index} skipped: {skipped.skipped}")
        t0 = time.perf_counter()
        cells, x = self.register(a.cloud, b.cloud)
        t1 = time.perf_counter()
        pair = self.decide(a.index, b.index, cells, a.cloud, b.cloud, x)
        _add(timing, "register", t1 - t0)
        _add(timing, "decide", time.perf_counter() - t1)
        return pair

    # -- the whole sequence ---------------------------------------------------------------------
    def run(self, sequence: Sequence, *, progress: Progress | None = None, keep_clouds: bool = False) -> RunResult:
        """Classify a sequence. Streams: each frame is read and preprocessed once, and only the
        clouds of pending pairs are held.

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
        for j in range(n):
            fr = self.frame(sequence, j, timing=timing)
            frames.append(fr)
            pending[j] = fr
            if j >= k:
                first = pending.pop(j - k)
                pair = self.pair(first, fr, timing=timing)
                pair.truth = sequence.pair_truth(j - k, j)
                pairs.append(pair)
                if not keep_clouds:
                    first.cloud = None
                if progress:
                    progress("pairs", len(pairs), n - k)
        if all(f.skipped for f in frames):
            reasons = Counter(f.skipped for f in frames).most_common(1)[0][0]
            raise InputError(f"no object in any of the {n} frames (segmenter "
                             f"{self.segmenter_name(sequence)!r}: {reasons})", path=sequence.path)
        if not keep_clouds:
            for f in frames:
                f.cloud = None
        timing["total"] = time.perf_counter() - t_start
        return self.summarise(sequence, frames, pairs, timing)

    def summarise(self, sequence: Sequence, frames: list[FrameResult], pairs: list[PairResult],
                  timing: dict[str, float]) -> RunResult:
        """Filter the pair decisions, label the sequence and record how it was obtained."""
        decided = [p.decision for p in pairs if p.decision != "skipped"]
        filtered = max_count_filter(decided, w=self.params.w)
        plugins = {kind: getattr(self.config, kind) for kind in PLUGIN_KINDS}
        plugins["segmenter"] = self.segmenter_name(sequence)
        params = {"pipeline": as_dict(self.params)}
        for kind in PLUGIN_KINDS:
            params[kind] = as_dict(self.config.plugin_params(self.registry, kind, plugins[kind]))
        return RunResult(
            sequence=dict(name=sequence.name, path=str(sequence.path), object=sequence.object_name,
                          n_frames=len(sequence), truth=sequence.label),
            label=sequence_label(filtered), fractions=fractions(decided), pairs=pairs, filtered=filtered,
            frames=frames, params=params, plugins=plugins, timing_s={k: round(v, 4) for k, v in timing.items()},
            version=_version())


def max_count_filter(decisions: list[str], *, w: int) -> list[str]:
    """Moving max-count (mode) filter with a centred window of ``w`` decisions.

    A tie goes to the decision at the window's centre if it is among the tied, else to the least
    severe of the tied (NM < RM < AM), so an isolated AM cannot win a tie.
    """
    out = []
    before = (w - 1) // 2
    for t in range(len(decisions)):
        window = decisions[max(0, t - before): t - before + w]
        counts = Counter(window)
        top = max(counts.values())
        tied = [d for d in counts if counts[d] == top]
        out.append(decisions[t] if decisions[t] in tied else min(tied, key=SEVERITY.__getitem__))
    return out


def sequence_label(filtered: Iterable[str]) -> str:
    """``articulated`` if any filtered decision is AM, else ``rigid`` if any is RM, else ``static``."""
    seen = set(filtered)
    return "articulated" if "AM" in seen else "rigid" if "RM" in seen else "static"


def fractions(decided: list[str]) -> dict[str, float]:
    """Share of the decided pairs in each class (the paper's per-sequence "probabilities")."""
    n = len(decided)
    return {d: (decided.count(d) / n if n else 0.0) for d in DECISIONS}


def _add(timing: dict[str, float], stage: str, seconds: float) -> None:
    timing[stage] = timing.get(stage, 0.0) + seconds


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("artclass")
    except PackageNotFoundError:
        return "unknown"
