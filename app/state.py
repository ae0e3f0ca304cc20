"""The app's caches and shared sidebar: plugin registry, sequences, stage results, configuration.

Caching follows the pipeline's stages, so that a slider only re-runs what depends on it:

=================  ==========================================  ===========================================
cache              key                                         recomputed when
=================  ==========================================  ===========================================
``frame_result``   sequence, frame, segmenter + preprocessor   a segmentation or preprocessing parameter
``registered``     ... + registrar, x, min_cell_points         x or a registrar parameter (no re-segmenting)
``decided``        ... + rule, alpha, min_fitness              q̄, t̄, α, min_fitness (no ICP)
(not cached)       summarise                                   w, k (k only pairs other, cached frames)
=================  ==========================================  ===========================================

The frame and register stages are ``st.cache_resource``: every re-run gets the very same cloud and
registration objects (nothing is copied, and a decision rule's :func:`artclass_core.pipeline.pair_memo`
evidence survives a slider move). Nothing in the app modifies them: :meth:`Pipeline.decide` and
:meth:`Pipeline.checked_cells` work on copies. The register stage runs without the fitness check
(``min_fitness`` = 0); it is applied when deciding (:func:`app.runner.decide_registered`). The
decisions are ``st.cache_data`` (a copy per call; the app sets each pair's ground truth on it).
"""

from __future__ import annotations

import os
import statistics
import sys
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np
import streamlit as st
from streamlit.runtime.scriptrunner import add_script_run_ctx, get_script_run_ctx

from artclass_core import (ArtclassError, CellMotion, Config, FrameResult, InputError, MotionEvidence, PairResult,
                           Pipeline, PipelineParams, Registry, RunResult, Sequence, describe, find_sequences, load_registry,
                           open_sequences)
from artclass_core.pipeline import AUTO_SEGMENTER, CELL_REGISTRAR

from . import controls, uploads
from .runner import decide_registered, run_staged, stage_config, stage_key

ROOT = Path(__file__).resolve().parent.parent
ENV_SAMPLES = "ARTCLASS_SAMPLE_DATA"
# Session-state keys kept across page switches (besides the configuration's cfg_ keys).
PERSIST = controls.KEY_PREFIXES + ("an_source", "an_sample", "an_folder", "an_seqname", "ev_folder", "ev_compare")
KIND_TITLES = {"rule": "Decision rule", "pipeline": "Pipeline", "preprocessor": "Preprocessing",
               "registrar": "Registration", "segmenter": "Segmentation"}


# -- where data comes from ---------------------------------------------------------------------------
def samples_dir() -> Path:
    """The bundled samples (``sample_data/``; ``ARTCLASS_SAMPLE_DATA`` overrides, e.g. for tests)."""
    return Path(os.environ.get(ENV_SAMPLES) or ROOT / "sample_data").resolve()


def data_roots() -> list[Path]:
    """Folders a typed-in path may lie in (``--data-root``, ``ARTCLASS_DATA_ROOTS``, else the samples)."""
    return uploads.data_roots(sys.argv[1:], default=[samples_dir()])


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


@st.cache_resource(max_entries=32, show_spinner=False)
def _pipeline(key: str, _config: Config) -> Pipeline:
    return Pipeline(registry(), _config)


def stage_pipeline(config: Config, stage: str) -> Pipeline:
    """A cached :class:`Pipeline` holding only what ``stage`` depends on (segmenters, e.g. ONNX
    sessions, are created once per segmentation setting, not once per slider move)."""
    sc = stage_config(config, stage)
    return _pipeline(repr(sc), sc)


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


# -- cached stages -------------------------------------------------------------------------------------
@st.cache_resource(max_entries=2000, show_spinner=False)
def frame_result(seq_key: str, i: int, key: str, _sequence: Sequence, _config: Config) -> FrameResult:
    """Segment and preprocess frame ``i`` (``Pipeline.frame``); keeps the cloud. Shared: read only."""
    return stage_pipeline(_config, "frame").frame(_sequence, i)


@st.cache_resource(max_entries=2000, show_spinner=False)
def registered(seq_key: str, i: int, j: int, key: str, _config: Config, _source: FrameResult,
               _target: FrameResult) -> tuple[tuple[CellMotion, ...] | MotionEvidence, float | None]:
    """Registration of the pair (i, j) (``Pipeline.register`` without the fitness check): the cells
    and the cell size x, or a pair registrar's motion evidence. Shared: read only."""
    cells, x = stage_pipeline(_config, "register").register(_source.cloud, _target.cloud)
    return (cells if isinstance(cells, MotionEvidence) else tuple(cells)), x


@st.cache_data(max_entries=4000, show_spinner=False)
def decided(seq_key: str, i: int, j: int, key: str, _config: Config, _source: FrameResult, _target: FrameResult,
            _cells: tuple[CellMotion, ...] | MotionEvidence, x: float | None,
            _between: tuple[FrameResult, ...]) -> PairResult:
    """Fitness and alpha checks and the decision rule of the pair (:func:`app.runner.decide_registered`)."""
    cells = _cells if isinstance(_cells, MotionEvidence) else list(_cells)
    return decide_registered(stage_pipeline(_config, "decide"), i, j, cells, _source.cloud, _target.cloud, x,
                             tuple(f.cloud for f in _between))


