"""Fuzzing the readers and the ``--param`` parser with Hypothesis, through the real command line.

Random bytes as PNG files, random ``meta.json`` values, random folder layouts and random ``--param``
values must give either a result (exit status 0) or the one-line error (``artclass: error: ...``,
exit status 2), never a traceback, and must never write into the input folder (its list of files and
folders, their contents and their modification times are compared before and after). The search is
derandomized (the same examples on every run) and bounded, so the suite's time stays predictable.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
from datetime import timedelta
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from artclass_core import PipelineParams, describe
from artclass_core.cli import main

from fixtures_layouts import write_folder, write_rbo, write_tum, write_ycbv

N_FRAMES = 3
RUN = ["--param", "k=1", "--workers", "1"]  # two pairs: every frame is read
FUZZ = settings(
    max_examples=15,
    deadline=timedelta(seconds=30),
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def templates(tmp_path_factory) -> dict[str, tuple[Path, str]]:
    """One small sequence per layout: reader -> (folder, the path argument's ``#name`` suffix)."""
    root = tmp_path_factory.mktemp("fuzz_templates")
    return {
        "folder": (write_folder(root / "folder", n_frames=N_FRAMES), ""),
        "ycbv": (write_ycbv(root / "ycbv", n_frames=N_FRAMES), "#0000/025_mug"),
        "tum": (write_tum(root / "tum", n_frames=N_FRAMES), ""),
        "rbo": (write_rbo(root / "rbo", n_frames=N_FRAMES), ""),
    }


def state(folder: Path) -> dict[str, tuple]:
    """Every file and folder under ``folder``: kind, modification time (ns), size and content hash."""
    out = {}
    for p in sorted(folder.rglob("*")):
        st_ = p.lstat()
        digest = hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() and not p.is_symlink() else None
        out[str(p.relative_to(folder))] = (p.is_dir(), st_.st_mtime_ns, st_.st_size, digest)
    return out


def run_and_check(capfd, argv: list[str], *, watch: Path) -> int:
    """Run the CLI on ``argv``; assert a result or the one-line error, no traceback, no write under ``watch``."""
    capfd.readouterr()
    before = state(watch)
    code = main([str(a) for a in argv])
    out, err = capfd.readouterr()
    assert state(watch) == before, "the run changed the input folder"
    assert "Traceback" not in out + err
    assert code in (0, 2), f"exit status {code}: {err}"
    if code == 2:
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("artclass: error: "), err
    return code


def copy_of(template: Path) -> tuple[Path, Path]:
    """A fresh copy of ``template`` in a new temporary folder: (the folder, the copy)."""
    tmp = Path(tempfile.mkdtemp(prefix="artclass_fuzz_"))
    return tmp, Path(shutil.copytree(template, tmp / template.name))


# -- readers ----------------------------------------------------------------------------------------
@FUZZ
@given(
    layout=st.sampled_from(["folder", "ycbv", "tum", "rbo"]),
    pick=st.integers(0, 10_000),
    header=st.booleans(),
    data=st.binary(max_size=600),
)
def test_random_bytes_as_a_png(templates, capfd, layout, pick, header, data):
    template, suffix = templates[layout]
    tmp, seq = copy_of(template)
    try:
        pngs = sorted(seq.rglob("*.png"))
        victim = pngs[pick % len(pngs)]
        victim.write_bytes((PNG_SIGNATURE if header else b"") + data)
        run_and_check(capfd, ["classify", f"{seq}{suffix}", *RUN], watch=tmp)
    finally:
        shutil.rmtree(tmp)


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3),
    max_leaves=6,
)
META_KEYS = ("fx", "fy", "cx", "cy", "depth_scale", "object", "label", "width", "height")


@FUZZ
@given(
    changes=st.dictionaries(
        st.sampled_from(META_KEYS) | st.text(max_size=8), JSON_VALUES | st.just(None), max_size=4
    ),
    raw=st.none() | st.binary(max_size=200),
)
def test_random_meta_json_values(templates, capfd, changes, raw):
    tmp, seq = copy_of(templates["folder"][0])
    try:
        meta_path = seq / "meta.json"
        if raw is not None:
            meta_path.write_bytes(raw)
        else:
            meta = json.loads(meta_path.read_text())
            for key, value in changes.items():
                if value is None:
                    meta.pop(key, None)
                else:
                    meta[key] = value
            meta_path.write_text(json.dumps(meta, allow_nan=True))
        run_and_check(capfd, ["classify", seq, *RUN], watch=tmp)
    finally:
        shutil.rmtree(tmp)


NAMES = (
    "rgb",
    "depth",
    "mask",
    "meta.json",
    "truth.json",
    "rgb.txt",
    "depth.txt",
    "camera_info.csv",
    "000000.png",
    "000001.png",
    "x.png",
    "0000",
    "camera_rgb",
    "camera_depth",
    "data",
)
CONTENTS = st.sampled_from(["png", "depth_png", "json", "empty"]) | st.binary(max_size=100)


@FUZZ
@given(
    entries=st.lists(
        st.tuples(st.lists(st.sampled_from(NAMES), min_size=1, max_size=3), CONTENTS), min_size=1, max_size=8
    )
)
def test_random_folder_layouts(templates, capfd, entries):
    template = templates["folder"][0]
    sources = {
        "png": template / "rgb" / "000000.png",
        "depth_png": template / "depth" / "000000.png",
        "json": template / "meta.json",
    }
    tmp = Path(tempfile.mkdtemp(prefix="artclass_fuzz_"))
    try:
        seq = tmp / "seq"
        seq.mkdir()
        for parts, content in entries:
            path = seq.joinpath(*parts)
            if any(p.exists() and not p.is_dir() for p in [*reversed(path.parents)][1:]) or path.is_dir():
                continue  # a file already stands where a folder is needed
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(
                sources[content].read_bytes()
                if content in sources
                else b""
                if content == "empty"
                else content
            )
        run_and_check(capfd, ["classify", seq, *RUN], watch=tmp)
    finally:
        shutil.rmtree(tmp)


# -- the --param parser -------------------------------------------------------------------------------
KNOWN = sorted(
    {n for s in describe(PipelineParams) for n in (s.name, s.symbol) if n}
    | {"v", "r", "s", "x", "q_bar", "t_bar", "k", "w", "alpha"}
)
VALUES = (
    st.sampled_from(["auto", "nan", "inf", "-inf", "1e309", "", "-1", "0", "true", "none", "1/2"])
    | st.floats().map(repr)
    | st.integers(-(10**6), 10**6).map(str)
    | st.text(max_size=10)
)


@FUZZ
@given(
    params=st.lists(
        st.tuples(
            st.sampled_from(KNOWN) | st.text(max_size=8), st.sampled_from(["=", " = ", "", "=="]), VALUES
        ).map("".join),
        min_size=1,
        max_size=3,
    )
)
def test_random_param_values(templates, capfd, params):
    template = templates["folder"][0]
    argv = ["classify", template, "--workers", "1", "--param", "k=1"]
    for item in params:
        argv += ["--param", item]
    run_and_check(capfd, argv, watch=template.parent)
