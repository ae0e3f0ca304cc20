"""The app's caches and shared sidebar: plugin registry, sequences, the stage cache, configuration.

The app runs a sequence exactly as the command line does, with :meth:`artclass_core.Pipeline.run`, through
one :class:`artclass_core.StageCache` held for the server's lifetime (``st.cache_resource``). The cache
keeps every frame's cloud and every pair's registrations keyed on what they depend on
(:data:`artclass_core.config.STAGE_DEPENDENCIES`), so a slider only re-runs what depends on it:
a decision parameter (q̄, t̄, α, min_fitness, the rule's own) re-decides without registering; x or a
registrar parameter re-registers without re-segmenting; k re-uses every frame; w only re-filters.
Pipelines are cached per configuration, and share their segmenters (e.g. ONNX sessions, and the hand
masks the page shows) per segmentation setting.
"""

from __future__ import annotations

import os
import statistics
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import streamlit as st

from artclass_core import (
    ArtclassError,
    Config,
    InputError,
    Pipeline,
    PipelineParams,
    Registry,
    RunResult,
    Sequence,
    StageCache,
    describe,
    find_sequences,
    load_registry,
    open_sequences,
)
from artclass_core.config import AUTO_SEGMENTER, CELL_REGISTRAR, stage_config

from . import controls, uploads

ROOT = Path(__file__).resolve().parent.parent
ENV_SAMPLES = "ARTCLASS_SAMPLE_DATA"
# Session-state keys kept across page switches (besides the configuration's cfg_ keys).
PERSIST = controls.KEY_PREFIXES + (
    "an_source",
    "an_sample",
    "an_folder",
    "an_seqname",
    "ev_folder",
    "ev_compare",
)
KIND_TITLES = {
    "rule": "Decision rule",
    "pipeline": "Pipeline",
    "preprocessor": "Preprocessing",
    "registrar": "Registration",
    "segmenter": "Segmentation",
}


# -- where data comes from ---------------------------------------------------------------------------
def samples_dir() -> Path:
    """The bundled samples (``sample_data/``; ``ARTCLASS_SAMPLE_DATA`` overrides, e.g. for tests)."""
    return Path(os.environ.get(ENV_SAMPLES) or ROOT / "sample_data").resolve()


def data_roots() -> list[Path]:
    """Folders a typed-in path may lie in (``--data-root``, ``ARTCLASS_DATA_ROOTS``, else the samples)."""
    return uploads.data_roots(sys.argv[1:], default=[samples_dir()])


def path_input(where, label: str, key: str, help: str) -> Path | None:
    """A text box for a path on this machine (``where``: ``st``, ``st.sidebar`` or a column), first
    holding the first data root; the path typed, or None when it lies outside the data roots."""
    roots = data_roots()
    st.session_state.setdefault(key, str(roots[0]) if roots else "")
    text = where.text_input(label, key=key, help=f"{help} Allowed under: " + ", ".join(map(str, roots)))
    return uploads.confine(text, roots)


def _stamp(path: str | Path) -> int:
    """Changes when files are added to or removed from the folder (part of the cache keys)."""
    try:
        return Path(path).stat().st_mtime_ns
    except OSError:
        return 0


# -- cached resources ----------------------------------------------------------------------------------
@st.cache_resource(show_spinner=False)
def registry() -> Registry:
    return load_registry()


@st.cache_resource(max_entries=64, ttl=3600, show_spinner=False)
def _open(path: str, stamp: int) -> list[Sequence]:
    return open_sequences(registry(), path)


def open_path(path: str) -> list[Sequence]:
    """The sequences at ``path`` (``PATH#NAME`` for one of several), through whichever reader
    recognises it. Raises :class:`InputError` when none does."""
    return _open(path, _stamp(path.partition("#")[0]))


@st.cache_resource(max_entries=16, ttl=600, show_spinner=False)
def _find(root: str, stamp: int, labelled_only: bool) -> tuple[list[Sequence], list[InputError]]:
    return find_sequences(registry(), root, labelled_only=labelled_only)


