"""Plotly figure builders for artclass results: the app's plots, reusable from notebooks and scripts.

Pure functions of artclass data types: no Streamlit, no file access, no algorithm. Each returns a
:class:`plotly.graph_objects.Figure` (or plain rows for a table)::

    from artclass_plugins.figures import decision_timeline, motion_arrows, frame_images, cells_table, confusion_figure

Stable API
----------
decision_timeline(result, *, selected=None)       per-pair decisions, filtered decisions, label, fractions
class_fractions(result)                            share of decided pairs per class (bar chart)
motion_arrows(pair, source, target, *, ...)        3D clouds of a pair with one cone per matched cell
frame_images(frame, mask, *, title=None)           RGB with the mask overlaid, and the depth image
cells_table(pair)                                  one row (dict) per cell of a pair, in mm and degrees
confusion_figure(metrics, *, title=None)           confusion matrix of ``Evaluation.metrics()``
figures_html(figures, *, title)                    several figures in one self-contained HTML page
sweep_figure(table, *, title=...)                  accuracy against each swept parameter (``artclass sweep``)

Units: the clouds are plotted in metres (camera frame: x right, y down, z forward, seen from the
camera); hover texts and tables give translations and displacements in millimetres, angles in degrees.
"""

from __future__ import annotations

import base64
import html
import itertools
from collections.abc import Mapping, Sequence
from typing import Any

import cv2
import numpy as np
import pandas as pd
import plotly.graph_objects as go
from plotly.subplots import make_subplots

from artclass_core import Cloud, Frame, PairResult, RunResult
from artclass_core.geometry import transform
from artclass_core.sweep import summary, swept_names
from artclass_core.types import DECISIONS

__all__ = [
    "DECISION_COLOURS",
    "LABEL_COLOURS",
    "CLUSTER_COLOURS",
    "decision_timeline",
    "class_fractions",
    "motion_arrows",
    "frame_images",
    "cells_table",
    "confusion_figure",
    "figures_html",
    "selected_pair_index",
    "sweep_figure",
]

DECISION_COLOURS = {
    "AM": "#E4572E",
    "RM": "#2E86AB",
    "NM": "#57A773",
    "undecided": "#8E7DBE",
    "skipped": "#B8B8B8",
}
LABEL_COLOURS = {
    "articulated": DECISION_COLOURS["AM"],
    "rigid": DECISION_COLOURS["RM"],
    "static": DECISION_COLOURS["NM"],
}
DECISION_NAMES = {
    "AM": "articulated motion",
    "RM": "rigid motion",
    "NM": "no motion",
    "undecided": "no model explains it",
    "skipped": "skipped",
}
# Distinct, colour-blind-friendly colours for motion clusters (Okabe-Ito, then Tableau).
CLUSTER_COLOURS = (
    "#0072B2",
    "#E69F00",
    "#009E73",
    "#CC79A7",
    "#D55E00",
    "#56B4E9",
    "#F0E442",
    "#000000",
    "#8C564B",
    "#BCBD22",
    "#17BECF",
    "#7F7F7F",
)
SOURCE_COLOUR = "#5B8DB8"
TARGET_COLOUR = "#E8A33D"
_LEVELS = ["skipped", "undecided", "NM", "RM", "AM"]
_FONT = dict(family="Inter, Segoe UI, Helvetica, Arial, sans-serif", size=13)


def _layout(fig: go.Figure, **kw) -> go.Figure:
    kw.setdefault("margin", dict(l=10, r=10, t=60, b=10))
    fig.update_layout(template="plotly_white", font=_FONT, **kw)
    return fig


# -- the run -----------------------------------------------------------------------------------------
def selected_pair_index(result: RunResult, frame_i: Any) -> int | None:
    """Index into ``result.pairs`` of the pair starting at frame ``frame_i`` (a clicked x value)."""
    try:
        i = int(round(float(frame_i)))
    except (TypeError, ValueError):
        return None
    return next((n for n, p in enumerate(result.pairs) if p.i == i), None)


def class_fractions(result: RunResult) -> go.Figure:
    """Horizontal bars: the share of decided pairs that are AM, RM and NM (the paper's Tables 3-4)."""
    fig = go.Figure()
    _fraction_bars(fig, result)
    return _layout(
        fig,
        title="Class fractions",
        xaxis=dict(range=[0, 1.15], tickformat=".0%"),
        height=260,
        showlegend=False,
    )


def _fraction_bars(fig: go.Figure, result: RunResult, **where) -> None:
    names = ["NM", "RM", "AM"]
    values = [result.fractions.get(d, 0.0) for d in names]
    fig.add_trace(
        go.Bar(
            x=values,
            y=names,
            orientation="h",
            marker_color=[DECISION_COLOURS[d] for d in names],
            text=[f"{v:.0%}" for v in values],
            textposition="outside",
            cliponaxis=False,
            name="fractions",
            showlegend=False,
            hovertemplate="%{y}: %{x:.1%} of decided pairs<extra></extra>",
        ),
        **where,
    )


