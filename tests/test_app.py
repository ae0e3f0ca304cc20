"""The Streamlit app: every page through ``streamlit.testing.v1.AppTest``, and its pure modules
(zip uploads and path confinement, the stage-by-stage runner, the slider options, the figures).

The app folder is not installed; like a notebook, the tests import it from the project root.
Sequences come from the synthetic generator (seeded, so every run sees the same data).
"""

from __future__ import annotations

import io
import json
import os
import shutil
import stat
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from streamlit.testing.v1 import AppTest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from app import controls, figures, runner, uploads  # noqa: E402
from artclass_core import (Config, InputError, Pipeline, PipelineParams, describe, load_registry,  # noqa: E402
                           open_sequences)
from artclass_core.evaluate import evaluate  # noqa: E402
from artclass_plugins.synth import generate_sequence  # noqa: E402

APP = str(ROOT / "app" / "streamlit_app.py")
TIMEOUT = 300
N_FRAMES = 12
SEQUENCES = {  # name: (object, motion)
    "laptop_articulate": ("laptop", "articulate"),
    "mug_carry": ("mug", "carry"),
}


# -- data and helpers ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def data_root(tmp_path_factory) -> Path:
    """A data root holding a few small synthetic sequences (what the app opens in these tests)."""
    root = tmp_path_factory.mktemp("app_data")
    for n, (name, (obj, motion)) in enumerate(SEQUENCES.items()):
        generate_sequence(root / name, object_name=obj, motion=motion, noise="low", n_frames=N_FRAMES, seed=n,
                          width=320, height=240)
    return root


@pytest.fixture(scope="module")
def registry():
    return load_registry()


@pytest.fixture
def app(data_root, tmp_path, monkeypatch) -> AppTest:
    """The app, with ``data_root`` as its bundled samples and its only data root."""
    monkeypatch.setenv("ARTCLASS_SAMPLE_DATA", str(data_root))
    monkeypatch.delenv("ARTCLASS_DATA_ROOTS", raising=False)
    monkeypatch.setenv("ARTCLASS_UPLOAD_DIR", str(tmp_path / "uploads"))
    return AppTest.from_file(APP, default_timeout=TIMEOUT)


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
    config = Config(**{k: plugins[k] for k in kinds}, pipeline=PipelineParams(**params["pipeline"]),
                    **{f"{k}_params": registry.get(k, plugins[k]).Params(**params[k]) for k in kinds})
    expected = Pipeline(registry, config).run(open_sequences(registry, folder)[0])
    assert timeline_decisions(at) == [p.decision for p in expected.pairs]
    assert metric(at, "Label") == expected.label
    pair = expected.pairs[at.session_state["an_pair"]]
    if pair.cells:
        assert selected_cells(at) == (len(pair.cells), sum(c.matched for c in pair.cells))


def selected_cells(at: AppTest) -> tuple[int, int]:
    """(cells, matched cells) of the selected pair, from the heading of its cells table."""
    import re
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
    """Counts calls of Pipeline stage methods (the real methods still run)."""

    def __init__(self, monkeypatch, *names):
        self.calls = {n: 0 for n in names}
        for name in names:
            original = getattr(Pipeline, name)

            def counted(self_, *args, _name=name, _original=original, **kwargs):
                self.calls[_name] += 1
                return _original(self_, *args, **kwargs)
            monkeypatch.setattr(Pipeline, name, counted)


# -- the analyse page ------------------------------------------------------------------------------------
def test_opens_on_the_bundled_samples_with_no_configuration(monkeypatch):
    for name in ("ARTCLASS_SAMPLE_DATA", "ARTCLASS_DATA_ROOTS"):
        monkeypatch.delenv(name, raising=False)
    samples = ROOT / "sample_data"
    assert samples.is_dir(), f"{samples} is missing: the bundled samples are part of the repository"
    folders = sorted(p for p in samples.iterdir() if (p / "meta.json").is_file())
    first = next(p for p in folders if json.loads((p / "meta.json").read_text()).get("label") == "articulated")
    at = ok(AppTest.from_file(APP, default_timeout=TIMEOUT).run())
    assert [t.value for t in at.title] == [first.name]
    options = at.selectbox(key="an_sample").options          # shown as "name  (label)"
    assert [o.split()[0] for o in options] == [p.name for p in folders]
    assert timeline_decisions(at)
    # With no data root configured, typed-in paths are confined to the bundled samples.
    open_folder(at, samples / folders[-1].name)
    assert [t.value for t in ok(at).title] == [folders[-1].name]
    open_folder(at, ROOT)
    assert any("outside the data folders" in e for e in errors(at)), errors(at)


