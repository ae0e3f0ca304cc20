"""The analyse page through ``streamlit.testing.v1.AppTest``: opening sequences, the sliders and
what they re-run, error messages, uploads."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from streamlit.testing.v1 import AppTest

from app import controls
from artclass_core import Config, Pipeline, PipelineParams, open_sequences

from app_helpers import (
    APP,
    N_FRAMES,
    ROOT,
    TIMEOUT,
    CallCounter,
    array,
    assert_matches_pipeline,
    chart,
    copy_sequence,
    errors,
    metric,
    ok,
    open_folder,
    selected_cells,
    timeline_decisions,
    use_paper_rule,
    zip_folder,
)

pytestmark = pytest.mark.slow  # the app's page runs (AppTest), each a whole sequence


# -- the analyse page ------------------------------------------------------------------------------------
def test_opens_on_the_bundled_samples_with_no_configuration(monkeypatch):
    for name in ("ARTCLASS_SAMPLE_DATA", "ARTCLASS_DATA_ROOTS"):
        monkeypatch.delenv(name, raising=False)
    samples = ROOT / "sample_data"
    assert samples.is_dir(), f"{samples} is missing: the bundled samples are part of the repository"
    folders = sorted(p for p in samples.iterdir() if (p / "meta.json").is_file())
    first = next(
        p for p in folders if json.loads((p / "meta.json").read_text()).get("label") == "articulated"
    )
    at = ok(AppTest.from_file(APP, default_timeout=TIMEOUT).run())
    assert [t.value for t in at.title] == [first.name]
    options = at.selectbox(key="an_sample").options  # shown as "name  (label)"
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
    assert sum(len(array(t["x"])) for t in spec["data"] if t["type"] == "cone") == sum(
        m.n_points > 0 for m in pair.motions
    )
    assert (
        len([e for e in app.get("plotly_chart") if not e.key.startswith("an_joints_")]) == 4
    )  # timeline, 3D, two frames
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
    # No frame is read again; the only registrations are the longer pairs (i, i + slow_factor k) of
    # pairs that newly show no motion, one at most per pair that has frames that far.
    pipeline = Config().pipeline
    reach = N_FRAMES - pipeline.k * pipeline.slow_factor
    assert counter.calls["frame"] == 0 and counter.calls["register"] <= reach, counter.calls
    registered = counter.calls["register"]
    assert counter.calls["decide"] > 0
    assert_matches_pipeline(app, registry, data_root / "laptop_articulate")
    # min_fitness is checked when deciding: no ICP either, yet the cells it rejects change.
    matched_before = selected_cells(app)[1]
    app.select_slider(key="cfg_p:pipeline:core:min_fitness").set_value(0.9)
    ok(app.run())
    assert counter.calls["register"] == registered and counter.calls["frame"] == 0, counter.calls
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
    assert counter.calls["frame"] == 0  # the frames are cached; only new pairs are registered
    app.select_slider(key="cfg_p:pipeline:core:w").set_value(1)
    registered = counter.calls["register"]
    ok(app.run())
    filtered = next(t for t in chart(app, "pair decision")["data"] if t["name"].startswith("filtered"))
    decided = [d for d in timeline_decisions(app) if d != "skipped"]
    assert array(filtered["y"]) == decided  # w = 1: the filter changes nothing
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
    open_folder(app, data_root)  # holds two sequences but is not one: no reader recognises it
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
    open_folder(app, data_root / "mug_carry")  # the samples are not a root any more
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


def test_missing_intrinsics_is_reported_with_the_file(app, data_root, tmp_path, monkeypatch):
    seq = copy_sequence(data_root, "mug_carry", tmp_path / "roots" / "no_fx")
    meta = json.loads((seq / "meta.json").read_text())
    del meta["fx"]
    (seq / "meta.json").write_text(json.dumps(meta))
    monkeypatch.setenv("ARTCLASS_DATA_ROOTS", str(tmp_path / "roots"))
    open_folder(ok(app.run()), seq)
    assert not app.exception
    assert any("meta.json" in e and "'fx'" in e for e in errors(app)), errors(app)


def test_no_object_found_is_an_error_message(app, data_root, tmp_path, monkeypatch):
    seq = copy_sequence(data_root, "mug_carry", tmp_path / "roots" / "empty_masks")
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


def test_upload_a_zip_and_a_bad_zip(app, data_root, tmp_path):
    ok(app.run())
    app.sidebar.radio(key="an_source").set_value("Upload a zip").run()
    assert any("upload a zip" in e for e in errors(app))
    data = zip_folder(data_root / "mug_carry", prefix="mug_carry/")
    app.get("file_uploader")[0].set_value(("mug_carry.zip", data, "application/zip"))
    ok(app.run())
    assert [t.value for t in app.title] == ["mug_carry"]
    extracted = list((tmp_path / "uploads").iterdir())
    assert len(extracted) == 1 and (extracted[0] / "mug_carry" / "meta.json").is_file()
    app.get("file_uploader")[0].set_value(("broken.zip", b"this is not a zip", "application/zip"))
    app.run()
    assert not app.exception
    assert any("broken.zip" in e and "not a readable zip file" in e for e in errors(app)), errors(app)


def test_analyse_offers_hand_exclusion_with_a_mask_free_segmenter(app):
    ok(app.run())
    app.selectbox(key="cfg_plugin:segmenter").set_value("depth_threshold")
    ok(app.run())
    box = app.checkbox(key=controls.value_key("segmenter", "depth_threshold", "exclude_hands"))
    assert box.value is True and any(c.key.startswith("an_frame_") for c in app.get("plotly_chart"))