def find(root: str | Path, *, labelled_only: bool) -> tuple[list[Sequence], list[InputError]]:
    return _find(str(root), _stamp(root), labelled_only)


def sequence_key(seq: Sequence) -> str:
    return f"{seq.path}#{seq.name}@{_stamp(seq.path)}"


# -- the stage cache and the pipelines ----------------------------------------------------------------
@st.cache_resource(show_spinner=False)
def stage_cache() -> StageCache:
    """Clouds and registrations shared by every run of the app (a sequence's entries go with it)."""
    return StageCache(max_frames=2000, max_pairs=2000)


@st.cache_resource(max_entries=16, show_spinner=False)
def _segmenters(key: str) -> dict:
    return {}


@st.cache_resource(max_entries=32, show_spinner=False)
def _pipeline(key: str, _config: Config) -> Pipeline:
    return Pipeline(registry(), _config, segmenters=_segmenters(repr(stage_config(_config, "segment"))))


def pipeline(config: Config) -> Pipeline:
    """The :class:`Pipeline` of ``config`` (cached); pipelines with the same segmentation settings
    share their segmenter objects."""
    return _pipeline(repr(config), config)


def run_sequence(
    seq: Sequence, config: Config, *, progress: Callable[[str, int, int], None] | None = None
) -> RunResult:
    """Classify ``seq`` (:meth:`Pipeline.run` through the app's :func:`stage_cache`, on every CPU),
    keeping the clouds for display. ``progress`` is called in the script's thread."""
    return pipeline(config).run(
        seq, cache=stage_cache(), keep_clouds=True, progress=progress, workers=os.cpu_count() or 1
    )


@st.cache_data(max_entries=64, show_spinner=False)
def _mask(seq_key: str, i: int, key: str, _sequence: Sequence, _config: Config) -> np.ndarray | None:
    return pipeline(_config).segmenter(_sequence).segment(_sequence[i], sequence=_sequence)


def mask_of(seq: Sequence, i: int, config: Config) -> np.ndarray | None:
    """The segmenter's mask of frame ``i`` (for display; the run keeps only the cloud)."""
    segment = stage_config(config, "segment")
    return _mask(sequence_key(seq), i, repr(segment), seq, segment)


# -- the configuration sidebar (shared by the pages) ------------------------------------------------------
def resolved_segmenter(reg: Registry, name: str, seq: Sequence | None) -> str | None:
    """The segmenter that ``name`` means for ``seq`` (``auto`` depends on the sequence's masks)."""
    if name != AUTO_SEGMENTER:
        return name
    if seq is None:
        return None
    return Pipeline(reg, Config()).segmenter_name(seq)


def hints_from(result: RunResult | None) -> dict[str, dict[str, float]]:
    """What the automatic parameters resolved to in ``result``, by kind and parameter name.

    The pipeline's x is each pair's ``cell_size_m``; a plugin parameter with symbol ``v`` and unit
    ``m`` is matched to the frames' ``info["v_m"]`` (the convention the preprocessors report in).
    """
    if result is None:
        return {}
    hints: dict[str, dict[str, float]] = {}
    xs = [p.cell_size_m for p in result.pairs if p.cell_size_m]
    if xs:
        hints["pipeline"] = {"cell_size_m": statistics.median(xs)}
    reg = registry()
    for kind in ("segmenter", "preprocessor", "registrar", "rule"):
        name = result.plugins.get(kind)
        try:
            cls = reg.get(kind, name).Params
        except ArtclassError:
            continue
        for spec in describe(cls):
            info_key = f"{spec.symbol}_{spec.unit}" if spec.symbol and spec.unit else None
            values = [
                f.info[info_key]
                for f in result.frames
                if info_key and isinstance(f.info.get(info_key), (int, float))
            ]
            if values:
                hints.setdefault(kind, {})[spec.name] = float(statistics.median(values))
    return hints