def test_opens_on_first_articulated_sample_and_matches_the_pipeline(app, data_root, registry):
    ok(app.run())
    assert [t.value for t in app.title] == ["laptop_articulate"]
    label = metric(app, "Label")
    assert label in ("articulated", "rigid", "static")
    # The stage-by-stage run through the caches gives what Pipeline.run gives on the same settings.
    seq = open_sequences(registry, data_root / "laptop_articulate")[0]
    expected = Pipeline(registry, Config()).run(seq)
    assert label == expected.label
    assert timeline_decisions(app) == [p.decision for p in expected.pairs]
    assert len(timeline_decisions(app)) == N_FRAMES - Config().pipeline.k
    # The 3D view of the selected pair: the target cloud, and per motion its points and one arrow.
    pair = expected.pairs[app.session_state["an_pair"]]
    spec = chart(app, f"frame {pair.j}")
    names = [t.get("name", "") for t in spec["data"] if t["type"] == "scatter3d"]
    assert len([n for n in names if n.startswith("motion ")]) == len(pair.motions) >= 1, names
    assert sum(len(array(t["x"])) for t in spec["data"] if t["type"] == "cone") == sum(m.n_points > 0 for m in pair.motions)
    assert len([e for e in app.get("plotly_chart") if not e.key.startswith("an_joints_")]) == 4   # timeline, 3D, two frames
    assert any(d.label.startswith("Run result") for d in app.get("download_button"))


def test_decision_sliders_redecide_without_icp(app, monkeypatch, registry, data_root):
    use_paper_rule(ok(app.run()))
    app.toggle(key="cfg_advanced").set_value(True).run()
    # A tight ICP correspondence distance, so that cells' fitness spreads below 1 (min_fitness matters).
    app.select_slider(key="cfg_p:registrar:icp_point_to_point:max_correspondence_cells").set_value(0.1)
    before = timeline_decisions(ok(app.run()))
    counter = CallCounter(monkeypatch, "frame", "register", "decide")
    # Huge steps rounded to the nearest bin put every cell's motion in the zero key: NM everywhere.
    app.selectbox(key="cfg_p:rule:paper:rounding").set_value("round")
    app.select_slider(key="cfg_p:rule:paper:q_bar").set_value(2.0)
    app.select_slider(key="cfg_p:rule:paper:t_bar").set_value(10.0)
    ok(app.run())
    after = timeline_decisions(app)
    assert set(after) <= {"NM", "skipped"} and "NM" in after, after
    assert after != before
    assert metric(app, "Label") == "static"
    assert counter.calls["register"] == 0 and counter.calls["frame"] == 0, counter.calls
    assert counter.calls["decide"] > 0
    assert_matches_pipeline(app, registry, data_root / "laptop_articulate")
    # min_fitness is checked when deciding: no ICP either, yet the cells it rejects change.
    matched_before = selected_cells(app)[1]
    app.select_slider(key="cfg_p:pipeline:core:min_fitness").set_value(0.9)
    ok(app.run())
    assert counter.calls["register"] == 0 and counter.calls["frame"] == 0, counter.calls
    assert selected_cells(app)[1] < matched_before
    assert_matches_pipeline(app, registry, data_root / "laptop_articulate")
    app.select_slider(key="cfg_p:pipeline:core:min_fitness").set_value(0.3)
    ok(app.run())
    assert selected_cells(app)[1] == matched_before
    # Moving x re-registers the pairs, but does not segment or preprocess again.
    app.checkbox(key="cfg_auto:pipeline:core:cell_size_m").uncheck().run()
    app.select_slider(key="cfg_p:pipeline:core:cell_size_m").set_value(0.03)
    ok(app.run())
    assert counter.calls["register"] > 0 and counter.calls["frame"] == 0, counter.calls
    assert_matches_pipeline(app, registry, data_root / "laptop_articulate")


