"""Helpers for the app tests: reading what an ``AppTest`` shows, and driving its widgets.

The app tests open small synthetic sequences (rendered once per test run, see ``conftest.py``).
"""

from __future__ import annotations

import io
import json
import re
import shutil
import zipfile
from pathlib import Path

import numpy as np
from streamlit.testing.v1 import AppTest

from artclass_core import Config, Pipeline, PipelineParams, StageCache, open_sequences

ROOT = Path(__file__).resolve().parents[1]
APP = str(ROOT / "app" / "streamlit_app.py")
TIMEOUT = 300
N_FRAMES = 12
SEQUENCES = {  # name: (object, motion)
    "laptop_articulate": ("laptop", "articulate"),
    "mug_carry": ("mug", "carry"),
}


def errors(at: AppTest) -> list[str]:
    return [e.value for e in at.error]


def ok(at: AppTest) -> AppTest:
    assert not at.exception, [e.value for e in at.exception]
    assert not errors(at), errors(at)
    return at


def metric(at: AppTest, label: str) -> str:
    return next(m.value for m in at.metric if m.label == label)


def chart(at: AppTest, trace_name: str) -> dict:
    """The figure (as plotted) of the first Plotly chart with a trace called ``trace_name``."""
    for element in at.get("plotly_chart"):
        spec = json.loads(element.proto.spec)
        if any(t.get("name") == trace_name for t in spec["data"]):
            return spec
    raise AssertionError(f"no chart with a trace {trace_name!r}")


def array(value) -> list:
    """A trace's data array as plotted: a list, or Plotly's typed-array form {dtype, bdata[, shape]}."""
    if isinstance(value, dict) and "bdata" in value:
        import base64

        out = np.frombuffer(base64.b64decode(value["bdata"]), dtype=np.dtype(value["dtype"]))
        return out.reshape(value["shape"]).tolist() if "shape" in value else out.tolist()
    return list(value)


def timeline_decisions(at: AppTest) -> list[str]:
    spec = chart(at, "pair decision")
    return array(next(t for t in spec["data"] if t["name"] == "pair decision")["y"])


def assert_matches_pipeline(at: AppTest, registry, folder: Path) -> None:
    """The app's pair decisions are what ``Pipeline.run`` gives with the plugins and parameters the
    app reports (in the timeline's ``layout.meta``): the caches never serve a stale stage."""
    meta = chart(at, "pair decision")["layout"]["meta"]
    plugins, params = meta["plugins"], meta["params"]
    kinds = ("segmenter", "preprocessor", "registrar", "rule")
    config = Config(
        **{k: plugins[k] for k in kinds},
        pipeline=PipelineParams(**params["pipeline"]),
        **{f"{k}_params": registry.get(k, plugins[k]).Params(**params[k]) for k in kinds},
    )
    expected = Pipeline(registry, config).run(open_sequences(registry, folder)[0])
    assert timeline_decisions(at) == [p.decision for p in expected.pairs]
    assert metric(at, "Label") == expected.label
    pair = expected.pairs[at.session_state["an_pair"]]
    if pair.cells:
        assert selected_cells(at) == (len(pair.cells), sum(c.matched for c in pair.cells))


def selected_cells(at: AppTest) -> tuple[int, int]:
    """(cells, matched cells) of the selected pair, from the heading of its cells table."""
    label = next(e.label for e in at.expander if e.label.startswith("Cells of pair"))
    n, m = re.search(r"\((\d+) cells, (\d+) matched\)", label).groups()
    return int(n), int(m)


def use_paper_rule(at: AppTest) -> AppTest:
    at.selectbox(key="cfg_plugin:rule").set_value("paper")
    at.selectbox(key="cfg_plugin:preprocessor").set_value("paper")
    return at.run()


def open_folder(at: AppTest, path: str | Path) -> AppTest:
    at.sidebar.radio(key="an_source").set_value("Folder on the server").run()
    at.text_input(key="an_folder").set_value(str(path))
    return at.run()


class CallCounter:
    """Counts what the app computes rather than takes from its stage cache: frames and registrations
    stored in the cache, and decisions (the real methods still run)."""

    def __init__(self, monkeypatch, *names):
        self.calls = {n: 0 for n in names}
        put, decide = StageCache.put, Pipeline.decide

        def counted_put(cache, stage, key, value):
            if stage in self.calls:
                self.calls[stage] += 1
            return put(cache, stage, key, value)

        def counted_decide(pipeline, *args, **kwargs):
            if "decide" in self.calls:
                self.calls["decide"] += 1
            return decide(pipeline, *args, **kwargs)

        monkeypatch.setattr(StageCache, "put", counted_put)
        monkeypatch.setattr(Pipeline, "decide", counted_decide)


def copy_sequence(data_root: Path, name: str, dest: Path) -> Path:
    shutil.copytree(data_root / name, dest)
    return dest


def zip_folder(folder: Path, *, prefix: str = "") -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(folder.rglob("*")):
            zf.write(path, prefix + path.relative_to(folder).as_posix())
    return buf.getvalue()