def config_sidebar(
    reg: Registry, *, sequence: Sequence | None = None, hints: dict[str, dict[str, float]] | None = None
) -> Config:
    """Plugin choices and parameter widgets in the sidebar; returns the :class:`Config` they give.

    Raises :class:`ArtclassError` (e.g. a ``ParamError``) when the values do not make a valid
    configuration; the widgets are drawn in any case.
    """
    hints = hints or {}
    sb = st.sidebar
    sb.subheader("Plugins")
    names = {}
    # The rule comes before the registrar: only registrars that give what the rule decides from are offered.
    for kind, title in (
        ("segmenter", "Segmenter"),
        ("preprocessor", "Preprocessor"),
        ("rule", "Decision rule"),
        ("registrar", "Registrar"),
    ):
        options = ([AUTO_SEGMENTER] if kind == "segmenter" else []) + reg.names(kind)
        if kind == "registrar" and names.get("rule") in reg.names("rule"):
            needs = reg.get("rule", names["rule"]).needs
            options = [n for n in options if reg.get("registrar", n).gives == needs]
        key = f"cfg_plugin:{kind}"
        default = getattr(Config(), kind)
        if kind == "registrar" and default not in options:
            default = CELL_REGISTRAR
        if st.session_state.get(key) not in options:
            st.session_state[key] = default if default in options else (options[0] if options else None)
        describe_ = {n: reg.plugins[kind][n].cls.description for n in reg.names(kind)}
        describe_[AUTO_SEGMENTER] = "the sequence's own masks when it has them, else depth_threshold"
        names[kind] = sb.selectbox(
            title, options, key=key, help="; ".join(f"{n}: {d}" for n, d in describe_.items())
        )
    sb.subheader("Parameters")
    advanced = sb.toggle(
        "Show all parameters",
        key="cfg_advanced",
        help="Also show the parameters that have no symbol in the paper.",
    )
    built = {}
    errors = []

    def section(kind: str, plugin: str | None, params_cls, expanded: bool):
        title = KIND_TITLES[kind] + (f" ({plugin})" if plugin and kind != "pipeline" else "")
        with sb.expander(title, expanded=expanded):
            if params_cls is None:
                st.caption("Chosen per sequence (auto); its parameters show once a sequence is open.")
                return None
            try:
                return controls.params_widgets(
                    kind, plugin or "core", params_cls, advanced=advanced, hints=hints.get(kind, {})
                )
            except ArtclassError as exc:
                errors.append(exc)
                st.error(str(exc))
                return None

    built["rule"] = section("rule", names["rule"], reg.get("rule", names["rule"]).Params, True)
    built["pipeline"] = section("pipeline", None, PipelineParams, True)
    built["preprocessor"] = section(
        "preprocessor", names["preprocessor"], reg.get("preprocessor", names["preprocessor"]).Params, False
    )
    built["registrar"] = section(
        "registrar", names["registrar"], reg.get("registrar", names["registrar"]).Params, False
    )
    seg = None
    try:
        seg = resolved_segmenter(reg, names["segmenter"], sequence)
        seg_cls = reg.get("segmenter", seg).Params if seg else None
    except ArtclassError as exc:
        errors.append(exc)
        seg_cls = None
    built["segmenter"] = section("segmenter", seg, seg_cls, False)
    sb.button(
        "Reset parameters to defaults",
        on_click=controls.reset_params,
        key="cfg_reset",
        help="Every parameter back to its default (automatic where the paper derives it).",
    )
    if errors:
        raise errors[0]
    return Config(
        segmenter=names["segmenter"],
        preprocessor=names["preprocessor"],
        registrar=names["registrar"],
        rule=names["rule"],
        pipeline=built["pipeline"],
        segmenter_params=built["segmenter"],
        preprocessor_params=built["preprocessor"],
        registrar_params=built["registrar"],
        rule_params=built["rule"],
    )


def keep_state() -> None:
    """Carry the configuration and sequence choice over page switches (call at the top of a run)."""
    for key in list(st.session_state):
        if isinstance(key, str) and key.startswith(PERSIST):
            st.session_state[key] = st.session_state[key]
