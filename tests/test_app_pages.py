"""The evaluate and plugins pages, and switching between pages, through ``AppTest``."""

from __future__ import annotations

import json

import pytest

from artclass_core import Config, open_sequences
from artclass_core.evaluate import evaluate

from app_helpers import N_FRAMES, SEQUENCES, array, errors, metric, ok, timeline_decisions

pytestmark = pytest.mark.slow  # the app's page runs (AppTest)


# -- the other pages -------------------------------------------------------------------------------------
def test_evaluate_page(app, data_root, registry):
    ok(app.run())
    app.switch_page("app_pages/evaluate.py")
    ok(app.run())
    assert [b for b in app.button if b.key == "ev_run"]
    app.text_input(key="ev_folder").set_value(str(data_root))
    rules = registry.names("rule")
    compare = next((r for r in rules if r != Config().rule), None)
    if compare:
        app.selectbox(key="ev_compare").set_value(compare)
    app.button(key="ev_run").click()
    ok(app.run())
    assert metric(app, "Sequences / errors") == f"{len(SEQUENCES)} / 0"
    text = "\n".join(m.value for m in app.markdown)
    assert "Confusion matrix" in text and "laptop_articulate" in text
    confusions = [json.loads(c.proto.spec) for c in app.get("plotly_chart")]
    assert len(confusions) == (2 if compare else 1)
    # The page's numbers are those of artclass_core.evaluate on the same sequences.
    seqs = [open_sequences(registry, data_root / n)[0] for n in sorted(SEQUENCES)]
    expected = evaluate(registry, seqs, Config()).metrics()
    z = array(confusions[0]["data"][0]["z"])
    assert z == [
        [expected["confusion"][t][p] for p in expected["confusion"][t]] for t in expected["confusion"]
    ]
    # A folder outside the roots is refused, with a message.
    app.text_input(key="ev_folder").set_value("/etc").run()
    assert not app.exception
    assert any("outside the data folders" in e for e in errors(app)), errors(app)


def test_plugins_page(app, registry):
    app.run()
    app.switch_page("app_pages/plugins.py")
    ok(app.run())
    labels = " ".join(e.label for e in app.expander)
    for kind in ("segmenter", "preprocessor", "registrar", "rule"):
        for name in registry.names(kind):
            assert f"**{name}**" in labels


def test_page_switch_keeps_the_settings(app):
    ok(app.run())
    app.select_slider(key="cfg_p:pipeline:core:k").set_value(4).run()
    app.switch_page("app_pages/plugins.py").run()
    app.switch_page("app_pages/analyse.py")
    ok(app.run())
    assert app.select_slider(key="cfg_p:pipeline:core:k").value == 4
    assert len(timeline_decisions(app)) == N_FRAMES - 4
