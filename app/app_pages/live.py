"""Live: classify a RealSense camera's frames, or a recording played frame by frame, as they arrive;
the timeline grows and the latest pair is shown in 3D."""

from __future__ import annotations

import logging

import streamlit as st

from app import state
from artclass_core import ArtclassError, Config
from artclass_plugins import figures
from artclass_plugins.live import classify_live, open_source
from artclass_plugins.live.sources import has_realsense

log = logging.getLogger("artclass.app")
SOURCES = ("A recording on the server", "RealSense camera")
MASK_FREE = "depth_threshold"  # the default segmenter: a live camera gives no masks


def sidebar(reg) -> tuple[str | None, Config, int]:
    """The source (a path, or None for the camera), the configuration and the frame limit."""
    sb = st.sidebar
    sb.subheader("Source")
    choices = SOURCES if has_realsense() else SOURCES[:1]
    source = sb.radio("Source", choices, key="lv_source", label_visibility="collapsed")
    path = None
    if source == SOURCES[0]:
        path = state.path_input(
            sb,
            "Recording",
            "lv_path",
            "A ROS or RealSense bag (.bag, .db3, .mcap, a ROS 2 bag folder) or a sequence folder.",
        )
    segmenters = [n for n in reg.names("segmenter") if n != "mask"]
    st.session_state.setdefault("lv_segmenter", MASK_FREE if MASK_FREE in segmenters else segmenters[0])
    segmenter = sb.selectbox(
        "Segmenter", segmenters, key="lv_segmenter", help="A segmenter that needs no masks."
    )
    limit = sb.number_input("Stop after (frames; 0: when the source ends)", 0, 10**6, 0, key="lv_max_frames")
    return path, Config(segmenter=segmenter), int(limit)


def main() -> None:
    reg = state.registry()
    st.title("Live")
    try:
        path, config, limit = sidebar(reg)
    except ArtclassError as exc:
        st.error(str(exc))
        return
    st.caption(
        "Frames are classified as they arrive: the decision so far after every pair, the timeline "
        "growing, and the latest pair's points coloured by the motion that explains them."
    )
    if not st.button("Start", key="lv_start", type="primary", icon=":material/play_arrow:"):
        return
    source = open_source(reg, path)
    summary, timeline, view = st.empty(), st.empty(), st.empty()
    update = None
    for n, update in enumerate(classify_live(reg, source, config, max_frames=limit or None)):
        result, pair = update.result, update.pair
        with summary.container():
            c1, c2, c3 = st.columns(3)
            c1.metric("Decision so far", result.label)
            c2.metric("Pairs", len(result.pairs))
            c3.metric("Frames", update.n_frames)
        timeline.plotly_chart(figures.decision_timeline(result), key=f"lv_timeline_{n}", theme=None)
        if pair.evidence is not None and pair.labels is not None and update.target.cloud is not None:
            view.plotly_chart(
                figures.motion_parts(pair, update.target.cloud), key=f"lv_motion_{n}", theme=None
            )
        else:
            view.caption(f"Pair {pair.i} → {pair.j}: {pair.decision} ({pair.reason or 'no 3D view'})")
    if update is None:
        st.warning(f"Too few frames for a pair (k = {config.pipeline.k}).")
    else:
        st.success(f"{update.result.sequence['name']}: {update.result.label} ({update.n_frames} frames)")


try:
    main()
except ArtclassError as exc:
    st.error(str(exc))
except Exception as exc:  # a bug: one line here, the traceback in the server log
    log.exception("unexpected error in the live page")
    st.error(f"Unexpected error ({type(exc).__name__}: {exc}). The details are in the server log.")
