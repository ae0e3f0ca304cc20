"""Analyse one sequence: choose it, tune the pipeline, see every pair's decision and why."""

from __future__ import annotations

import json
import logging

import numpy as np
import pandas as pd
import streamlit as st

from app import state, uploads
from artclass_core import ArtclassError, InputError, Sequence
from artclass_core.articulation import Articulation
from artclass_core.config import JOINT_ESTIMATOR, PART_FINDER
from artclass_core.types import DECISIONS
from artclass_plugins import figures

log = logging.getLogger("artclass.app")
SOURCES = ("Bundled samples", "Folder on the server", "Upload a zip")


def _samples() -> list[Sequence]:
    root = state.samples_dir()
    if not root.is_dir():
        return []
    found, _errors = state.find(root, labelled_only=False)
    return sorted(found, key=lambda s: s.name)


def choose_sequence(reg) -> Sequence | None:
    """The sidebar's sequence chooser. Returns the chosen sequence, or raises ArtclassError."""
    sb = st.sidebar
    sb.subheader("Sequence")
    source = sb.radio("Source", SOURCES, key="an_source", label_visibility="collapsed")
    if source == SOURCES[0]:
        samples = _samples()
        if not samples:
            raise InputError(
                "no bundled samples found (generate them with `artclass sample`, or choose another source)",
                path=state.samples_dir(),
            )
        names = [s.name for s in samples]
        if st.session_state.get("an_sample") not in names:
            first = next((s.name for s in samples if s.label == "articulated"), names[0])
            st.session_state["an_sample"] = first
        labels = {s.name: f"{s.name}  ({s.label})" if s.label else s.name for s in samples}
        name = sb.selectbox("Sample", names, key="an_sample", format_func=labels.get)
        return samples[names.index(name)]
    if source == SOURCES[1]:
        path = state.path_input(
            sb, "Folder", "an_folder", "A sequence folder (PATH#NAME picks one of several)."
        )
        found = state.open_path(path)
    else:
        upload = sb.file_uploader("Sequence as a zip (native folder format)", type=["zip"], key="an_upload")
        if upload is not None:
            dest = uploads.extract_upload(upload.getvalue(), name=upload.name, root=uploads.upload_root())
            st.session_state["an_upload_path"] = str(dest)
            st.session_state["an_upload_name"] = upload.name
        path = st.session_state.get("an_upload_path")
        if not path:
            raise InputError("upload a zip of a sequence folder (meta.json, rgb/, depth/, optional mask/)")
        found, errors = state.find(path, labelled_only=False)
        if not found:
            if errors:
                raise errors[0]
            raise InputError(
                "no sequence in the zip that a reader recognises (expected meta.json, rgb/, depth/)",
                path=st.session_state.get("an_upload_name", "upload.zip"),
            )
        sb.caption(f"Uploaded: {st.session_state.get('an_upload_name', '')}")
    if len(found) > 1:
        names = [s.name for s in found]
        if st.session_state.get("an_seqname") not in names:
            st.session_state["an_seqname"] = names[0]
        name = sb.selectbox("Sequence in this folder", names, key="an_seqname")
        return found[names.index(name)]
    return found[0]


class StageProgress:
    """One progress bar per stage, removed when the run is done."""

    TITLES = {"pairs": "Reading frames, registering and deciding pairs"}

    def __init__(self):
        self.box = st.empty()
        self.container = self.box.container()
        self.bars = {}

    def __call__(self, stage: str, done: int, total: int) -> None:
        if stage not in self.bars:
            self.bars[stage] = self.container.progress(0.0, text=self.TITLES.get(stage, stage))
        self.bars[stage].progress(
            done / max(total, 1), text=f"{self.TITLES.get(stage, stage)}: {done}/{total}"
        )

    def done(self) -> None:
        self.box.empty()


def _sync_pair_with_click(result) -> None:
    """A click on the timeline selects that pair (the slider follows)."""
    event = st.session_state.get("an_timeline")
    points = (
        (event or {}).get("selection", {}).get("points", [])
        if isinstance(event, dict)
        else getattr(getattr(event, "selection", None), "points", []) or []
    )
    if not points:
        return
    x = points[0].get("x")
    marker = json.dumps(points[0], sort_keys=True, default=str)
    if marker == st.session_state.get("an_timeline_seen"):
        return
    st.session_state["an_timeline_seen"] = marker
    n = figures.selected_pair_index(result, x)
    if n is not None:
        st.session_state["an_pair"] = n


