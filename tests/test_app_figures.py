"""``artclass_plugins.figures``: the Plotly figures the app and the notebooks draw."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from artclass_core import Config
from artclass_core.evaluate import evaluate
from artclass_plugins import figures

pytestmark = pytest.mark.slow  # renders the app's sequences and runs the pipeline on them


# -- figures.py ----------------------------------------------------------------------------------------------
def test_decision_timeline(laptop_run):
    fig = figures.decision_timeline(laptop_run, selected=1)
    traces = {t.name: t for t in fig.data}
    decisions = traces["pair decision"]
    assert list(decisions.y) == [p.decision for p in laptop_run.pairs]
    assert list(decisions.x) == [p.i for p in laptop_run.pairs]
    filtered = next(t for name, t in traces.items() if name.startswith("filtered"))
    assert list(filtered.y) == laptop_run.filtered
    assert list(traces["fractions"].x) == [laptop_run.fractions[d] for d in ("NM", "RM", "AM")]
    assert laptop_run.label in fig.layout.title.text
    assert fig.layout.shapes and fig.layout.shapes[0].x0 == laptop_run.pairs[1].i
    assert figures.selected_pair_index(laptop_run, laptop_run.pairs[2].i) == 2
    assert figures.selected_pair_index(laptop_run, "nonsense") is None


def test_decision_timeline_shows_undecided_pairs_and_the_reason(laptop_run):
    run = dataclasses.replace(
        laptop_run,
        pairs=[dataclasses.replace(laptop_run.pairs[0], decision="undecided"), *laptop_run.pairs[1:]],
        filtered=laptop_run.filtered[1:],
        reason="no part moves about a joint <over> the video",
    )
    decisions = next(t for t in figures.decision_timeline(run).data if t.name == "pair decision")
    assert decisions.y[0] == "undecided" and decisions.marker.symbol[0] == "diamond-open"
    assert "no model explains it" in decisions.hovertext[0]
    assert (
        "no part moves about a joint &lt;over&gt; the video"
        in figures.decision_timeline(run).layout.title.text
    )


def test_motion_arrows_one_cone_per_matched_cell(laptop_run):
    pair = next(p for p in laptop_run.pairs if p.decision != "skipped")
    source, target = laptop_run.frames[pair.i].cloud, laptop_run.frames[pair.j].cloud
    fig = figures.motion_arrows(pair, source, target, magnify=1.0)
    cones = [t for t in fig.data if t.type == "cone"]
    matched = [c for c in pair.cells if c.matched]
    assert sum(len(t.x) for t in cones) == len(matched)
    assert len(cones) == len({c.cluster for c in matched})  # one colour (trace) per cluster
    # With magnify=1 each cone is the true displacement of its cell centre, and hover has the numbers.
    by_centre = {tuple(np.round(c.centre_m, 9)): c.to_dict() for c in matched}
    for t in cones:
        for x, y, z, u, v, w, custom in zip(t.x, t.y, t.z, t.u, t.v, t.w, t.customdata):
            d = by_centre[tuple(np.round([x, y, z], 9))]
            np.testing.assert_allclose([u, v, w], d["centre_displacement_m"], atol=1e-12)
            assert custom[0] == pytest.approx(d["fitness"]) and custom[1] == pytest.approx(d["rotation_deg"])
    names = [t.name for t in fig.data]
    assert f"frame {pair.i}" in names and f"frame {pair.j}" in names
    skipped = [c for c in pair.cells if not c.matched]
    if skipped:
        assert len(next(t for t in fig.data if t.name.startswith("skipped cells")).x) == len(skipped)


def test_frame_images_and_cells_table(laptop, laptop_run):
    frame = laptop[0]
    fig = figures.frame_images(frame, frame.mask)
    assert [t.type for t in fig.data] == ["image", "heatmap"]
    assert fig.data[0].source.startswith("data:image/png;base64,")
    depth = np.asarray(fig.data[1].z, dtype=float)
    assert np.nanmax(depth) == pytest.approx(float(frame.depth_m.max()), rel=1e-3)
    assert str(int(frame.mask.sum())) in fig.layout.annotations[0].text
    pair = next(p for p in laptop_run.pairs if p.decision != "skipped")
    rows = figures.cells_table(pair)
    assert len(rows) == len(pair.cells)
    for row, cell in zip(rows, pair.cells):
        assert row["status"] == ("matched" if cell.matched else cell.skipped)
        if cell.registration is not None:
            d = cell.to_dict()
            assert row["displacement_mm"] == pytest.approx(
                1000 * np.linalg.norm(d["centre_displacement_m"]), abs=0.01
            )
            assert row["rotation_deg"] == pytest.approx(d["rotation_deg"], abs=1e-3)
        else:
            assert row["fitness"] is None
    json.dumps(rows)  # JSON-ready


def test_frame_images_with_hand_overlays_the_hand(laptop):
    frame = laptop[0]
    hand = np.zeros(frame.depth_m.shape, bool)
    hand[:20, :30] = True
    plain = figures.frame_images(frame, frame.mask)
    fig = figures.frame_images_with_hand(frame, frame.mask, hand)
    assert "hand (600 px)" in fig.layout.annotations[0].text
    assert fig.data[0].source != plain.data[0].source
    assert figures.frame_images_with_hand(frame, frame.mask, None).data[0].source == plain.data[0].source


def test_confusion_figure_and_html_export(registry, laptop, laptop_run):
    metrics = evaluate(registry, [laptop], Config()).metrics()
    fig = figures.confusion_figure(metrics)
    (heat,) = fig.data
    assert list(heat.y) == list(metrics["confusion"])
    assert [list(r) for r in heat.z] == [list(metrics["confusion"][t].values()) for t in metrics["confusion"]]
    assert sum(map(sum, heat.z)) == 1
    page = figures.figures_html(
        {"timeline": figures.decision_timeline(laptop_run), "confusion": fig}, title="t"
    )
    assert page.count("<h2>") == 2 and page.count('class="plotly-graph-div"') == 2
    assert (
        page.count("* plotly.js v") == 1 and 'src="https://' not in page
    )  # plotly.js embedded once: offline


def test_joint_state_band_never_bridges_unknown_frames():
    from types import SimpleNamespace

    states = np.array([0.0, 0.1, np.nan, 0.2, 0.3, np.nan, np.nan, 0.5])
    estimate = SimpleNamespace(type="revolute", states=states, states_std=np.full(8, 0.01))
    fig = figures.joint_states(SimpleNamespace(joints=[SimpleNamespace(child=1, estimate=estimate)]))
    band = next(t for t in fig.data if t.fill == "toself")
    x = np.array([np.nan if v is None else v for v in band.x], float)
    runs = [r[np.isfinite(r)] for r in np.split(x, np.flatnonzero(np.isnan(x)))]
    spans = sorted((r.min(), r.max()) for r in runs if len(r))
    assert spans == [(0.0, 1.0), (3.0, 4.0), (6.7, 7.3)]  # the lone frame 7 gets a narrow band of its own
    line = next(t for t in fig.data if t.mode == "lines+markers")
    np.testing.assert_allclose(np.array(line.y, float), np.degrees(states))