def test_k_changes_the_pairs_and_w_only_the_filter(app, monkeypatch):
    ok(app.run())
    assert len(timeline_decisions(app)) == N_FRAMES - 5
    counter = CallCounter(monkeypatch, "frame", "register")
    app.select_slider(key="cfg_p:pipeline:core:k").set_value(3)
    ok(app.run())
    assert len(timeline_decisions(app)) == N_FRAMES - 3
    assert counter.calls["frame"] == 0          # the frames are cached; only new pairs are registered
    app.select_slider(key="cfg_p:pipeline:core:w").set_value(1)
    registered = counter.calls["register"]
    ok(app.run())
    filtered = next(t for t in chart(app, "pair decision")["data"] if t["name"].startswith("filtered"))
    decided = [d for d in timeline_decisions(app) if d != "skipped"]
    assert array(filtered["y"]) == decided             # w = 1: the filter changes nothing
    assert counter.calls["register"] == registered


def test_reset_restores_the_defaults(app):
    ok(app.run())
    app.select_slider(key="cfg_p:pipeline:core:k").set_value(2).run()
    assert app.session_state["cfg_p:pipeline:core:k"] == 2
    app.button(key="cfg_reset").click().run()
    ok(app)
    assert app.session_state["cfg_p:pipeline:core:k"] == PipelineParams().k
    assert len(timeline_decisions(app)) == N_FRAMES - PipelineParams().k


def test_bad_folder_is_an_error_message_and_the_app_keeps_working(app, data_root):
    ok(app.run())
    open_folder(app, data_root / "no_such_sequence")
    assert not app.exception
    assert any("no such file or folder" in e for e in errors(app)), errors(app)
    open_folder(app, data_root)   # holds two sequences but is not one: no reader recognises it
    assert any("not a sequence that any reader recognises" in e for e in errors(app)), errors(app)
    open_folder(app, data_root / "mug_carry")
    ok(app)
    assert [t.value for t in app.title] == ["mug_carry"]


def test_a_corrupt_frame_is_an_error_message(app, data_root, tmp_path, monkeypatch):
    """The app reads frames on several threads: a corrupt one still ends the run with a message that
    names it, and no traceback."""
    seq = tmp_path / "root" / "mug_carry"
    shutil.copytree(data_root / "mug_carry", seq)
    bad = sorted((seq / "rgb").iterdir())[3]
    bad.write_bytes(b"not an image")
    monkeypatch.setenv("ARTCLASS_DATA_ROOTS", str(tmp_path / "root"))
    open_folder(ok(app.run()), seq)
    assert not app.exception
    assert any(bad.name in e for e in errors(app)), errors(app)


def test_path_outside_the_data_roots_is_refused(app, data_root, tmp_path):
    outside = tmp_path / "elsewhere"
    shutil.copytree(data_root / "mug_carry", outside)
    ok(app.run())
    for path in (outside, f"{data_root}/../{outside.name}", "/etc"):
        open_folder(app, path)
        assert not app.exception
        assert any("outside the data folders" in e for e in errors(app)), (path, errors(app))
    (data_root / "link_out").symlink_to(outside)
    try:
        open_folder(app, data_root / "link_out")
        assert any("outside the data folders" in e for e in errors(app)), errors(app)
    finally:
        (data_root / "link_out").unlink()


def test_data_roots_from_the_environment(app, data_root, tmp_path, monkeypatch):
    other = tmp_path / "other_root"
    shutil.copytree(data_root / "mug_carry", other / "mug_carry")
    monkeypatch.setenv("ARTCLASS_DATA_ROOTS", str(other))
    open_folder(ok(app.run()), other / "mug_carry")
    ok(app)
    open_folder(app, data_root / "mug_carry")   # the samples are not a root any more
    assert any("outside the data folders" in e for e in errors(app)), errors(app)


def test_real_ycb_video_scene_through_the_folder_source(app, shared_data, monkeypatch, registry):
    """A real recording (YCB-Video scene 0000, one sequence per object) opened as a user would."""
    monkeypatch.setenv("ARTCLASS_DATA_ROOTS", str(shared_data))
    scene = shared_data / "ycbv" / "0000"
    open_folder(ok(app.run()), scene)
    ok(app)
    names = app.selectbox(key="an_seqname").options
    assert names == [s.name for s in open_sequences(registry, scene)] and len(names) == 3
    assert [t.value for t in app.title] == [names[0]]
    app.selectbox(key="an_seqname").set_value(names[1])
    ok(app.run())
    assert [t.value for t in app.title] == [names[1]]
    assert_matches_pipeline(app, registry, Path(f"{scene}#{names[1].split('/')[-1]}"))