def show_result(seq: Sequence, config, result) -> None:
    pairs = result.pairs
    decided = [p for p in pairs if p.decision in DECISIONS]
    undecided = sum(p.decision == "undecided" for p in pairs)
    truth = seq.label
    c1, c2, c3, c4 = st.columns(4)
    c1.metric("Label", result.label)
    c2.metric(
        "Ground truth",
        truth or "unknown",
        delta=None if not truth else ("correct" if result.label in seq.accepted_labels else "wrong"),
        delta_color="normal" if truth and result.label in seq.accepted_labels else "inverse",
    )
    c3.metric(
        "Pairs decided",
        f"{len(decided)} / {len(pairs)}",
        help=f"{undecided} undecided (no model explains them: a motion beyond what registration reaches), "
        f"{len(pairs) - len(decided) - undecided} skipped.",
    )
    c4.metric(
        "Run time",
        f"{result.timing_s.get('total', 0.0):.2f} s",
        help="Wall time of this run, cached stages included (frames "
        f"{result.timing_s.get('frames', 0):.2f} s, registration {result.timing_s.get('register', 0):.2f} s, "
        f"decisions {result.timing_s.get('decide', 0):.2f} s).",
    )
    st.markdown(f"**Why {result.label}:** {result.reason}")
    if not pairs:
        st.info("No pairs to show.")
        return
    _sync_pair_with_click(result)
    n_pairs = len(pairs)
    if st.session_state.get("an_pair") not in range(n_pairs):
        st.session_state["an_pair"] = next((n for n, p in enumerate(pairs) if p.decision != "skipped"), 0)
    selected = st.session_state["an_pair"]
    timeline = figures.decision_timeline(result, selected=selected)
    st.plotly_chart(
        timeline,
        key="an_timeline",
        on_select="rerun",
        selection_mode="points",
        config={"displaylogo": False},
        theme=None,
    )
    st.caption("Click a pair in the timeline, or use the slider, to see its cells below.")
    # The labels name the frames only: a label that changed with the decisions would make a new
    # widget (and lose the chosen pair) whenever a slider re-decides.
    st.select_slider(
        "Pair",
        options=list(range(n_pairs)),
        key="an_pair",
        format_func=lambda n: f"{pairs[n].i} → {pairs[n].j}",
    )
    pair = pairs[st.session_state["an_pair"]]
    source, target = result.frames[pair.i], result.frames[pair.j]
    if pair.decision == "skipped" and not pair.cells and pair.evidence is None:
        st.warning(f"Pair {pair.i} → {pair.j} was skipped: {pair.reason}")
        motion = None
    else:
        if pair.decision in ("skipped", "undecided"):
            st.warning(f"Pair {pair.i} → {pair.j} was {pair.decision}: {pair.reason}")
        if pair.evidence is not None and pair.labels is not None:
            motion = figures.motion_parts(pair, target.cloud)
            st.plotly_chart(motion, key="an_motion", config={"displaylogo": False}, theme=None)
            st.caption(
                f"Rule reason: {pair.reason or '—'}. Points of frame {pair.i} coloured by the motion that "
                f"explains them (the pair's part segmentation), frame {pair.j} in grey; one arrow per "
                "motion, from its points' centre. Hover a point for its motion."
            )
        else:
            motion = figures.motion_arrows(pair, source.cloud, target.cloud)
            st.plotly_chart(motion, key="an_motion", config={"displaylogo": False}, theme=None)
            st.caption(
                f"Rule reason: {pair.reason or '—'}. Arrows: motion of each cell's centre under its ICP "
                "transform, coloured by the motion cluster (hash key) the rule put it in. Hover a cell for "
                "its fitness, rotation and translation."
            )
    images = {}
    cols = st.columns(2)
    for col, fr in zip(cols, (source, target)):
        with col:
            frame = seq[fr.index]
            mask = state.mask_of(seq, fr.index, config)
            images[fr.index] = figures.frame_images_with_hand(frame, mask, hand_of(seq, fr.index, config))
            st.plotly_chart(
                images[fr.index],
                key=f"an_frame_{'ij'[fr is target]}",
                config={"displaylogo": False},
                theme=None,
            )
            if fr.skipped:
                st.caption(f"Frame {fr.index} skipped: {fr.skipped}")
    parts = show_parts(seq, config, result, pair)
    if pair.motions:
        with st.expander(f"Motions of pair {pair.i} → {pair.j} ({len(pair.motions)})", expanded=False):
            st.dataframe(pd.DataFrame(figures.motions_table(pair)), hide_index=True, width="stretch")
    else:
        with st.expander(
            f"Cells of pair {pair.i} → {pair.j} ({len(pair.cells)} cells, "
            f"{sum(c.matched for c in pair.cells)} matched)",
            expanded=False,
        ):
            st.dataframe(pd.DataFrame(figures.cells_table(pair)), hide_index=True, width="stretch")
    export(
        seq,
        result,
        {
            "Decision timeline": timeline,
            **({f"Pair {pair.i} → {pair.j} (3D motion)": motion} if motion is not None else {}),
            **{f"Frame {n}": f for n, f in images.items()},
            **parts,
        },
    )
    with st.expander("Resolved automatic values and frame details"):
        st.dataframe(pd.DataFrame([f.to_dict() for f in result.frames]), hide_index=True, width="stretch")


