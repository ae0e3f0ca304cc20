"""The command line end to end: ``artclass_core.cli.main`` in process, and once the installed script."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from artclass_core.cli import main
from artclass_core.interfaces import KINDS

from conftest import ROOT, sample_sequences

LABELS = {"articulated", "rigid", "static"}
BUILTINS = {
    "reader": {"folder", "ycbv", "rbo", "tum"},
    "segmenter": {"mask", "depth_threshold", "u2net", "maskrcnn"},
    "preprocessor": {"paper", "fine"},
    "registrar": {"icp_point_to_point", "icp_point_to_plane"},
    "rule": {"dense", "paper"},
    "joint_estimator": {"bic"},
    "part_finder": {"tracks"},
}
SAMPLES = sample_sequences()


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    status = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return status, out, err


def check_result(d: dict, *, name: str) -> None:
    assert d["sequence"]["name"] == name
    assert d["label"] in LABELS
    k = d["params"]["pipeline"]["k"]
    n = d["sequence"]["n_frames"]
    assert [(p["i"], p["j"]) for p in d["pairs"]] == [(i, i + k) for i in range(n - k)]
    for p in d["pairs"]:
        assert p["decision"] in ("AM", "RM", "NM", "skipped")
        assert p["decision"] != "skipped" or p["reason"], "a skipped pair says why"
    decided = [p["decision"] for p in d["pairs"] if p["decision"] != "skipped"]
    assert set(d["fractions"]) == {"AM", "RM", "NM"}
    if decided:
        assert sum(d["fractions"].values()) == pytest.approx(1.0)
        assert d["fractions"]["AM"] == pytest.approx(decided.count("AM") / len(decided))
    assert len(d["filtered"]) == len(decided)
    assert {"pipeline", "segmenter", "preprocessor", "registrar", "rule"} <= set(d["params"])
    assert set(d["plugins"]) == {"segmenter", "preprocessor", "registrar", "rule"}
    assert d["timing_s"]["total"] > 0
    assert len(d["frames"]) == n


def test_sample_data_is_bundled():
    assert len(SAMPLES) >= 3, f"sample_data/ should hold the bundled sequences, found {SAMPLES}"
    labels = {json.loads((s / "meta.json").read_text()).get("label") for s in SAMPLES}
    assert labels == LABELS, "the samples cover the three classes"


@pytest.mark.slow
@pytest.mark.parametrize("seq", SAMPLES, ids=lambda p: p.name)
def test_classify_json(capsys, seq):
    status, out, err = run_cli(capsys, "classify", seq, "--json")
    assert status == 0, err
    assert out.count("\n") == 1, "one JSON object on one line"
    check_result(json.loads(out), name=seq.name)


@pytest.mark.slow
def test_classify_workers_give_the_same_result(capsys):
    runs = []
    for workers in ("1", "2"):
        status, out, err = run_cli(
            capsys, "classify", SAMPLES[0], "--json", "--no-cells", "--workers", workers
        )
        assert status == 0, err
        d = json.loads(out)
        runs.append((d["label"], [(p["decision"], p["info"]) for p in d["pairs"]]))
    assert runs[0] == runs[1]
    status, out, err = run_cli(capsys, "classify", SAMPLES[0], "--workers", "0")
    assert status != 0 and "workers = 0 must be a positive integer" in err and "Traceback" not in err


@pytest.mark.slow
def test_classify_summary(capsys):
    seq = SAMPLES[0]
    status, out, err = run_cli(capsys, "classify", seq)
    assert status == 0, err
    lines = out.splitlines()
    assert lines[0].split(":")[0] == seq.name
    assert lines[0].split(": ")[1].split()[0] in LABELS
    assert "(ground truth: " in lines[0]
    for text in (
        "pairs (i, i+5):",
        "after max-count filter (w=3):",
        "fractions: AM",
        "plugins: segmenter=",
        "time:",
    ):
        assert any(text in line for line in lines), f"{text!r} missing from:\n{out}"


@pytest.mark.slow
def test_param_by_symbol_is_recorded(capsys):
    seq = SAMPLES[0]
    status, out, err = run_cli(
        capsys,
        "classify",
        seq,
        "--json",
        "--no-cells",
        "--rule",
        "paper",
        "--preprocessor",
        "paper",
        "--param",
        "k=3",
        "--param",
        "v=0.006",
        "--param",
        "q_bar=0.2",
        "--param",
        "w=1",
    )
    assert status == 0, err
    d = json.loads(out)
    assert d["params"]["pipeline"]["k"] == 3 and d["params"]["pipeline"]["w"] == 1
    assert d["params"]["preprocessor"]["voxel_size_m"] == 0.006
    assert d["params"]["rule"]["q_bar"] == 0.2
    assert all(p["j"] - p["i"] == 3 for p in d["pairs"])
    assert all(f["v_m"] == 0.006 for f in d["frames"] if "v_m" in f)
    assert "cells" not in d["pairs"][0]
    assert d["filtered"] == [p["decision"] for p in d["pairs"] if p["decision"] != "skipped"], (
        "w = 1: no filtering"
    )


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--param", "zzz=1"], "unknown parameter 'zzz'; known: "),
        (["--param", "k=0"], "k = 0 is out of bounds [1, 1000]"),
        (["--param", "k"], "expected NAME=VALUE"),
        (["--rule", "nope"], "unknown rule 'nope'; registered: "),
    ],
)
def test_bad_options_give_one_line(capsys, argv, message):
    status, out, err = run_cli(capsys, "classify", SAMPLES[0], *argv)
    assert status == 2 and out == ""
    assert err.startswith("artclass: error: ") and message in err and err.count("\n") == 1, err


@pytest.mark.slow
def test_evaluate_real_ycbv(capsys, shared_data):
    root = shared_data / "ycbv"
    status, out, err = run_cli(capsys, "evaluate", root, "--param", "k=2")
    assert status == 0, err
    for heading in (
        "## Sequences",
        "## Accuracy per object (Tables 1-2)",
        "## Pair fractions per object (Tables 3-4)",
        "## Summary",
        "## Confusion matrix",
    ):
        assert heading in out
    rows = [line for line in out.splitlines() if line.startswith("| 000")]
    assert len(rows) == 7, "3 objects in scene 0000 and 4 in scene 0001"
    assert not any("error:" in row for row in rows), out
    for obj in ("025_mug", "003_cracker_box", "006_mustard_bottle"):
        assert obj in out


@pytest.mark.slow
def test_evaluate_synthetic_smoke_set(capsys, tmp_path):
    from artclass_plugins.synth import generate_set

    paths = generate_set(tmp_path / "smoke", preset="smoke", seed=0)
    status, out, err = run_cli(capsys, "evaluate", tmp_path / "smoke", "--json", "--compare-rule", "paper")
    assert status == 0, err
    evals = json.loads(out)["evaluations"]
    assert len(evals) == 2 and evals[1]["rule"] == "paper"
    for e in evals:
        m = e["metrics"]
        assert m["n_sequences"] == len(paths) == 4 and m["errors"] == 0
        assert 0.0 <= m["accuracy"] <= 1.0
        assert {s["name"] for s in e["sequences"]} == {p.name for p in paths}
        assert m["pair_total"] > 0, "the synthetic sequences carry per-pair truth"
    status, out, err = run_cli(capsys, "evaluate", tmp_path / "smoke")
    assert status == 0, err
    assert "## Accuracy per object (Tables 1-2)" in out and "## Confusion matrix" in out
    for p in paths:
        assert f"| {p.name} |" in out


@pytest.mark.slow
def test_evaluate_on_a_local_dask_cluster_is_the_serial_evaluation(capsys, tmp_path, rendered_root):
    pytest.importorskip("distributed", reason="Dask is in the test extra: pip install -e '.[test]'")
    rendered_root(
        tmp_path,
        {"laptop": ("laptop", "articulate"), "mug": ("mug", "carry")},
        n_frames=8,
        width=160,
        height=120,
    )
    runs = []
    for extra in ([], ["--scheduler", "local"]):
        status, out, err = run_cli(
            capsys, "evaluate", tmp_path, "--json", "--param", "k=3", "--compare-rule", "paper", *extra
        )
        assert status == 0, err
        evals = json.loads(out)["evaluations"]
        for e in evals:  # times differ from run to run
            e["metrics"].pop("segment_ms_per_frame")
            for s in e["sequences"]:
                s.pop("seconds")
                s.pop("segment_s")
        runs.append(evals)
    assert [e["rule"] for e in runs[0]] == ["dense", "paper"]
    assert runs[0] == runs[1]


def test_progress_bars_show_counts_and_close(capsys):
    from artclass_core.cli import _Bars

    bars = _Bars()
    for done in range(4):
        bars("pairs", done, 3)
    bars("rows", 0, 0)  # nothing to do: opened and closed at once
    err = capsys.readouterr().err
    assert "pairs: 100%" in err and "3/3" in err and "rows: 0row" in err, err
    assert not bars._bars, "finished bars are closed"


def test_plugins_lists_the_registry(capsys, registry):
    status, out, err = run_cli(capsys, "plugins", "--json")
    assert status == 0, err
    table = json.loads(out)["plugins"]
    for kind in KINDS:
        listed = [p["name"] for p in table[kind]]
        assert listed == registry.names(kind)
        assert BUILTINS[kind] <= set(listed), f"built-in {kind}s missing: {BUILTINS[kind] - set(listed)}"
        for p in table[kind]:
            assert p["description"] and p["source"]
    paper = next(p for p in table["preprocessor"] if p["name"] == "paper")
    assert {"v", "r", "s"} <= {s["symbol"] for s in paper["params"]}
    status, out, err = run_cli(capsys, "plugins")
    assert status == 0
    for names in BUILTINS.values():
        for name in names:
            assert f"  {name} " in out


@pytest.mark.slow
def test_installed_console_script():
    """The real ``artclass`` script of this environment, in a fresh process."""
    script = Path(sys.executable).with_name("artclass")
    assert script.is_file(), f"{script} is not installed (pip install -e .)"
    seq = SAMPLES[0]
    proc = subprocess.run(
        [str(script), "classify", str(seq), "--json", "--no-cells"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        stdin=subprocess.DEVNULL,
    )
    assert proc.returncode == 0, proc.stderr
    check_result(json.loads(proc.stdout), name=seq.name)