@st.cache_data(max_entries=64, show_spinner=False)
def frame_mask(seq_key: str, i: int, key: str, _sequence: Sequence, _config: Config) -> np.ndarray | None:
    """The segmenter's mask of frame ``i`` (for display; the frame stage does not return it)."""
    pipeline = stage_pipeline(_config, "frame")
    return pipeline.segmenter(_sequence).segment(_sequence[i], sequence=_sequence)


def run_sequence(seq: Sequence, config: Config, *, progress: Callable[[str, int, int], None] | None = None) -> RunResult:
    """Classify ``seq`` through the stage caches (see :func:`app.runner.run_staged`), on every CPU.
    The worker threads share the script run's context, as Streamlit's caches expect of their callers
    (https://docs.streamlit.io/develop/concepts/design/multithreading); they call nothing else of
    Streamlit's."""
    skey = sequence_key(seq)
    fkey, rkey, dkey = (stage_key(config, s) for s in ("frame", "register", "decide"))
    ctx = get_script_run_ctx()

    def in_ctx(fn: Callable) -> Callable:
        def run(*args):
            if ctx is not None and get_script_run_ctx(suppress_warning=True) is None:
                add_script_run_ctx(threading.current_thread(), ctx)
            return fn(*args)
        return run

    return run_staged(
        seq, config, Pipeline(registry(), config),
        frame=in_ctx(lambda i: frame_result(skey, i, fkey, seq, config)),
        register=in_ctx(lambda a, b: registered(skey, a.index, b.index, rkey, config, a, b)),
        decide=in_ctx(lambda a, b, cells, x, between: decided(skey, a.index, b.index, dkey, config, a, b, cells, x,
                                                              between)),
        progress=progress, workers=os.cpu_count() or 1)


def mask_of(seq: Sequence, i: int, config: Config) -> np.ndarray | None:
    return frame_mask(sequence_key(seq), i, stage_key(config, "frame"), seq, config)


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
            values = [f.info[info_key] for f in result.frames if info_key and isinstance(f.info.get(info_key), (int, float))]
            if values:
                hints.setdefault(kind, {})[spec.name] = float(statistics.median(values))
    return hints


def config_sidebar(reg: Registry, *, sequence: Sequence | None = None,
                   hints: dict[str, dict[str, float]] | None = None) -> Config:
    """Plugin choices and parameter widgets in the sidebar; returns the :class:`Config` they give.

    Raises :class:`ArtclassError` (e.g. a ``ParamError``) when the values do not make a valid
    configuration; the widgets are drawn in any case.
    """
    hints = hints or {}
    sb = st.sidebar
    sb.subheader("Plugins")
    names = {}
    # The rule comes before the registrar: only registrars that give what the rule decides from are offered.
    for kind, title in (("segmenter", "Segmenter"), ("preprocessor", "Preprocessor"), ("rule", "Decision rule"),
                        ("registrar", "Registrar")):
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
        names[kind] = sb.selectbox(title, options, key=key, help="; ".join(f"{n}: {d}" for n, d in describe_.items()))
    sb.subheader("Parameters")
    advanced = sb.toggle("Show all parameters", key="cfg_advanced",
                         help="Also show the parameters that have no symbol in the paper.")
    built = {}
    errors = []

    def section(kind: str, plugin: str | None, params_cls, expanded: bool):
        title = KIND_TITLES[kind] + (f" ({plugin})" if plugin and kind != "pipeline" else "")
        with sb.expander(title, expanded=expanded):
            if params_cls is None:
                st.caption("Chosen per sequence (auto); its parameters show once a sequence is open.")
                return None
            try:
                return controls.params_widgets(kind, plugin or "core", params_cls, advanced=advanced,
                                               hints=hints.get(kind, {}))
            except ArtclassError as exc:
                errors.append(exc)
                st.error(str(exc))
                return None

    built["rule"] = section("rule", names["rule"], reg.get("rule", names["rule"]).Params, True)
    built["pipeline"] = section("pipeline", None, PipelineParams, True)
    built["preprocessor"] = section("preprocessor", names["preprocessor"],
                                    reg.get("preprocessor", names["preprocessor"]).Params, False)
    built["registrar"] = section("registrar", names["registrar"], reg.get("registrar", names["registrar"]).Params, False)
    seg = None
    try:
        seg = resolved_segmenter(reg, names["segmenter"], sequence)
        seg_cls = reg.get("segmenter", seg).Params if seg else None
    except ArtclassError as exc:
        errors.append(exc)
        seg_cls = None
    built["segmenter"] = section("segmenter", seg, seg_cls, False)
    sb.button("Reset parameters to defaults", on_click=controls.reset_params, key="cfg_reset",
              help="Every parameter back to its default (automatic where the paper derives it).")
    if errors:
        raise errors[0]
    return Config(segmenter=names["segmenter"], preprocessor=names["preprocessor"], registrar=names["registrar"],
                  rule=names["rule"], pipeline=built["pipeline"], segmenter_params=built["segmenter"],
                  preprocessor_params=built["preprocessor"], registrar_params=built["registrar"],
                  rule_params=built["rule"])


def keep_state() -> None:
    """Carry the configuration and sequence choice over page switches (call at the top of a run)."""
    for key in list(st.session_state):
        if isinstance(key, str) and key.startswith(PERSIST):
            st.session_state[key] = st.session_state[key]