@st.cache_resource(max_entries=4, show_spinner="Finding parts and joints")
def articulation_of(seq_key: str, config_key: str, _result) -> Articulation:
    """The parts and joints of a run (keyed on the sequence and the whole configuration)."""
    reg = state.registry()
    finder = reg.create("part_finder", PART_FINDER)
    return finder.find(_result, estimator=reg.create("joint_estimator", JOINT_ESTIMATOR))


def show_parts(seq: Sequence, config, result, pair) -> dict:
    """The parts in colour (in 3D and on frame ``pair.i``), each joint's axis as an arrow, and the
    joint states over the video. Returns the figures shown, for the export."""
    if not any(p.motions for p in result.pairs):
        return {}
    st.subheader("Parts and joints")
    try:
        articulation = articulation_of(state.sequence_key(seq), repr(config), result)
    except ArtclassError as exc:
        st.warning(f"No parts: {exc}")
        return {}
    st.markdown(f"**{articulation.summary()}**")
    figs = {"Parts and joints (3D)": figures.parts_3d(articulation)}
    left, right = st.columns([3, 2])
    left.plotly_chart(
        figs["Parts and joints (3D)"], key="an_joints_3d", config={"displaylogo": False}, theme=None
    )
    figs[f"Frame {pair.i}: parts"] = figures.part_image(seq[pair.i], articulation.label_image(pair.i))
    right.plotly_chart(
        figs[f"Frame {pair.i}: parts"], key="an_joints_image", config={"displaylogo": False}, theme=None
    )
    if articulation.joints:
        figs["Joint states"] = figures.joint_states(articulation)
        st.plotly_chart(
            figs["Joint states"], key="an_joints_states", config={"displaylogo": False}, theme=None
        )
        st.caption(
            "The joint's state in each frame, relative to the first frame where the part was seen moving "
            "(the band: one standard deviation). Axes are in the camera frame of the first frame."
        )
    return figs


def hand_of(seq: Sequence, i: int, config) -> np.ndarray | None:
    """The hand or gripper mask the segmenter left out of frame ``i`` (None when it looks for none);
    the segmenter keeps it from the run, so this costs no new segmentation."""
    segmenter = state.pipeline(config).segmenter(seq)
    finder = getattr(segmenter, "hand_mask", None)
    return None if finder is None else finder(seq[i], sequence=seq)


def export(seq: Sequence, result, figs: dict) -> None:
    st.subheader("Export")
    c1, c2, c3 = st.columns(3)
    c1.download_button(
        "Run result (JSON)",
        data=lambda: json.dumps(result.to_dict(), indent=1),
        file_name=f"{seq.name}_result.json",
        mime="application/json",
        on_click="ignore",
        key="an_dl_json",
        icon=":material/data_object:",
    )
    c2.download_button(
        "Figures (HTML)",
        data=lambda: figures.figures_html(figs, title=f"artclass: {seq.name}"),
        file_name=f"{seq.name}_figures.html",
        mime="text/html",
        on_click="ignore",
        key="an_dl_html",
        icon=":material/insert_chart:",
    )
    if _has_kaleido():
        c3.download_button(
            "Timeline (PNG)",
            data=lambda: next(iter(figs.values())).to_image(format="png"),
            file_name=f"{seq.name}_timeline.png",
            mime="image/png",
            on_click="ignore",
            key="an_dl_png",
            icon=":material/image:",
        )
    else:
        c3.caption("PNG export needs the optional package kaleido; the HTML export works offline.")


def _has_kaleido() -> bool:
    import importlib.util

    return importlib.util.find_spec("kaleido") is not None


def main() -> None:
    reg = state.registry()
    seq, seq_error = None, None
    try:
        seq = choose_sequence(reg)
    except ArtclassError as exc:
        seq_error = exc
    config, config_error = None, None
    try:
        config = state.config_sidebar(reg, sequence=seq, hints=st.session_state.get("an_hints"))
    except ArtclassError as exc:
        config_error = exc
    if seq is None:
        st.title("Analyse a sequence")
        st.error(str(seq_error))
        return
    st.title(seq.name)
    st.caption(
        f"{seq.object_name} · {len(seq)} frames · {seq.intrinsics.width}×{seq.intrinsics.height} px · "
        f"ground truth: {seq.label or 'unknown'} · `{seq.path}`"
    )
    if config is None:
        st.error(str(config_error))
        return
    progress = StageProgress()
    try:
        result = state.run_sequence(seq, config, progress=progress)
    except ArtclassError as exc:
        progress.done()
        st.error(str(exc))
        return
    progress.done()
    st.session_state["an_hints"] = state.hints_from(result)
    show_result(seq, config, result)


try:
    main()
except ArtclassError as exc:  # anything the user can fix that escaped the sections above
    st.error(str(exc))
except Exception as exc:  # a bug: one line here, the traceback in the server log
    log.exception("unexpected error in the analyse page")
    st.error(f"Unexpected error ({type(exc).__name__}: {exc}). The details are in the server log.")