def decision_timeline(result: RunResult, *, selected: int | None = None) -> go.Figure:
    """The decision of every pair (i, i + k) over time, with the filtered decisions and the label.

    Parameters
    ----------
    result : a run
    selected : index into ``result.pairs`` of the pair to mark with a vertical line

    Returns
    -------
    Figure with, on the left, one marker per pair at its decision level (``skipped`` < ``undecided`` <
    NM < RM < AM)
    in trace ``"pair decision"`` (``customdata`` = pair index, x = the pair's first frame), the
    moving max-count filtered decisions in trace ``"filtered (w = ...)"``, the per-pair ground truth
    (if known) in ``"ground truth"`` (these two take no hover or clicks: the pair markers carry
    everything, so a click always lands on a pair); on the right the class fractions. The title
    gives the label, and its subtitle the reason for it.
    """
    w = result.params.get("pipeline", {}).get("w")
    k = result.params.get("pipeline", {}).get("k")
    fig = make_subplots(
        rows=1,
        cols=2,
        column_widths=[0.8, 0.2],
        horizontal_spacing=0.06,
        subplot_titles=("", "Class fractions"),
    )
    pairs = result.pairs
    xs = [p.i for p in pairs]
    decided = [p for p in pairs if p.decision in DECISIONS]
    filtered = (
        dict(zip((p.i for p in decided), result.filtered)) if len(result.filtered) == len(decided) else {}
    )
    hover = [
        f"frames {p.i} → {p.j}: <b>{p.decision}</b> ({DECISION_NAMES[p.decision]})<br>{html.escape(p.reason)}"
        + (f"<br>after the filter: {filtered[p.i]}" if p.i in filtered else "")
        + (f"<br>truth: {p.truth}" if p.truth else "")
        + f"<br>{sum(c.matched for c in p.cells)} of "
        f"{len(p.cells)} cells matched"
        for p in pairs
    ]
    fig.add_trace(
        go.Scatter(
            x=xs,
            y=[p.decision for p in pairs],
            mode="markers",
            name="pair decision",
            marker=dict(
                size=13,
                color=[DECISION_COLOURS[p.decision] for p in pairs],
                line=dict(width=1, color="white"),
                symbol=[
                    {"skipped": "x-thin-open", "undecided": "diamond-open"}.get(p.decision, "circle")
                    for p in pairs
                ],
            ),
            customdata=list(range(len(pairs))),
            hovertext=hover,
            hovertemplate="%{hovertext}<extra></extra>",
        ),
        row=1,
        col=1,
    )
    if decided and len(result.filtered) == len(decided):
        fig.add_trace(
            go.Scatter(
                x=[p.i for p in decided],
                y=list(result.filtered),
                mode="lines",
                line_shape="hvh",
                name=f"filtered (w = {w})" if w else "filtered",
                line=dict(color="#333333", width=2, dash="dot"),
                hoverinfo="skip",
            ),
            row=1,
            col=1,
        )
    truth = [p for p in pairs if p.truth]
    if truth:
        fig.add_trace(
            go.Scatter(
                x=[p.i for p in truth],
                y=[p.truth for p in truth],
                mode="markers",
                name="ground truth",
                marker=dict(size=19, symbol="circle-open", color="#333333", line=dict(width=1.5)),
                hoverinfo="skip",
            ),
            row=1,
            col=1,
        )
    if selected is not None and 0 <= selected < len(pairs):
        fig.add_vline(x=pairs[selected].i, line=dict(color="#888888", width=1.5, dash="dash"), row=1, col=1)
    _fraction_bars(fig, result, row=1, col=2)
    fig.update_yaxes(
        type="category", categoryorder="array", categoryarray=_LEVELS, range=[-0.5, 4.5], row=1, col=1
    )
    fig.update_xaxes(
        title_text=f"pair (i, i + {k}): first frame i" if k else "first frame i of the pair",
        row=1,
        col=1,
        range=[min(xs, default=0) - 0.7, max(xs, default=0) + 0.7],
    )
    fig.update_xaxes(range=[0, 1.3], tickformat=".0%", row=1, col=2)
    truth_text = ""
    if result.sequence.get("truth"):
        ok = result.label == result.sequence["truth"]
        truth_text = f"  ·  ground truth: {result.sequence['truth']} {'✓' if ok else '✗'}"
    colour = LABEL_COLOURS.get(result.label, "#333333")
    return _layout(
        fig,
        height=330,
        title=dict(
            text=f"{html.escape(str(result.sequence.get('name', '')))}: <b style='color:{colour}'>{result.label}</b>"
            f"{truth_text}"
            + (
                f"<br><span style='font-size:12px'>{html.escape(result.reason)}</span>"
                if result.reason
                else ""
            ),
            x=0.01,
        ),
        legend=dict(orientation="h", yanchor="bottom", y=1.02, xanchor="right", x=0.78),
        clickmode="event+select",
        meta=dict(
            sequence=result.sequence,
            label=result.label,
            plugins=result.plugins,
            params=_jsonable(result.params),
        ),
        margin=dict(l=10, r=10, t=80, b=10),
    )


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.generic,)):
        return value.item()
    return value if value is None or isinstance(value, (str, int, float, bool)) else str(value)


