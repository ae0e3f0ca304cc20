"""Bad input gives one clear line naming the file and the problem, exit status 2, no traceback, and
nothing is ever written into the input folder.

Each case builds a small sequence in one of the supported layouts (tests/fixtures_layouts.py), spoils
it the way a user's data can be spoilt, runs the real command line (``artclass_core.cli.main``) and
checks stdout/stderr at the file-descriptor level (so a library printing behind Python's back would
show up too).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io

from artclass_core.cli import main

from fixtures_layouts import (
    snapshot,
    write_camera_info,
    write_folder,
    write_png,
    write_rbo,
    write_tum,
    write_ycbv,
)


def run(capfd, argv: list[str], *, watch: Path) -> tuple[int, str, str]:
    """Run the CLI; assert that nothing under ``watch`` was created, removed or changed."""
    before = snapshot(watch)
    listing = sorted(p.relative_to(watch) for p in watch.rglob("*"))
    code = main([str(a) for a in argv])
    out, err = capfd.readouterr()
    assert snapshot(watch) == before, "the run changed files in the input folder"
    assert sorted(p.relative_to(watch) for p in watch.rglob("*")) == listing, (
        "the run created files or folders"
    )
    return code, out, err


def assert_error(code: int, out: str, err: str, *, path: Path | None, problem: str) -> str:
    """Exit status 2 and exactly one line ``artclass: error: [<path>: ]<problem>`` on stderr."""
    assert code == 2, f"exit status {code}; stderr: {err}"
    assert "Traceback" not in err and "Traceback" not in out
    assert out == ""
    lines = err.splitlines()
    assert len(lines) == 1, f"expected one line on stderr, got:\n{err}"
    line = lines[0]
    prefix = "artclass: error: " + (f"{path}: " if path is not None else "")
    assert line.startswith(prefix), f"{line!r} does not start with {prefix!r}"
    assert re.search(problem, line[len(prefix) :]), f"{line!r} does not say {problem!r}"
    return line


def truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def small_rgb(path: Path) -> None:
    write_png(path, np.full((24, 32, 3), 128, np.uint8))


def eight_bit(path: Path) -> None:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    write_png(path, (image // 256).astype(np.uint8))


def edit_json(path: Path, **changes) -> None:
    data = json.loads(path.read_text())
    for key, value in changes.items():
        if value is None:
            data.pop(key, None)
        else:
            data[key] = value
    path.write_text(json.dumps(data))


# -- the path itself ------------------------------------------------------------------------------------
def test_missing_path(tmp_path, capfd):
    missing = tmp_path / "no_such_sequence"
    assert_error(
        *run(capfd, ["classify", missing], watch=tmp_path), path=missing, problem="no such file or folder"
    )


def test_missing_root_for_evaluate(tmp_path, capfd):
    missing = tmp_path / "no_such_root"
    assert_error(*run(capfd, ["evaluate", missing], watch=tmp_path), path=missing, problem="no such folder")


def test_folder_no_reader_recognises(tmp_path, capfd):
    (tmp_path / "notes.txt").write_text("some text, no images\n")
    (tmp_path / "frames").mkdir()
    write_png(tmp_path / "frames" / "0.png", np.zeros((8, 8, 3), np.uint8))
    assert_error(
        *run(capfd, ["classify", tmp_path], watch=tmp_path),
        path=tmp_path,
        problem=r"not a sequence that any reader recognises \(tried: bag, folder, .*rbo.*tum.*ycbv",
    )


def test_unknown_sequence_name(tmp_path, capfd):
    scene = write_ycbv(tmp_path, n_frames=3)
    assert_error(
        *run(capfd, ["classify", f"{scene}#banana"], watch=tmp_path),
        path=scene,
        problem="no sequence named 'banana'; found: 0000/025_mug, 0000/061_foam_brick",
    )


# -- intrinsics -----------------------------------------------------------------------------------------
def test_meta_json_without_fx(tmp_path, capfd):
    seq = write_folder(tmp_path)
    edit_json(seq / "meta.json", fx=None)
    assert_error(
        *run(capfd, ["classify", seq], watch=tmp_path), path=seq / "meta.json", problem="missing 'fx'"
    )


def test_meta_json_fx_zero(tmp_path, capfd):
    seq = write_folder(tmp_path)
    edit_json(seq / "meta.json", fx=0)
    assert_error(
        *run(capfd, ["classify", seq], watch=tmp_path),
        path=seq / "meta.json",
        problem=r"'fx' must be a positive finite number, got 0(\.0)?$",
    )


def test_meta_json_not_json(tmp_path, capfd):
    seq = write_folder(tmp_path)
    (seq / "meta.json").write_text('{"fx": 60, "fy": ')
    assert_error(
        *run(capfd, ["classify", seq], watch=tmp_path), path=seq / "meta.json", problem="not valid JSON"
    )


def test_meta_mat_without_intrinsic_matrix(tmp_path, capfd):
    scene = write_ycbv(tmp_path, n_frames=3, drop=("intrinsic_matrix",))
    assert_error(
        *run(capfd, ["classify", f"{scene}#025_mug"], watch=tmp_path),
        path=scene / "000001-meta.mat",
        problem="missing 'intrinsic_matrix'",
    )


def test_meta_mat_with_zero_focal_length(tmp_path, capfd):
    scene = write_ycbv(tmp_path, n_frames=3)
    meta = scipy.io.loadmat(scene / "000001-meta.mat")
    meta["intrinsic_matrix"][0, 0] = 0.0
    scipy.io.savemat(scene / "000001-meta.mat", {k: v for k, v in meta.items() if not k.startswith("__")})
    assert_error(
        *run(capfd, ["classify", f"{scene}#025_mug"], watch=tmp_path),
        path=scene / "000001-meta.mat",
        problem="fx=0, .*focal lengths must be positive",
    )


def test_rbo_without_camera_info(tmp_path, capfd):
    seq = write_rbo(tmp_path, camera_info=False)
    assert_error(
        *run(capfd, ["classify", seq], watch=tmp_path),
        path=seq,
        problem="no camera intrinsics: expected camera_rgb_camera_info.csv",
    )


def test_rbo_camera_info_fx_zero(tmp_path, capfd):
    seq = write_rbo(tmp_path)
    write_camera_info(seq / "camera_rgb_camera_info.csv", fx=0.0)
    assert_error(
        *run(capfd, ["classify", seq], watch=tmp_path),
        path=seq / "camera_rgb_camera_info.csv",
        problem="'field.K0' must be a positive finite number",
    )


def test_tum_meta_json_fx_zero(tmp_path, capfd):
    seq = write_tum(tmp_path, config=dict(fx=0, fy=60, cx=31.5, cy=23.5))
    assert_error(
        *run(capfd, ["classify", seq], watch=tmp_path),
        path=seq / "meta.json",
        problem="'fx' must be a positive finite number",
    )


# -- images -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("layout", ["folder", "ycbv", "tum", "rbo"])
def test_depth_and_rgb_of_different_sizes(layout, tmp_path, capfd):
    if layout == "folder":
        seq = write_folder(tmp_path)
        bad = seq / "rgb" / "000000.png"
        small_rgb(bad)
        target = seq
    elif layout == "ycbv":
        seq = write_ycbv(tmp_path)
        bad = seq / "000001-color.png"
        small_rgb(bad)
        target = f"{seq}#025_mug"
    elif layout == "tum":
        seq = write_tum(tmp_path)
        bad = sorted((seq / "rgb").glob("*.png"))[0]
        small_rgb(bad)
        target = seq
    else:
        seq = write_rbo(tmp_path)
        bad = sorted((seq / "camera_depth_registered").glob("*.txt"))[0]
        np.savetxt(bad, np.ones((24, 32)))
        target = seq
    line = assert_error(
        *run(capfd, ["classify", target], watch=tmp_path),
        path=bad,
        problem=r"is 32x24 but .* is 64x48|is 64x48 but .* is 32x24",
    )
    assert "32x24" in line and "64x48" in line


@pytest.mark.parametrize("which", ["rgb", "depth", "mask"])
def test_truncated_png_in_folder_format(which, tmp_path, capfd):
    seq = write_folder(tmp_path)
    bad = seq / which / "000000.png"
    truncate(bad)
    assert_error(
        *run(capfd, ["classify", seq], watch=tmp_path), path=bad, problem="unreadable or truncated image"
    )


@pytest.mark.parametrize("layout", ["ycbv", "tum", "rbo"])
def test_truncated_png_in_dataset_layouts(layout, tmp_path, capfd):
    if layout == "ycbv":
        seq = write_ycbv(tmp_path)
        bad, target = seq / "000001-label.png", f"{seq}#025_mug"
    elif layout == "tum":
        seq = write_tum(tmp_path)
        bad, target = sorted((seq / "depth").glob("*.png"))[0], seq
    else:
        seq = write_rbo(tmp_path)
        bad, target = sorted((seq / "camera_rgb").glob("*.png"))[0], seq
    truncate(bad)
    assert_error(
        *run(capfd, ["classify", target], watch=tmp_path), path=bad, problem="unreadable or truncated image"
    )


@pytest.mark.parametrize("layout", ["folder", "ycbv", "tum"])
def test_depth_that_is_not_16_bit(layout, tmp_path, capfd):
    if layout == "folder":
        seq = write_folder(tmp_path)
        bad, target = seq / "depth" / "000000.png", seq
    elif layout == "ycbv":
        seq = write_ycbv(tmp_path)
        bad, target = seq / "000001-depth.png", f"{seq}#025_mug"
    else:
        seq = write_tum(tmp_path)
        bad, target = sorted((seq / "depth").glob("*.png"))[0], seq
    eight_bit(bad)
    assert_error(
        *run(capfd, ["classify", target], watch=tmp_path),
        path=bad,
        problem="depth must be a single-channel 16-bit image, got uint8",
    )


def test_rbo_depth_that_is_not_a_matrix(tmp_path, capfd):
    seq = write_rbo(tmp_path)
    bad = sorted((seq / "camera_depth_registered").glob("*.txt"))[0]
    bad.write_text("0.8 0.8 0.8\n0.8 oops 0.8\n")
    assert_error(
        *run(capfd, ["classify", seq], watch=tmp_path), path=bad, problem="not a numeric depth matrix"
    )


def test_rbo_joint_states_not_numbers(tmp_path, capfd):
    seq = write_rbo(tmp_path)
    csv_path = seq / "flapbox_joint_states.csv"
    lines = csv_path.read_text().splitlines()
    lines[3] = lines[3].replace("j_0_1,", "j_0_1,open,")
    csv_path.write_text("\n".join(lines) + "\n")
    assert_error(
        *run(capfd, ["classify", seq], watch=tmp_path), path=csv_path, problem="line 4: .* not a number"
    )


def test_tum_list_line_without_timestamp(tmp_path, capfd):
    seq = write_tum(tmp_path)
    (seq / "depth.txt").write_text("# depth\ndepth/a.png 1305031102.0\n")
    assert_error(
        *run(capfd, ["classify", seq], watch=tmp_path),
        path=seq / "depth.txt",
        problem="line 2 is not 'timestamp filename'",
    )


# -- sequences the pipeline cannot use --------------------------------------------------------------
@pytest.mark.parametrize(
    "blank, dtype, problem",
    [
        ("mask", np.uint8, r"no object in any of the 8 frames \(segmenter 'mask': no object found"),
        # a mask over pixels the sensor did not read (a thin dark object under time of flight): the
        # error says how large the masks are and how few of their pixels have depth
        (
            "depth",
            np.uint16,
            r"only 0 object points from a mask of \d+ pixels, 0 of them with a depth reading",
        ),
    ],
)
def test_no_object_on_any_frame(tmp_path, capfd, blank, dtype, problem):
    seq = write_folder(tmp_path)
    for image in (seq / blank).glob("*.png"):
        write_png(image, np.zeros((48, 64), dtype))
    assert_error(
        *run(capfd, ["classify", seq, "--segmenter", "mask"], watch=tmp_path), path=seq, problem=problem
    )


def test_sequence_shorter_than_k_plus_one(tmp_path, capfd):
    seq = write_folder(tmp_path, n_frames=3)
    assert_error(
        *run(capfd, ["classify", seq], watch=tmp_path),
        path=seq,
        problem="sequence has 3 frames; k = 5 needs at least 6",
    )
    assert_error(
        *run(capfd, ["classify", seq, "--param", "k=4"], watch=tmp_path),
        path=seq,
        problem="sequence has 3 frames; k = 4 needs at least 5",
    )


# -- plugins and parameters ---------------------------------------------------------------------------
@pytest.mark.parametrize(
    "option,kind",
    [
        ("--rule", "rule"),
        ("--segmenter", "segmenter"),
        ("--registrar", "registrar"),
        ("--preprocessor", "preprocessor"),
        ("--reader", "reader"),
    ],
)
def test_unknown_plugin_name(option, kind, tmp_path, capfd):
    seq = write_folder(tmp_path)
    line = assert_error(
        *run(capfd, ["classify", seq, option, "nosuch"], watch=tmp_path),
        path=None,
        problem=f"unknown {kind} 'nosuch'; registered: ",
    )
    if kind == "reader":
        assert "folder" in line and "ycbv" in line


def test_unknown_parameter_name(tmp_path, capfd):
    seq = write_folder(tmp_path)
    assert_error(
        *run(capfd, ["classify", seq, "--param", "nosuch=1"], watch=tmp_path),
        path=None,
        problem=r"unknown parameter 'nosuch'; known: .*\bk\b",
    )


@pytest.mark.parametrize(
    "setting,expected",
    [
        ("k=0", r"parameter k = 0 is out of bounds \[1, 1000\]"),
        ("alpha=1.5", r"parameter alpha = 1\.5 is out of bounds \[0(\.0)?, 1(\.0)?\]"),
        ("min_fitness=-0.1", r"parameter min_fitness = -0\.1 is out of bounds \[0(\.0)?, 1(\.0)?\]"),
    ],
)
def test_parameter_out_of_bounds(setting, expected, tmp_path, capfd):
    seq = write_folder(tmp_path)
    assert_error(
        *run(capfd, ["classify", seq, "--param", setting], watch=tmp_path), path=None, problem=expected
    )


def test_parameter_of_the_wrong_type(tmp_path, capfd):
    seq = write_folder(tmp_path)
    assert_error(
        *run(capfd, ["classify", seq, "--param", "k=five"], watch=tmp_path),
        path=None,
        problem="parameter k: 'five' is not a valid int",
    )


def test_evaluate_reports_bad_folders_and_goes_on(tmp_path, capfd):
    """One broken sequence under a root does not stop ``evaluate``; it is reported in one line."""
    good = write_folder(tmp_path, "good", n_frames=3)
    bad = write_folder(tmp_path, "bad")
    edit_json(bad / "meta.json", fx=None)
    code, out, err = run(capfd, ["evaluate", tmp_path], watch=tmp_path)
    assert code == 0 and "Traceback" not in err
    assert err.splitlines() == [
        f"artclass: skipping {bad / 'meta.json'}: missing 'fx' (camera intrinsics and "
        f"depth scale are required)"
    ]
    assert f"| {good.name} |" in out and "error: " in out and "needs at least 6" in out