def _copy(data_root: Path, name: str, dest: Path) -> Path:
    shutil.copytree(data_root / name, dest)
    return dest


def test_missing_intrinsics_is_reported_with_the_file(app, data_root, tmp_path, monkeypatch):
    seq = _copy(data_root, "mug_carry", tmp_path / "roots" / "no_fx")
    meta = json.loads((seq / "meta.json").read_text())
    del meta["fx"]
    (seq / "meta.json").write_text(json.dumps(meta))
    monkeypatch.setenv("ARTCLASS_DATA_ROOTS", str(tmp_path / "roots"))
    open_folder(ok(app.run()), seq)
    assert not app.exception
    assert any("meta.json" in e and "'fx'" in e for e in errors(app)), errors(app)


def test_no_object_found_is_an_error_message(app, data_root, tmp_path, monkeypatch):
    seq = _copy(data_root, "mug_carry", tmp_path / "roots" / "empty_masks")
    import cv2
    for mask in sorted((seq / "mask").iterdir()):
        image = cv2.imread(str(mask), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(mask), np.zeros_like(image))
    monkeypatch.setenv("ARTCLASS_DATA_ROOTS", str(tmp_path / "roots"))
    open_folder(ok(app.run()), seq)
    app.selectbox(key="cfg_plugin:segmenter").set_value("mask").run()
    assert not app.exception
    assert any("no object in any of the" in e for e in errors(app)), errors(app)


def test_too_few_frames_for_k_is_an_error_message(app):
    ok(app.run())
    app.select_slider(key="cfg_p:pipeline:core:k").set_value(N_FRAMES).run()
    assert not app.exception
    assert any(f"k = {N_FRAMES} needs at least {N_FRAMES + 1}" in e for e in errors(app)), errors(app)
    app.select_slider(key="cfg_p:pipeline:core:k").set_value(2).run()
    ok(app)


def _zip_folder(folder: Path, *, prefix: str = "") -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(folder.rglob("*")):
            zf.write(path, prefix + path.relative_to(folder).as_posix())
    return buf.getvalue()


def test_upload_a_zip_and_a_bad_zip(app, data_root, tmp_path):
    ok(app.run())
    app.sidebar.radio(key="an_source").set_value("Upload a zip").run()
    assert any("upload a zip" in e for e in errors(app))
    data = _zip_folder(data_root / "mug_carry", prefix="mug_carry/")
    app.get("file_uploader")[0].set_value(("mug_carry.zip", data, "application/zip"))
    ok(app.run())
    assert [t.value for t in app.title] == ["mug_carry"]
    extracted = list((tmp_path / "uploads").iterdir())
    assert len(extracted) == 1 and (extracted[0] / "mug_carry" / "meta.json").is_file()
    app.get("file_uploader")[0].set_value(("broken.zip", b"this is not a zip", "application/zip"))
    app.run()
    assert not app.exception
    assert any("broken.zip" in e and "not a readable zip file" in e for e in errors(app)), errors(app)


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
    assert z == [[expected["confusion"][t][p] for p in expected["confusion"][t]] for t in expected["confusion"]]
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


# -- uploads.py: zip limits and path confinement -------------------------------------------------------------
def _zip(entries: dict[str, bytes], *, symlinks: dict[str, str] | None = None) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in entries.items():
            zf.writestr(name, data)
        for name, target in (symlinks or {}).items():
            info = zipfile.ZipInfo(name)
            info.external_attr = (stat.S_IFLNK | 0o777) << 16
            zf.writestr(info, target)
    return buf.getvalue()


def test_extract_zip_extracts_inside_the_folder(tmp_path):
    dest = uploads.extract_zip(_zip({"seq/meta.json": b"{}", "seq/rgb/0.png": b"x" * 10}), tmp_path / "out")
    assert (dest / "seq" / "meta.json").read_bytes() == b"{}"
    assert (dest / "seq" / "rgb" / "0.png").stat().st_size == 10