# -- one pair in 3D ----------------------------------------------------------------------------------
def _subsample(points: np.ndarray, n: int) -> np.ndarray:
    if len(points) <= n:
        return points
    return points[np.linspace(0, len(points) - 1, n).astype(int)]


def _cell_rows(pair: PairResult) -> list[dict[str, Any]]:
    return [c.to_dict() for c in pair.cells]


def motion_arrows(
    pair: PairResult, source: Cloud, target: Cloud, *, max_points: int = 6000, magnify: float | None = None
) -> go.Figure:
    """Both clouds of a pair and one arrow (cone) per matched cell: the motion of the cell's centre.

    Parameters
    ----------
    pair : the pair, with its cells (each matched cell has a registration and, once decided, a cluster)
    source, target : the clouds of frames ``pair.i`` and ``pair.j``, metres
    max_points : at most this many points of each cloud are drawn (evenly spaced, deterministic)
    magnify : arrow length / true displacement; default: the longest arrow is 0.8 cell size long
        (never less than 1, at most 500)

    Returns
    -------
    Figure with traces ``frame i`` and ``frame j`` (points); per motion cluster one ``cone`` trace
    (together one cone per matched cell, anchored at the cell centre, pointing along ``R c + t - c``)
    and one marker trace at the cell centres, so cells that did not move show too, both named
    ``cluster N · M cells`` (the cluster's key is in the hover text); and ``skipped cells`` (small grey
    dots, hover gives the reason).
    Hover texts give the cell's ICP fitness, rotation angle (degrees), translation and centre
    displacement (mm).
    """
    fig = go.Figure()
    for cloud, name, colour in (
        (source, f"frame {pair.i}", SOURCE_COLOUR),
        (target, f"frame {pair.j}", TARGET_COLOUR),
    ):
        pts = _subsample(np.asarray(cloud.points), max_points)
        fig.add_trace(
            _markers(
                pts,
                name=name,
                marker=dict(size=1.6, color=colour, opacity=0.55),
                hoverinfo="skip",
            )
        )
    rows = _cell_rows(pair)
    matched = [(c, r) for c, r in zip(pair.cells, rows) if c.matched]
    disp = np.array([r["centre_displacement_m"] for _, r in matched]).reshape(-1, 3)
    longest = float(np.linalg.norm(disp, axis=1).max()) if len(disp) else 0.0
    cell = pair.cell_size_m or 0.05
    gain = (
        magnify
        if magnify is not None
        else (float(np.clip(0.8 * cell / longest, 1.0, 500.0)) if longest > 0 else 1.0)
    )
    clusters: dict[Any, list[int]] = {}
    for n, (c, _) in enumerate(matched):
        clusters.setdefault(c.cluster, []).append(n)
    for order, (cluster, members) in enumerate(
        sorted(clusters.items(), key=lambda kv: (kv[0] is None, kv[0] or 0))
    ):
        colour = CLUSTER_COLOURS[order % len(CLUSTER_COLOURS)] if cluster is not None else "#555555"
        cells = [matched[m][0] for m in members]
        info = [matched[m][1] for m in members]
        key = cells[0].key
        label = f"cluster {cluster}" if cluster is not None else "no cluster"
        name = f"{label} · {len(members)} cell{'s' if len(members) != 1 else ''}"
        centres = np.array([c.centre_m for c in cells], dtype=float).reshape(-1, 3)
        vec = disp[members] * gain
        custom = np.array(
            [
                [
                    r["fitness"],
                    r["rotation_deg"],
                    1000 * np.linalg.norm(r["translation_m"]),
                    1000 * np.linalg.norm(r["centre_displacement_m"]),
                    r["n_source"],
                    r["n_target"],
                    r["rmse_m"] * 1000,
                ]
                for r in info
            ]
        )
        cell_text = [
            f"{label}<br>cell {tuple(r['cell'])}" + (f"<br>key {html.escape(key)}" if key else "")
            for r in info
        ]
        template = (
            "%{text}<br>fitness %{customdata[0]:.2f}, rmse %{customdata[6]:.2f} mm"
            "<br>rotation %{customdata[1]:.2f}°<br>translation %{customdata[2]:.1f} mm"
            "<br>centre moved %{customdata[3]:.1f} mm<br>points %{customdata[4]:.0f} → %{customdata[5]:.0f}"
            "<extra></extra>"
        )
        fig.add_trace(
            _arrows(
                centres,
                vec,
                colour,
                name=name,
                group=f"c{order}",
                customdata=custom,
                text=cell_text,
                hovertemplate=template,
                lighting=dict(ambient=0.8, diffuse=0.6),
            )
        )
        fig.add_trace(
            _markers(
                centres,
                name=name,
                legendgroup=f"c{order}",
                showlegend=True,
                marker=dict(size=3.5, color=colour, symbol="circle"),
                customdata=custom,
                text=cell_text,
                hovertemplate=template,
            )
        )
    skipped = [(c, r) for c, r in zip(pair.cells, rows) if not c.matched]
    if skipped:
        centres = np.array([c.centre_m for c, _ in skipped], dtype=float).reshape(-1, 3)
        fig.add_trace(
            _markers(
                centres,
                name=f"skipped cells ({len(skipped)})",
                marker=dict(size=2.5, color="#8A8A8A", symbol="circle", opacity=0.8),
                text=[
                    f"cell {tuple(r['cell'])}<br>skipped: {html.escape(str(c.skipped))}<br>points "
                    f"{r['n_source']} → {r['n_target']}"
                    for c, r in skipped
                ],
                hovertemplate="%{text}<extra></extra>",
            )
        )
    title = (
        f"Pair {pair.i} → {pair.j}: <b style='color:{DECISION_COLOURS[pair.decision]}'>{pair.decision}</b>"
    )
    if pair.cell_size_m:
        title += f"  ·  cell size x = {1000 * pair.cell_size_m:.1f} mm"
    if len(disp):
        title += f"  ·  arrows ×{gain:.0f}" if gain >= 1.5 else ""
    return _scene(fig, title, pair)


