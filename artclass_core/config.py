"""Which plugins run, with which parameters, and what each stage's result depends on.

:class:`Config` is frozen and hashable: a safe cache key. :data:`STAGE_DEPENDENCIES` says, once, which
plugins and pipeline parameters each stage reads; the stage cache's keys, :meth:`Pipeline.redecide`'s
check that a result's registrations still hold and the app's caches are all derived from it
(:func:`depends_on`, :func:`stage_config`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from .errors import ParamError
from .params import Params, PipelineParams, as_dict, describe, parse_value
from .plugins import Registry

PLUGIN_KINDS = ("segmenter", "preprocessor", "registrar", "rule")
AUTO_SEGMENTER = "auto"  # the sequence's own masks when it has them, else depth_threshold
CELL_REGISTRAR, CELL_RULE = "icp_point_to_point", "paper"  # the paper's, for a per-cell pipeline
PART_FINDER, JOINT_ESTIMATOR = "tracks", "bic"  # the parts stage after a run, and its joint fit


@dataclass(frozen=True)
class StageDependencies:
    """What one stage reads besides the output of the stage before it.

    Attributes
    ----------
    plugins : plugin kinds whose choice and params the stage's output depends on
    params : :class:`PipelineParams` fields the stage's output depends on
    """

    plugins: tuple[str, ...] = ()
    params: tuple[str, ...] = ()


#: The stages in order, each with what it reads of the configuration. A stage's result depends on its
#: own entries and on those of every stage before it. ``k`` (which frames pair up) and ``w`` (the
#: max-count filter) act after the stages, on whole sequences. ``min_cell_points`` also marks a frame
#: with too small a cloud as skipped, a check made after the cached frame stages.
STAGE_DEPENDENCIES: dict[str, StageDependencies] = {
    "read": StageDependencies(),
    "segment": StageDependencies(plugins=("segmenter",)),
    "preprocess": StageDependencies(plugins=("preprocessor",)),
    "register": StageDependencies(
        plugins=("registrar",), params=("cell_size_m", "min_cell_points", "prealign")
    ),
    "decide": StageDependencies(plugins=("rule",), params=("min_fitness", "alpha")),
}
STAGES = tuple(STAGE_DEPENDENCIES)


def depends_on(stage: str) -> StageDependencies:
    """Everything the output of ``stage`` depends on: its own entries and those of the stages before it."""
    if stage not in STAGE_DEPENDENCIES:
        raise ValueError(f"unknown stage {stage!r}; expected one of {', '.join(STAGES)}")
    upto = STAGES[: STAGES.index(stage) + 1]
    return StageDependencies(
        plugins=tuple(k for s in upto for k in STAGE_DEPENDENCIES[s].plugins),
        params=tuple(p for s in upto for p in STAGE_DEPENDENCIES[s].params),
    )


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
    def paper(cls) -> Config:
        """The paper's pipeline as written: Algorithm 1 at D/20 and 5v, per-cell ICP from the identity,
        Algorithm 2's quantise-and-hash rule."""
        return cls(
            preprocessor="paper",
            registrar=CELL_REGISTRAR,
            rule="paper",
            pipeline=PipelineParams(prealign=False, slow_factor=1, video_joints=False),
        )

    def plugin_params(self, registry: Registry, kind: str, name: str | None = None) -> Params:
        """The params of the chosen plugin of ``kind`` (its defaults when none were set)."""
        name = name or getattr(self, kind)
        params = getattr(self, f"{kind}_params")
        cls = registry.get(kind, name).Params
        return params if isinstance(params, cls) else cls()

    def record(
        self, registry: Registry, *, segmenter: str
    ) -> tuple[dict[str, str], dict[str, dict[str, Any]]]:
        """The plugin of each kind (with the ``segmenter`` that ran) and every parameter, as recorded
        with a result."""
        plugins = {kind: getattr(self, kind) for kind in PLUGIN_KINDS}
        plugins["segmenter"] = segmenter
        params = {"pipeline": as_dict(self.pipeline)}
        params.update(
            (kind, as_dict(self.plugin_params(registry, kind, plugins[kind]))) for kind in PLUGIN_KINDS
        )
        return plugins, params

    def with_overrides(self, registry: Registry, overrides: dict[str, str | float | int | None]) -> Config:
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
            hits = [
                (kind, spec)
                for kind, p in targets.items()
                for spec in describe(type(p))
                if key in (spec.name, spec.symbol)
            ]
            if not hits:
                known = sorted(
                    {n for p in targets.values() for s in describe(type(p)) for n in (s.name, s.symbol) if n}
                )
                raise ParamError(f"unknown parameter {key!r}; known: {', '.join(known)}")
            for kind, spec in hits:
                changes[kind][spec.name] = parse_value(spec, value) if isinstance(value, str) else value
        fields = {}
        for kind, p in targets.items():
            if changes[kind]:
                p = dataclasses.replace(p, **changes[kind])
            fields["pipeline" if kind == "pipeline" else f"{kind}_params"] = p
        return dataclasses.replace(self, **fields)


def stage_config(config: Config, stage: str) -> Config:
    """The part of ``config`` that the output of ``stage`` depends on (:func:`depends_on`); every
    other field at its default. Two configurations that differ only in what a stage ignores give equal
    (and equally hashable) stage configurations, e.g. for caching a pipeline per segmentation setting."""
    deps = depends_on(stage)
    base, defaults = Config(), PipelineParams()
    kept = {f: getattr(config, f) for kind in deps.plugins for f in (kind, f"{kind}_params")}
    pipeline = dataclasses.replace(defaults, **{p: getattr(config.pipeline, p) for p in deps.params})
    return dataclasses.replace(base, **kept, pipeline=pipeline)


def stage_dependencies(config: Config, registry: Registry, stage: str, *, segmenter: str) -> tuple:
    """What the output of ``stage`` depends on, as a hashable tuple (a cache key's part): a
    ``(kind, name, params)`` triple per plugin and a ``(name, value)`` pair per pipeline parameter of
    :func:`depends_on`; ``segmenter`` is the segmenter the sequence resolves to."""
    deps = depends_on(stage)
    names = {kind: segmenter if kind == "segmenter" else getattr(config, kind) for kind in deps.plugins}
    return (
        *((kind, name, config.plugin_params(registry, kind, name)) for kind, name in names.items()),
        *((p, getattr(config.pipeline, p)) for p in deps.params),
    )


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