@pytest.mark.parametrize("entries, symlinks, problem", [
    ({"../evil.txt": b"x"}, None, "points outside the folder"),
    ({"seq/../../evil.txt": b"x"}, None, "points outside the folder"),
    ({"/etc/evil.txt": b"x"}, None, "absolute path"),
    ({"C:/evil.txt": b"x"}, None, "absolute path"),
    ({"..\\evil.txt": b"x"}, None, "points outside the folder"),
    ({"ok.txt": b"x"}, {"seq/link": "/etc/passwd"}, "symbolic link"),
])
def test_extract_zip_refuses_escaping_entries(tmp_path, entries, symlinks, problem):
    with pytest.raises(InputError, match=problem) as err:
        uploads.extract_zip(_zip(entries, symlinks=symlinks), tmp_path / "out", name="upload.zip")
    assert err.value.path == "upload.zip"
    assert not (tmp_path / "out").exists()
    assert not (tmp_path / "evil.txt").exists()


def test_extract_zip_limits(tmp_path):
    many = _zip({f"f{i}.txt": b"x" for i in range(11)})
    with pytest.raises(InputError, match="holds 11 entries; the limit is 10"):
        uploads.extract_zip(many, tmp_path / "a", max_files=10)
    big = _zip({"big.bin": b"\0" * 2_000_000})     # compresses to a few kB
    assert len(big) < 50_000
    with pytest.raises(InputError, match="the limit is 1.0 MB"):
        uploads.extract_zip(big, tmp_path / "b", max_total_bytes=1_000_000)
    with pytest.raises(InputError, match="not a readable zip file"):
        uploads.extract_zip(b"PK\x03\x04 truncated", tmp_path / "c")
    assert not any((tmp_path / d).exists() for d in "abc")
    uploads.extract_zip(many, tmp_path / "d", max_files=11)   # at the limit: fine
    assert len(list((tmp_path / "d").iterdir())) == 11


def test_extract_upload_is_content_addressed_and_pruned(tmp_path):
    data = _zip({"seq/meta.json": b"{}"})
    first = uploads.extract_upload(data, name="a.zip", root=tmp_path)
    again = uploads.extract_upload(data, name="b.zip", root=tmp_path)
    assert first == again and (first / "seq" / "meta.json").is_file()
    other = uploads.extract_upload(_zip({"x.txt": b"1"}), name="c.zip", root=tmp_path)
    assert other != first
    old = time.time() - 3 * 24 * 3600
    os.utime(first, (old, old))
    assert uploads.prune(tmp_path, max_age_s=24 * 3600) == [first]
    assert not first.exists() and other.exists()


def test_confine(tmp_path):
    root = tmp_path / "root"
    (root / "seq").mkdir(parents=True)
    (tmp_path / "outside").mkdir()
    (root / "escape").symlink_to(tmp_path / "outside")
    assert uploads.confine(str(root / "seq"), [root]) == str((root / "seq").resolve())
    assert uploads.confine("seq", [root]) == str((root / "seq").resolve())
    assert uploads.confine(f"{root}/seq#obj_1", [root]) == f"{(root / 'seq').resolve()}#obj_1"
    for bad in (str(tmp_path / "outside"), f"{root}/../outside", "../outside", str(root / "escape"), "/"):
        with pytest.raises(InputError, match="outside the data folders"):
            uploads.confine(bad, [root])
    with pytest.raises(InputError, match="no folder given"):
        uploads.confine("  ", [root])
    with pytest.raises(InputError, match="no data folders are configured"):
        uploads.confine(str(root), [])