def _scene(fig: go.Figure, title: str, pair: PairResult) -> go.Figure:
    """The 3D layout of a pair's figure: camera view, axes in metres, legend at the right."""
    axis = dict(
        showbackground=True,
        backgroundcolor="#F4F6F8",
        gridcolor="#DDDDDD",
        zerolinecolor="#CCCCCC",
        tickformat=".2f",
    )
    return _layout(
        fig,
        height=560,
        title=dict(text=title, x=0.01),
        legend=dict(
            itemsizing="constant",
            yanchor="top",
            y=0.98,
            xanchor="left",
            x=0.8,
            bgcolor="rgba(255,255,255,0.7)",
            maxheight=480,
        ),
        scene=dict(
            aspectmode="data",
            domain=dict(x=[0.0, 0.78], y=[0.0, 1.0]),
            xaxis=dict(title="x (m)", **axis),
            yaxis=dict(title="y (m)", **axis),
            zaxis=dict(title="z (m)", **axis),
            camera=dict(up=dict(x=0, y=-1, z=0), eye=dict(x=0.35, y=-0.45, z=-1.5)),
        ),
        uirevision=f"pair-{pair.i}-{pair.j}",
    )


def motion_parts(
    pair: PairResult, target: Cloud, *, max_points: int = 6000, magnify: float | None = None
) -> go.Figure:
    """A pair decided from motions: the source points coloured by the motion that explains them, the
    target cloud in grey, and one arrow per motion (from its points' centroid, along its displacement).

    Parameters
    ----------
    pair : a pair with ``motions`` and ``labels`` (and the ``evidence`` the labels index)
    target : the cloud of frame ``pair.j``, metres
    max_points : at most this many points of each cloud are drawn (evenly spaced, deterministic)
    magnify : arrow length / true displacement; default: the longest arrow is a fifth of the object

    Returns
    -------
    Figure with traces ``frame j`` (grey points), one ``motion N · M points`` trace per motion (its points
    and its arrow share a legend entry), and ``no evidence`` for points no motion explains.
    """
    fig = go.Figure()
    pts = _subsample(np.asarray(target.points), max_points)
    fig.add_trace(
        _markers(
            pts,
            name=f"frame {pair.j}",
            marker=dict(size=1.4, color="#B8B8B8", opacity=0.35),
            hoverinfo="skip",
        )
    )
    ev = pair.evidence
    points, labels = ev.points[ev.forward], pair.labels[ev.forward]  # the source's points
    size = float(np.linalg.norm(np.ptp(points, axis=0))) if len(points) else 0.1
    moved = [points[labels == n] for n in range(len(pair.motions))]
    centroids = [m.mean(axis=0) if len(m) else np.zeros(3) for m in moved]
    shifts = [transform(c[None], m.T_target_from_source)[0] - c for c, m in zip(centroids, pair.motions)]
    longest = max((float(np.linalg.norm(d)) for d in shifts), default=0.0)
    gain = (
        magnify
        if magnify is not None
        else (float(np.clip(0.2 * size / longest, 1.0, 500.0)) if longest > 0 else 1.0)
    )
    step = max(1, len(points) // max_points)
    for n, (motion, own, c, d) in enumerate(zip(pair.motions, moved, centroids, shifts)):
        colour = CLUSTER_COLOURS[n % len(CLUSTER_COLOURS)]
        name = f"motion {n} · {motion.n_points} points"
        text = (
            f"motion {n} ({html.escape(motion.name)})<br>rotation {motion.to_dict()['rotation_deg']:.1f}°"
            f"<br>points moved {1000 * motion.displacement_m:.1f} mm (median)"
        )
        own = own[::step]
        fig.add_trace(
            _markers(
                own,
                name=name,
                legendgroup=f"m{n}",
                marker=dict(size=2.2, color=colour, opacity=0.8),
                text=[text] * len(own),
                hovertemplate="%{text}<extra></extra>",
            )
        )
        if len(moved[n]):
            v = d * gain
            fig.add_trace(_arrow(c, v, colour, name=name, group=f"m{n}", text=text))
    loose = points[labels < 0][::step]
    if len(loose):
        fig.add_trace(
            _markers(
                loose,
                name=f"no evidence ({int((labels < 0).sum())})",
                hoverinfo="skip",
                marker=dict(size=1.6, color="#555555", opacity=0.6),
            )
        )
    title = (
        f"Pair {pair.i} → {pair.j}: <b style='color:{DECISION_COLOURS[pair.decision]}'>{pair.decision}</b>"
    )
    title += f"  ·  {len(pair.motions)} motion{'s' if len(pair.motions) != 1 else ''}"
    title += f"  ·  arrows ×{gain:.0f}" if gain >= 1.5 else ""
    return _scene(fig, title, pair)


def motions_table(pair: PairResult) -> list[dict[str, Any]]:
    """One row per selected motion: where it came from, its points, rotation and displacement."""
    return [
        dict(motion=n, **{k: v for k, v in m.to_dict().items() if k != "T_target_from_source"})
        for n, m in enumerate(pair.motions)
    ]


# -- frames --------------------------------------------------------------------------------------------
def _overlay(
    rgb: np.ndarray, mask: np.ndarray | None, *, colour=(228, 87, 46), alpha: float = 0.45
) -> np.ndarray:
    out = np.ascontiguousarray(rgb[..., :3], dtype=np.uint8).copy()
    if mask is None or not mask.any():
        return out
    m = mask.astype(bool)
    out[m] = (out[m] * (1 - alpha) + np.array(colour) * alpha).astype(np.uint8)
    contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(out, contours, -1, colour, max(1, out.shape[1] // 320))
    return out


def _png_uri(rgb: np.ndarray) -> str:
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:  # pragma: no cover - cv2 encodes any uint8 RGB image
        raise ValueError("could not encode the image as PNG")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def frame_images(
    frame: Frame, mask: np.ndarray | None, *, title: str | None = None, max_width: int = 320
) -> go.Figure:
    """The frame's colour image with ``mask`` overlaid (tint + outline), beside its depth image.

    Parameters
    ----------
    frame : the frame (``rgb`` (H, W, 3) uint8, ``depth_m`` (H, W) metres, 0 = no reading)
    mask : bool (H, W), the segmenter's object mask, or None
    title : figure title (default: the frame's index and name)
    max_width : the depth image is shown at most this many pixels wide (subsampled, for speed)

    Returns
    -------
    Figure with an ``image`` trace (the overlay, as an embedded PNG) and a ``heatmap`` trace
    (depth in metres, no-reading pixels blank).
    """
    h, w = frame.depth_m.shape[:2]
    step = max(1, int(np.ceil(w / max_width)))
    depth = np.asarray(frame.depth_m[::step, ::step], dtype=np.float32).copy()
    depth[~(np.isfinite(depth) & (depth > 0))] = np.nan
    n_mask = int(np.count_nonzero(mask)) if mask is not None else 0
    fig = make_subplots(
        rows=1,
        cols=2,
        horizontal_spacing=0.04,
        subplot_titles=(
            f"colour + mask ({n_mask} px)" if mask is not None else "colour (no mask)",
            "depth (m)",
        ),
    )
    fig.add_trace(
        go.Image(source=_png_uri(_overlay(frame.rgb, mask)), name="colour", hoverinfo="skip"), row=1, col=1
    )
    fig.add_trace(
        go.Heatmap(
            z=depth,
            x=np.arange(depth.shape[1]) * step,
            y=np.arange(depth.shape[0]) * step,
            colorscale="Viridis",
            name="depth",
            colorbar=dict(title="m", thickness=12, len=0.9),
            hovertemplate="u %{x}, v %{y}: %{z:.3f} m<extra></extra>",
        ),
        row=1,
        col=2,
    )
    fig.update_xaxes(showticklabels=False, showgrid=False, zeroline=False)
    fig.update_yaxes(showticklabels=False, showgrid=False, zeroline=False)
    fig.update_yaxes(autorange="reversed", scaleanchor="x2", row=1, col=2)
    fig.update_xaxes(range=[0, w], row=1, col=2)
    return _layout(
        fig,
        height=max(220, int(300 * h / max(w, 1)) + 60),
        title=dict(text=title or f"frame {frame.index} ({html.escape(frame.name)})", x=0.01),
        margin=dict(l=5, r=5, t=60, b=5),
    )


# -- tables ------------------------------------------------------------------------------------------
def cells_table(pair: PairResult) -> list[dict[str, Any]]:
    """One row per cell of ``pair``: where it is, how many points, and how it registered.

    Keys: ``cell``, ``status`` (``matched`` or the skip reason), ``cluster``, ``key``, ``n_source``,
    ``n_target``, ``fitness``, ``rmse_mm``, ``rotation_deg``, ``translation_mm`` (length of t),
    ``displacement_mm`` (motion of the cell centre), ``centre_mm`` (x, y, z). Unregistered cells
    have None in the registration columns.
    """
    out = []
    for cell, r in zip(pair.cells, _cell_rows(pair)):
        reg = "fitness" in r
        out.append(
            {
                "cell": str(tuple(r["cell"])),
                "status": "matched" if cell.matched else str(cell.skipped),
                "cluster": r["cluster"],
                "key": r["key"],
                "n_source": r["n_source"],
                "n_target": r["n_target"],
                "fitness": round(r["fitness"], 3) if reg else None,
                "rmse_mm": round(1000 * r["rmse_m"], 3) if reg else None,
                "rotation_deg": round(r["rotation_deg"], 3) if reg else None,
                "translation_mm": round(1000 * float(np.linalg.norm(r["translation_m"])), 2) if reg else None,
                "displacement_mm": round(1000 * float(np.linalg.norm(r["centre_displacement_m"])), 2)
                if reg
                else None,
                "centre_mm": ", ".join(f"{1000 * v:.0f}" for v in r["centre_m"]),
            }
        )
    return out


# -- evaluation ----------------------------------------------------------------------------------------
def confusion_figure(metrics: Mapping[str, Any], *, title: str | None = None) -> go.Figure:
    """The confusion matrix of ``Evaluation.metrics()``: rows ground truth, columns predicted.

    Returns a figure with one ``heatmap`` trace whose ``z`` holds the counts (rows in the order
    articulated, rigid, static; columns those and ``error``), each cell annotated with its count.
    """
    confusion = metrics["confusion"]
    truths = list(confusion)
    predicted = list(next(iter(confusion.values())))
    z = [[confusion[t][p] for p in predicted] for t in truths]
    fig = go.Figure(
        go.Heatmap(
            z=z,
            x=predicted,
            y=truths,
            colorscale="Blues",
            showscale=False,
            texttemplate="%{z}",
            textfont=dict(size=18),
            xgap=3,
            ygap=3,
            hovertemplate="truth %{y}, predicted %{x}: %{z}<extra></extra>",
        )
    )
    fig.update_yaxes(autorange="reversed", title="ground truth")
    fig.update_xaxes(side="top", title="predicted")
    acc = metrics.get("accuracy")
    text = title or "Confusion matrix"
    if acc is not None:
        text += f"  ·  accuracy {100 * acc:.1f} % of {metrics.get('n_sequences', '?')}"
    return _layout(
        fig, height=340, title=dict(text=text, x=0.01, y=0.97), margin=dict(l=10, r=10, t=90, b=10)
    )


# -- export --------------------------------------------------------------------------------------------
def figures_html(figures: Mapping[str, go.Figure] | Sequence[go.Figure], *, title: str = "artclass") -> str:
    """Several figures in one self-contained HTML page (plotly.js embedded once; works offline)."""
    items = list(figures.items()) if isinstance(figures, Mapping) else [(None, f) for f in figures]
    parts = []
    for n, (heading, fig) in enumerate(items):
        if heading:
            parts.append(f"<h2>{html.escape(heading)}</h2>")
        parts.append(fig.to_html(full_html=False, include_plotlyjs=(n == 0)))
    return (
        "<!DOCTYPE html><html><head><meta charset='utf-8'>"
        f"<title>{html.escape(title)}</title><style>body{{font-family:sans-serif;margin:2em}}</style></head>"
        f"<body><h1>{html.escape(title)}</h1>{''.join(parts)}</body></html>"
    )


def frame_images_with_hand(
    frame: Frame, mask: np.ndarray | None, hand: np.ndarray | None, **kwargs
) -> go.Figure:
    """:func:`frame_images`, with the hand or gripper mask (bool (H, W), or None) overlaid in blue on
    the colour image and its size in the subplot title."""
    fig = frame_images(frame, mask, **kwargs)
    if hand is not None and hand.any():
        fig.data[0].source = _png_uri(_overlay(_overlay(frame.rgb, mask), hand, colour=(46, 120, 228)))
        fig.layout.annotations[0].text += f" + hand ({int(np.count_nonzero(hand))} px)"
    return fig


# -- parts and joints ------------------------------------------------------------------------------------


def _part_colour(index: int) -> str:
    return "#8C8C8C" if index == 0 else CLUSTER_COLOURS[(index - 1) % len(CLUSTER_COLOURS)]


def parts_3d(articulation, *, max_points: int = 4000) -> go.Figure:
    """The parts found in a video, each in its colour (at the first state, in the base's coordinates
    of the first frame), and one arrow per joint along its axis.

    Parameters
    ----------
    articulation : :class:`artclass_core.articulation.Articulation`
    max_points : at most this many points of each part are drawn

    Returns
    -------
    Figure with one ``base`` / ``partN`` trace per part and one ``<type> axis`` cone and line per joint.
    """
    fig = go.Figure()
    extent = np.concatenate([p.points_m for p in articulation.parts if len(p.points_m)] or [np.zeros((1, 3))])
    length = max(float(np.linalg.norm(np.ptp(extent, axis=0))) / 2, 0.05)
    for part in articulation.parts:
        pts = _subsample(np.asarray(part.points_m), max_points)
        fig.add_trace(
            _markers(
                pts,
                name=part.name,
                marker=dict(size=2.0, color=_part_colour(part.index), opacity=0.8),
                hovertemplate=f"{part.name}<extra></extra>",
            )
        )
    for joint in articulation.joints:
        e = joint.estimate
        if e.axis_direction is None or e.axis_point_m is None:
            continue
        d, c = np.asarray(e.axis_direction, float), np.asarray(e.axis_point_m, float)
        tail, head = c - d * length / 2, c + d * length / 2
        colour = _part_colour(joint.child)
        text = html.escape(e.summary(up=articulation.UP))
        fig.add_trace(
            go.Scatter3d(
                x=[tail[0], head[0]],
                y=[tail[1], head[1]],
                z=[tail[2], head[2]],
                mode="lines",
                line=dict(color=colour, width=6),
                name=f"{e.type} axis",
                legendgroup=f"j{joint.child}",
                text=[text] * 2,
                hovertemplate="%{text}<extra></extra>",
            )
        )
        tip = d * length / 5
        fig.add_trace(_arrow(head, tip, colour, name=f"{e.type} axis", group=f"j{joint.child}", text=text))
    fig.update_layout(
        scene=dict(
            aspectmode="data",
            xaxis_title="x (m)",
            yaxis_title="y (m)",
            zaxis_title="z (m)",
            camera=dict(up=dict(x=0, y=-1, z=0), eye=dict(x=0.0, y=-0.3, z=-2.0)),
        )
    )
    return _layout(fig, title=f"Parts and joints: {articulation.summary()}", height=480)


def _bands(frames: np.ndarray, upper: np.ndarray, lower: np.ndarray) -> tuple[list, list]:
    """The outline (x, y) of a band between ``lower`` and ``upper`` over each run of consecutive frames
    where both are known, one after the other with None between them, which Plotly fills one by one:
    a band never bridges frames where the state is unknown. A frame alone gets a band 0.6 frame wide."""
    xs: list = []
    ys: list = []
    known = np.flatnonzero(np.isfinite(upper) & np.isfinite(lower))
    for run in np.split(known, np.flatnonzero(np.diff(known) > 1) + 1):
        if not len(run):
            continue
        x, hi, lo = frames[run].astype(float), upper[run], lower[run]
        if len(run) == 1:
            x, hi, lo = x[0] + np.array([-0.3, 0.3]), np.repeat(hi, 2), np.repeat(lo, 2)
        xs += [*x, *x[::-1], None]
        ys += [*hi, *lo[::-1], None]
    return xs, ys


def joint_states(articulation) -> go.Figure:
    """Each joint's state over the video (degrees or millimetres), with one standard deviation as a band."""
    fig = go.Figure()
    for joint in articulation.joints:
        e = joint.estimate
        scale, unit = (1000.0, "mm") if e.type == "prismatic" else (np.degrees(1.0), "deg")
        frames = np.arange(len(e.states))
        q = e.states * scale
        std = (e.states_std if e.states_std is not None else np.zeros_like(e.states)) * scale
        colour = _part_colour(joint.child)
        name = f"part{joint.child} ({e.type}, {unit})"
        x, y = _bands(frames, q + std, q - std)
        fig.add_trace(
            go.Scatter(
                x=x,
                y=y,
                fill="toself",
                fillcolor=colour,
                opacity=0.2,
                line=dict(width=0),
                hoverinfo="skip",
                showlegend=False,
                legendgroup=name,
            )
        )
        fig.add_trace(
            go.Scatter(
                x=frames,
                y=q,
                mode="lines+markers",
                name=name,
                legendgroup=name,
                line=dict(color=colour),
                hovertemplate="frame %{x}: %{y:.1f} " + unit + "<extra></extra>",
            )
        )
    return _layout(
        fig,
        title="Joint state over the video",
        xaxis_title="frame",
        yaxis_title="state (deg or mm)",
        height=320,
    )


def part_image(
    frame: Frame, labels: np.ndarray | None, *, title: str | None = None, max_width: int = 320
) -> go.Figure:
    """The colour image with each part of ``labels`` (H, W; 0 none, 1 + part index) in its colour."""
    rgb = frame.rgb.copy()
    if labels is not None:
        for value in np.unique(labels[labels > 0]):
            colour = _part_colour(int(value) - 1).lstrip("#")
            rgb = _overlay(rgb, labels == value, colour=tuple(int(colour[k : k + 2], 16) for k in (0, 2, 4)))
    if rgb.shape[1] > max_width:
        rgb = cv2.resize(
            rgb, (max_width, round(rgb.shape[0] * max_width / rgb.shape[1])), interpolation=cv2.INTER_AREA
        )
    fig = go.Figure(go.Image(source=_png_uri(rgb)))
    fig.update_xaxes(visible=False)
    fig.update_yaxes(visible=False)
    return _layout(
        fig, title=title or f"Frame {frame.index}: parts", height=300, margin=dict(l=0, r=0, t=40, b=0)
    )


def _arrow(at: np.ndarray, vector: np.ndarray, colour: str, *, name: str, group: str, text: str) -> go.Cone:
    """One cone of one colour from ``at`` along ``vector`` (metres), drawn to scale, with hover ``text``."""
    return _arrows(
        np.asarray(at)[None],
        np.asarray(vector)[None],
        colour,
        name=name,
        group=group,
        text=[text],
        hovertemplate="%{text}<extra></extra>",
    )


def _arrows(
    tails: np.ndarray, vectors: np.ndarray, colour: str, *, name: str, group: str, **style
) -> go.Cone:
    """Cones of one colour from ``tails`` along ``vectors`` (N, 3), metres, drawn to scale, with the
    trace's other ``style`` (hover text and template, lighting)."""
    return go.Cone(
        x=tails[:, 0],
        y=tails[:, 1],
        z=tails[:, 2],
        u=vectors[:, 0],
        v=vectors[:, 1],
        w=vectors[:, 2],
        sizemode="raw",
        sizeref=1.0,
        anchor="tail",
        colorscale=[[0, colour], [1, colour]],
        showscale=False,
        name=name,
        legendgroup=group,
        showlegend=False,
        **style,
    )


def _markers(points: np.ndarray, **style) -> go.Scatter3d:
    """A 3D scatter of ``points`` (N, 3), metres, as markers, with the trace's other ``style``."""
    return go.Scatter3d(x=points[:, 0], y=points[:, 1], z=points[:, 2], mode="markers", **style)


# -- sweeps ----------------------------------------------------------------------------------------------
def sweep_figure(table: pd.DataFrame, *, title: str = "Accuracy against each swept parameter"):
    """A Plotly figure: one panel per swept name, sequence accuracy (solid) and pair accuracy (dashed)
    against its values, one line per combination of the other swept names (named in the legend)."""
    summ = summary(table)
    names = swept_names(table) or ["setting"]
    fig = make_subplots(rows=1, cols=len(names), subplot_titles=names, shared_yaxes=True)
    palette = ["#2E86AB", "#E4572E", "#76B041", "#F2A541", "#8E6C8A", "#17BEBB", "#4D4D4D"]
    line = itertools.count()  # one colour per line, across the panels
    for col, name in enumerate(names, 1):
        others = [n for n in names if n != name]
        values = pd.to_numeric(summ[name], errors="coerce")
        numeric = bool(values.notna().all())
        summ["_x"] = values if numeric else summ[name]
        for key, part in summ.groupby(others, sort=False) if others else [((), summ)]:
            key = key if isinstance(key, tuple) else (key,)
            label = ", ".join(f"{n}={v}" for n, v in zip(others, key)) or "all"
            part = part.sort_values("_x") if numeric else part
            colour = palette[next(line) % len(palette)]
            for metric, dash in (("accuracy", None), ("pair_accuracy", "dash")):
                fig.add_trace(
                    go.Scatter(
                        x=part["_x"],
                        y=part[metric],
                        mode="lines+markers",
                        legendgroup=label,
                        name=f"{'sequence' if metric == 'accuracy' else 'pair'} accuracy, {label}",
                        line=dict(color=colour, dash=dash),
                        hovertemplate=f"{name}=%{{x}}<br>{metric.replace('_', ' ')} %{{y:.1%}}<extra>{label}</extra>",
                    ),
                    row=1,
                    col=col,
                )
        fig.update_xaxes(
            title_text=name,
            type=None if numeric else "category",
            tickvals=sorted(values.unique()) if numeric else None,
            row=1,
            col=col,
        )
    fig.update_yaxes(range=[-0.05, 1.05], tickformat=".0%", title_text="accuracy", col=1)
    fig.update_layout(
        template="plotly_white",
        title=title,
        height=420,
        margin=dict(t=80),
        legend=dict(orientation="h", y=-0.25),
    )
    return fig
