"""``artclass live``: frames classified as they arrive, from a bag played through the readers or a
RealSense recording played by the RealSense SDK (no camera); the frames recorded to a folder replay
to the same decisions; no camera and no file is one line and exit status 2."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest
from test_bag import classify_json, run_cli

from artclass_core import Frame, InputError, Intrinsics, open_sequences
from artclass_plugins.live import LiveSequence, StreamEnded, classify_live, open_source
from artclass_plugins.live.sources import SequenceSource, has_realsense
from artclass_plugins.readers.bag import write_bag

N_FRAMES = 12
SIZE = dict(width=160, height=120)


@pytest.fixture(scope="module")
def laptop_bag(rendered, registry, tmp_path_factory):
    """A small articulated sequence (folder) and the same frames as a ROS 1 bag."""
    folder = rendered("laptop", "articulate", n_frames=N_FRAMES, **SIZE)
    seq = open_sequences(registry, folder)[0]
    bag = tmp_path_factory.mktemp("live") / "laptop.bag"
    return folder, write_bag([seq[i] for i in range(len(seq))], bag, intrinsics=seq.intrinsics), seq


class Trickle:
    """A source that sends its frames only when told to (a camera that has not sent them yet)."""

    def __init__(self, n: int):
        self.name, self.path, self.n_frames = "trickle", Path("trickle"), None
        self.intrinsics = Intrinsics(50.0, 50.0, 3.5, 2.5, width=8, height=6)
        self.n, self.go, self.closed = n, threading.Semaphore(0), False

    def frames(self):
        for i in range(self.n):
            self.go.acquire()
            yield Frame(i, f"{i:06d}", np.full((6, 8, 3), i, np.uint8), np.full((6, 8), 1.0, np.float32))

    def close(self):
        self.closed = True


def test_live_sequence_waits_for_frames_and_ends_with_the_source():
    source = Trickle(3)
    seq = LiveSequence(source, keep=4)
    got = []
    reader = threading.Thread(target=lambda: got.append(seq[1].rgb[0, 0, 0]))
    reader.start()
    reader.join(timeout=0.2)
    assert reader.is_alive() and not got, "frame 1 is not there before the source sends it"
    source.go.release()
    source.go.release()
    reader.join(timeout=5)
    assert got == [1]
    source.go.release()
    assert seq[2].rgb[0, 0, 0] == 2
    with pytest.raises(StreamEnded, match="ended after 3 frames"):
        seq[3]
    seq.stop()
    assert source.closed


def test_live_source_error_reaches_the_classifier():
    class Broken(Trickle):
        def frames(self):
            raise InputError("the camera went away")
            yield

    seq = LiveSequence(Broken(1))
    with pytest.raises(InputError, match="went away"):
        seq[0]
    seq.stop()


@pytest.mark.slow
def test_live_bag_decides_as_classify_and_records_a_replayable_folder(laptop_bag, tmp_path, capsys):
    """Played through the readers, a bag gives every pair and the label ``classify`` gives; the frames
    recorded on the way replay to the same decisions."""
    _folder, bag, _seq = laptop_bag
    record = tmp_path / "rec"
    status, out, err = run_cli(
        capsys, "live", "--source", bag, "--record", record, "--json", "--player", "reader"
    )
    assert status == 0, err
    live = json.loads(out)
    runs = [live] + [classify_json(capsys, where) for where in (bag, record)]
    decisions = [[(p["i"], p["j"], p["decision"]) for p in r["pairs"]] for r in runs]
    assert decisions[0] == decisions[1] == decisions[2]
    assert live["label"] == runs[1]["label"] == "articulated"
    assert len(list((record / "rgb").iterdir())) == N_FRAMES


def test_live_prints_the_running_decision(laptop_bag, capsys):
    _folder, bag, _seq = laptop_bag
    status, out, err = run_cli(
        capsys,
        "live",
        "--source",
        bag,
        "--player",
        "reader",
        "--param",
        "k=2",
        "--param",
        "slow_factor=1",
        "--max-frames",
        4,
    )
    assert status == 0, err
    lines = out.strip().splitlines()
    assert [line.split()[1:4] for line in lines[:2]] == [["0", "->", "2"], ["1", "->", "3"]]
    assert all("so far:" in line for line in lines[:2])
    assert lines[2].startswith("laptop: ") and "(4 frames, 2 pairs)" in lines[2]


def test_record_refuses_a_folder_with_data(laptop_bag, tmp_path, capsys):
    _folder, bag, _seq = laptop_bag
    kept = tmp_path / "mine"
    kept.mkdir()
    (kept / "notes.txt").write_text("keep me")
    status, out, err = run_cli(capsys, "live", "--source", bag, "--player", "reader", "--record", kept)
    assert status == 2 and len(err.strip().splitlines()) == 1 and "record into a new one" in err
    assert [p.name for p in kept.iterdir()] == ["notes.txt"] and (kept / "notes.txt").read_text() == "keep me"


def test_no_camera_and_no_file_is_one_line(capsys):
    status, out, err = run_cli(capsys, "live")
    assert status == 2 and out == "" and len(err.strip().splitlines()) == 1
    assert ("no RealSense camera is connected" if has_realsense() else "artclass[realsense]") in err


def test_classify_live_stops_at_max_frames(laptop_bag, registry):
    _folder, bag, _seq = laptop_bag
    from artclass_core import Config

    config = Config(segmenter="depth_threshold").with_overrides(registry, {"k": "2", "slow_factor": "1"})
    updates = list(
        classify_live(registry, open_source(registry, str(bag), player="reader"), config, max_frames=5)
    )
    assert [(u.pair.i, u.pair.j) for u in updates] == [(0, 2), (1, 3), (2, 4)]
    last = updates[-1]
    assert last.result.pairs[-1] is last.pair and last.target.cloud is not None
    assert updates[0].pair.evidence is None, "only the latest pair keeps its evidence"


def test_sequence_source_plays_every_frame(laptop_bag, registry):
    _folder, bag, seq = laptop_bag
    source = open_source(registry, str(bag), player="reader")
    assert isinstance(source, SequenceSource) and source.n_frames == len(seq)
    frames = list(source.frames())
    assert [f.index for f in frames] == list(range(len(seq)))
    assert np.array_equal(frames[5].rgb, seq[5].rgb)


@pytest.mark.slow
def test_live_plays_a_realsense_recording_through_the_sdk(laptop_bag, registry, tmp_path, capsys):
    """The SDK plays a recording as if it were the camera (rs.align included): artclass live runs end
    to end on it, each frame it sends is a frame of the recording, and the label is classify's."""
    pytest.importorskip("pyrealsense2", reason="pyrealsense2 (the realsense extra) is not installed")
    from test_bag_realsense import sdk_record

    folder, _bag, seq = laptop_bag
    path = sdk_record([seq[i] for i in range(len(seq))], tmp_path / "laptop.db3", seq.intrinsics)
    source = open_source(registry, str(path))  # auto: the SDK plays its own recordings
    assert type(source).__name__ == "RealSenseSource"
    sent = list(source.frames())
    source.close()
    assert len(sent) >= N_FRAMES - 2  # the SDK leaves out a frame it cannot match into a set
    first = next(i for i in range(3) if np.array_equal(sent[0].rgb, seq[i].rgb))
    assert all(np.array_equal(f.rgb, seq[first + f.index].rgb) for f in sent)
    status, out, err = run_cli(capsys, "live", "--source", path, "--json")
    assert status == 0, err
    assert json.loads(out)["label"] == "articulated"


@pytest.mark.slow
def test_live_page_grows_the_timeline(app, laptop_bag, monkeypatch):
    """The app's live page plays a bag under a data root: decision, pairs and the final label."""
    from app_helpers import errors, metric, ok

    _folder, bag, _seq = laptop_bag
    monkeypatch.setenv("ARTCLASS_DATA_ROOTS", str(bag.parent))
    ok(app.run())
    app.switch_page("app_pages/live.py")
    ok(app.run())
    app.text_input(key="lv_path").set_value(str(bag))
    app.button(key="lv_start").click()
    ok(app.run())
    assert metric(app, "Decision so far") == "articulated"
    assert metric(app, "Pairs") == str(N_FRAMES - 5)
    assert any("laptop: articulated" in s.value for s in app.success), [s.value for s in app.success]
    assert len(app.get("plotly_chart")) == 2  # the timeline and the latest pair's 3D view
    app.text_input(key="lv_path").set_value("/etc/passwd").run()
    assert any("outside the data folders" in e for e in errors(app)), errors(app)