def test_data_roots(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    assert uploads.data_roots(["--data-root", str(a), "-x", "--data-root", str(b)], {}) == [a, b]
    assert uploads.data_roots([], {"ARTCLASS_DATA_ROOTS": f"{a}{os.pathsep}{b}"}) == [a, b]
    assert uploads.data_roots(["tests/test_app.py", "-q"], {}, default=[a]) == [a]
    assert uploads.data_roots(["--data-root", str(a)], {"ARTCLASS_DATA_ROOTS": str(b)}) == [a, b]


# -- runner.py: the staged run is Pipeline.run -------------------------------------------------------------
@pytest.fixture(scope="module")
def laptop(registry, data_root):
    return open_sequences(registry, data_root / "laptop_articulate")[0]


@pytest.fixture(scope="module")
def laptop_run(registry, laptop):
    return Pipeline(registry, Config()).run(laptop, keep_clouds=True)


@pytest.mark.parametrize("rule, min_fitness, workers", [("paper", 0.3, 1), ("paper", 0.95, 2), (None, 0.3, 2),
                                                        (None, 0.95, 1)])
def test_run_staged_equals_pipeline_run(registry, laptop, rule, min_fitness, workers):
    """Through the stage pipelines and the fitness check at decision time, as the app runs, on one
    thread or two. A tight ICP correspondence distance spreads the cells' fitness below 1, so
    min_fitness rejects some."""
    icp = registry.get("registrar", "icp_point_to_point").Params(max_correspondence_cells=0.1)
    config = Config(rule=rule or Config().rule, registrar="icp_point_to_point", registrar_params=icp,
                    pipeline=PipelineParams(k=3, w=1, min_fitness=min_fitness))
    expected = Pipeline(registry, config).run(laptop)
    stage = {s: Pipeline(registry, runner.stage_config(config, s)) for s in ("frame", "register", "decide")}
    seen = []
    result = runner.run_staged(
        laptop, config, Pipeline(registry, config), frame=lambda i: stage["frame"].frame(laptop, i),
        register=lambda a, b: stage["register"].register(a.cloud, b.cloud),
        decide=lambda a, b, cells, x, between: runner.decide_registered(
            stage["decide"], a.index, b.index, cells, a.cloud, b.cloud, x, tuple(f.cloud for f in between)),
        progress=lambda stage_, done, total: seen.append((stage_, done, total)), workers=workers)
    assert result.label == expected.label and result.filtered == expected.filtered
    assert [p.decision for p in result.pairs] == [p.decision for p in expected.pairs]
    assert [[c.skipped for c in p.cells] for p in result.pairs] == [[c.skipped for c in p.cells] for p in expected.pairs]
    assert [[c.cluster for c in p.cells] for p in result.pairs] == [[c.cluster for c in p.cells] for p in expected.pairs]
    assert [p.truth for p in result.pairs] == [p.truth for p in expected.pairs]
    assert result.fractions == expected.fractions
    if min_fitness == 0.95:   # the check at decision time did reject cells
        assert any(str(c.skipped).startswith("low fitness") for p in result.pairs for c in p.cells)
    assert ("frames", N_FRAMES, N_FRAMES) in seen and ("decision", N_FRAMES - 3, N_FRAMES - 3) in seen
    with pytest.raises(InputError, match="needs at least"):
        runner.run_staged(laptop, Config(pipeline=PipelineParams(k=N_FRAMES)), stage["decide"], frame=None,
                          register=None, decide=None)


def test_stage_keys_depend_on_what_the_stage_uses():
    base = Config(rule="paper")
    keys = {s: runner.stage_key(base, s) for s in ("frame", "register", "decide")}

    def changed(config):
        return {s for s in keys if runner.stage_key(config, s) != keys[s]}

    from artclass_plugins.rules.paper import PaperRuleParams
    assert changed(Config(rule="paper", rule_params=PaperRuleParams(q_bar=0.5))) == {"decide"}
    assert changed(Config(rule="paper", pipeline=PipelineParams(alpha=0.9))) == {"decide"}
    assert changed(Config(rule="paper", pipeline=PipelineParams(min_fitness=0.9))) == {"decide"}
    assert changed(Config(rule="paper", pipeline=PipelineParams(w=7))) == set()
    assert changed(Config(rule="paper", pipeline=PipelineParams(k=2))) == set()
    assert changed(Config(rule="paper", pipeline=PipelineParams(cell_size_m=0.02))) == {"register", "decide"}
    assert changed(Config(rule="paper", registrar="icp_point_to_plane")) == {"register", "decide"}
    assert changed(Config(rule="paper", pipeline=PipelineParams(min_cell_points=20))) == {"frame", "register", "decide"}
    assert changed(Config(rule="paper", segmenter="mask")) == {"frame", "register", "decide"}


# -- controls.py: sliders from the metadata ----------------------------------------------------------------
def test_slider_options_hold_every_default_within_bounds(registry):
    classes = [PipelineParams] + [registry.get(kind, name).Params for kind in ("segmenter", "preprocessor", "registrar",
                                                                               "rule") for name in registry.names(kind)]
    n_sliders = 0
    for cls in classes:
        for spec in describe(cls):
            if controls.widget_kind(spec) != "slider":
                continue
            n_sliders += 1
            options = controls.slider_options(spec)
            low, high = spec.bounds
            assert options == sorted(options) and len(set(options)) == len(options), spec.name
            assert low <= options[0] and options[-1] <= high, spec.name
            assert 2 <= len(options) <= 1000, (spec.name, len(options))
            if spec.default is not None:
                assert spec.default in options, spec.name
            assert all(isinstance(v, spec.type) for v in options), spec.name
    assert n_sliders >= 8


def test_slider_options_shapes():
    specs = {s.name: s for s in describe(PipelineParams)}
    x = controls.slider_options(specs["cell_size_m"])         # 0.1 mm .. 10 m: logarithmic
    assert x[0] == pytest.approx(1e-4) and x[-1] == 10.0 and 0.03 in x and 40 < len(x) < 80
    alpha = controls.slider_options(specs["alpha"])          # a fraction: even steps of 0.01
    assert alpha[:3] == [0.0, 0.01, 0.02] and alpha[-1] == 1.0 and 0.3 in alpha
    k = controls.slider_options(specs["k"])
    assert k[:21] == list(range(1, 22)) and k[-1] == 1000
    assert controls.nearest_option(x, 0.0317) == 0.03
    assert controls.format_value(specs["cell_size_m"], 0.005) == "5 mm"
    assert controls.format_value(specs["k"], 5) == "5 frames"
    assert controls.format_value(specs["cell_size_m"], None) == "auto"
    assert controls.label(specs["alpha"]) == "α · alpha" and controls.label(specs["k"]) == "k"


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


def test_motion_arrows_one_cone_per_matched_cell(laptop_run):
    pair = next(p for p in laptop_run.pairs if p.decision != "skipped")
    source, target = laptop_run.frames[pair.i].cloud, laptop_run.frames[pair.j].cloud
    fig = figures.motion_arrows(pair, source, target, magnify=1.0)
    cones = [t for t in fig.data if t.type == "cone"]
    matched = [c for c in pair.cells if c.matched]
    assert sum(len(t.x) for t in cones) == len(matched)
    assert len(cones) == len({c.cluster for c in matched})      # one colour (trace) per cluster
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
            assert row["displacement_mm"] == pytest.approx(1000 * np.linalg.norm(d["centre_displacement_m"]), abs=0.01)
            assert row["rotation_deg"] == pytest.approx(d["rotation_deg"], abs=1e-3)
        else:
            assert row["fitness"] is None
    json.dumps(rows)   # JSON-ready


def test_frame_images_with_hand_overlays_the_hand(laptop):
    frame = laptop[0]
    hand = np.zeros(frame.depth_m.shape, bool)
    hand[:20, :30] = True
    plain = figures.frame_images(frame, frame.mask)
    fig = figures.frame_images_with_hand(frame, frame.mask, hand)
    assert "hand (600 px)" in fig.layout.annotations[0].text
    assert fig.data[0].source != plain.data[0].source
    assert figures.frame_images_with_hand(frame, frame.mask, None).data[0].source == plain.data[0].source


def test_analyse_offers_hand_exclusion_with_a_mask_free_segmenter(app):
    ok(app.run())
    app.selectbox(key="cfg_plugin:segmenter").set_value("depth_threshold")
    ok(app.run())
    box = app.checkbox(key=controls.value_key("segmenter", "depth_threshold", "exclude_hands"))
    assert box.value is True and any(c.key.startswith("an_frame_") for c in app.get("plotly_chart"))


def test_confusion_figure_and_html_export(registry, laptop, laptop_run):
    metrics = evaluate(registry, [laptop], Config()).metrics()
    fig = figures.confusion_figure(metrics)
    (heat,) = fig.data
    assert list(heat.y) == list(metrics["confusion"])
    assert [list(r) for r in heat.z] == [list(metrics["confusion"][t].values()) for t in metrics["confusion"]]
    assert sum(map(sum, heat.z)) == 1
    page = figures.figures_html({"timeline": figures.decision_timeline(laptop_run), "confusion": fig}, title="t")
    assert page.count("<h2>") == 2 and page.count('class="plotly-graph-div"') == 2
    assert page.count("* plotly.js v") == 1 and 'src="https://' not in page   # plotly.js embedded once: offline
