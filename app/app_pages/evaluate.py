"""Evaluate the configured pipeline on a folder of labelled sequences (the paper's Tables 1-4)."""

from __future__ import annotations

import json
import logging

import pandas as pd
import streamlit as st

from app import state
from artclass_core import ArtclassError, Config, InputError, Sequence
from artclass_core.evaluate import Evaluation, evaluate, markdown
from artclass_core.sweep import read_table, summary
from artclass_plugins import figures
from artclass_plugins.figures import sweep_figure

log = logging.getLogger("artclass.app")
NO_COMPARE = "(none)"
FOLDER, SWEEP = "Evaluate a folder", "Open a sweep table"


@st.cache_data(max_entries=512, show_spinner=False)
def _outcome(seq_key: str, config_key: str, _sequence: Sequence, _config: Config):
    """One sequence's outcome under ``config`` (``evaluate`` on that sequence alone), cached."""
    return evaluate(state.registry(), [_sequence], _config).outcomes[0]


def run_evaluation(sequences: list[Sequence], config: Config, *, title: str) -> Evaluation:
    bar = st.progress(0.0, text=f"{title}: 0/{len(sequences)}")
    outcomes = []
    for n, seq in enumerate(sequences, 1):
        outcomes.append(_outcome(state.sequence_key(seq), repr(config), seq, config))
        bar.progress(n / len(sequences), text=f"{title}: {n}/{len(sequences)} ({seq.name})")
    bar.empty()
    return Evaluation(
        config.rule,
        outcomes,
        dict(plugins={k: getattr(config, k) for k in ("segmenter", "preprocessor", "registrar", "rule")}),
    )


def main() -> None:
    reg = state.registry()
    st.title("Evaluate on labelled sequences")
    st.caption(
        "Runs the pipeline configured in the sidebar on every labelled sequence under a folder and reports "
        "the paper's tables: accuracy per object, pair fractions, macro-F1 and the confusion matrix."
    )
    config, config_error = None, None
    try:
        config = state.config_sidebar(reg)
    except ArtclassError as exc:
        config_error = exc
    if (
        st.radio("Results", [FOLDER, SWEEP], horizontal=True, key="ev_source", label_visibility="collapsed")
        == SWEEP
    ):
        show_sweep()
        return
    c1, c2 = st.columns([3, 1])
    rules = [NO_COMPARE] + reg.names("rule")
    if st.session_state.get("ev_compare") not in rules:
        st.session_state["ev_compare"] = NO_COMPARE
    compare = c2.selectbox(
        "Compare with rule",
        rules,
        key="ev_compare",
        help="Also evaluate this decision rule with the same settings, side by side.",
    )
    folder = state.path_input(c1, "Folder of labelled sequences", "ev_folder", "Searched recursively.")
    if config is None:
        st.error(str(config_error))
        return
    sequences, errors = state.find(folder, labelled_only=True)
    for err in errors:
        st.warning(f"Skipped: {err}")
    if not sequences:
        raise InputError("no labelled sequence found under this folder", path=folder)
    st.write(
        f"{len(sequences)} labelled sequences: "
        + ", ".join(f"`{s.name}`" for s in sequences[:30])
        + (" …" if len(sequences) > 30 else "")
    )
    request = (folder, repr(config), compare)
    if st.button("Run evaluation", type="primary", key="ev_run", icon=":material/play_arrow:"):
        st.session_state["ev_request"] = request
    if st.session_state.get("ev_request") != request:
        st.info("Press **Run evaluation** (results are cached per sequence and setting).")
        return
    configs = [config]
    if compare != NO_COMPARE and compare != config.rule:
        configs.append(
            Config(
                segmenter=config.segmenter,
                preprocessor=config.preprocessor,
                registrar=config.registrar,
                rule=compare,
                pipeline=config.pipeline,
                segmenter_params=config.segmenter_params,
                preprocessor_params=config.preprocessor_params,
                registrar_params=config.registrar_params,
            )
        )
    evals = [run_evaluation(sequences, c, title=f"rule {c.rule}") for c in configs]
    show(evals)


def show_sweep() -> None:
    st.caption(
        "The table that `artclass sweep ROOT --grid NAME=V1,V2,... --out TABLE` wrote: one row per "
        "sequence and setting. The settings in the sidebar are not used here."
    )
    upload = st.file_uploader(
        "Sweep table (.parquet or .csv)", type=["parquet", "csv"], key="ev_sweep_upload"
    )
    if upload is None:
        st.info("Upload a sweep's table to see its accuracy against each swept parameter.")
        return
    table = read_table(upload)
    st.plotly_chart(sweep_figure(table), key="ev_sweep_figure", config={"displaylogo": False}, theme=None)
    st.dataframe(summary(table), hide_index=True, key="ev_sweep_summary")
    failed = table[table["error"].notna()]
    if len(failed):
        with st.expander(f"{len(failed)} row(s) failed"):
            st.dataframe(failed[["sequence", "setting", "error"]], hide_index=True)


def show(evals: list[Evaluation]) -> None:
    metrics = [e.metrics() for e in evals]
    for e, m in zip(evals, metrics):
        st.subheader(f"Rule `{e.rule}`")
        c = st.columns(4)
        c[0].metric("Sequence accuracy", f"{100 * m['accuracy']:.1f} %")
        c[1].metric("Macro-F1", f"{100 * m['macro_f1']:.1f} %")
        c[2].metric(
            "Pair accuracy", "–" if m["pair_accuracy"] is None else f"{100 * m['pair_accuracy']:.1f} %"
        )
        c[3].metric("Sequences / errors", f"{m['n_sequences']} / {m['errors']}")
    cols = st.columns(len(evals))
    for col, e, m in zip(cols, evals, metrics):
        col.plotly_chart(
            figures.confusion_figure(m, title=f"Confusion ({e.rule})"),
            key=f"ev_confusion_{e.rule}",
            config={"displaylogo": False},
            theme=None,
        )
    report = markdown(evals)
    st.markdown(report.replace("# artclass evaluation\n", "", 1))
    failed = [o for e in evals for o in e.outcomes if o.error]
    if failed:
        with st.expander(f"{len(failed)} sequence(s) failed"):
            st.dataframe(
                pd.DataFrame([dict(sequence=o.name, error=o.error) for o in failed]), hide_index=True
            )
    c1, c2 = st.columns(2)
    c1.download_button(
        "Report (Markdown)",
        data=report,
        file_name="evaluation.md",
        mime="text/markdown",
        on_click="ignore",
        key="ev_dl_md",
        icon=":material/description:",
    )
    c2.download_button(
        "Evaluation (JSON)",
        data=lambda: json.dumps(dict(evaluations=[e.to_dict() for e in evals]), indent=1, default=str),
        file_name="evaluation.json",
        mime="application/json",
        on_click="ignore",
        key="ev_dl_json",
        icon=":material/data_object:",
    )


try:
    main()
except ArtclassError as exc:
    st.error(str(exc))
except Exception as exc:
    log.exception("unexpected error in the evaluation page")
    st.error(f"Unexpected error ({type(exc).__name__}: {exc}). The details are in the server log.")
