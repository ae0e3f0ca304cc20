"""Sweeps: every setting of a grid over a folder of labelled sequences, into one table.

A sweep's rows must be exactly what separate runs give (the shared stage cache only saves work), the
same on a 2-worker Dask ``LocalCluster`` as here, and the same after an interrupted sweep is resumed.
The data are three small generated sequences (160 x 120, 8 frames) so the tests stay quick.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from artclass_core import ArtclassError, InputError, ParamError, Pipeline, load_registry, open_sequences
from artclass_core.cli import main
from artclass_core.sweep import (
    grid_settings,
    parse_grid,
    plan_tasks,
    read_table,
    summary,
    sweep,
    swept_names,
    write_table,
)
from artclass_plugins.figures import sweep_figure

from conftest import ROOT

pytestmark = pytest.mark.slow  # whole sweeps, two of them on a local Dask cluster

OBJECTS = {
    "laptop_articulate": ("laptop", "articulate"),
    "mug_carry": ("mug", "carry"),
    "cereal_box_static": ("cereal_box", "static"),
}
TIMING = (
    "seconds",
    "time_read_s",
    "time_segment_s",
    "time_preprocess_s",
    "time_register_s",
    "time_decide_s",
    "time_total_s",
)


@pytest.fixture(scope="module")
def registry():
    return load_registry()


@pytest.fixture(scope="module")
def root(tmp_path_factory, rendered_root) -> Path:
    return rendered_root(tmp_path_factory.mktemp("sweep_data"), OBJECTS, n_frames=8, width=160, height=120)


@pytest.fixture(scope="module")
def sequences(registry, root):
    return [open_sequences(registry, root / name)[0] for name in sorted(OBJECTS)]


def results(table: pd.DataFrame) -> pd.DataFrame:
    """The table without its timing columns (the only ones that differ from run to run)."""
    return table.drop(columns=list(TIMING)).reset_index(drop=True)


# -- the grid ---------------------------------------------------------------------------------------


def test_parse_grid():
    assert parse_grid(["q_bar=0.05, 0.1", "k=3,5,3"]) == {"q_bar": ["0.05", "0.1"], "k": ["3", "5"]}
    for bad in ("q_bar", "=1,2", "k="):
        with pytest.raises(ArtclassError, match="expected NAME=V1,V2"):
            parse_grid([bad])
    with pytest.raises(ArtclassError, match="given twice"):
        parse_grid(["k=1", "k=2"])


def test_grid_settings_are_every_combination(registry):
    settings = grid_settings(
        registry, {"q_bar": ["0.05", "0.2"], "k": ["3", "4", "5"]}, params={"w": "1"}, rule="paper"
    )
    assert [s.label for s in settings] == [f"q_bar={q}, k={k}" for q in ("0.05", "0.2") for k in (3, 4, 5)]
    config = settings[4].config(registry)
    assert (config.rule, config.rule_params.q_bar, config.pipeline.k, config.pipeline.w) == (
        "paper",
        0.2,
        4,
        1,
    )
    assert len({s.recipe for s in settings}) == 6
    rules = grid_settings(registry, {"rule": ["dense", "paper"]})
    assert [s.config(registry).rule for s in rules] == ["dense", "paper"]
    with pytest.raises(ParamError, match=r"setting k=0: .*k = 0 is out of bounds"):
        grid_settings(registry, {"k": ["3", "0"]})
    with pytest.raises(ArtclassError, match="unknown parameter 'nope'"):
        grid_settings(registry, {"nope": ["1"]})


def test_one_task_per_sequence_and_frame_stages(registry, sequences):
    decisions = grid_settings(registry, {"w": ["1", "3"], "k": ["3", "4"]})
    assert [(i, chosen) for i, _, chosen in plan_tasks(registry, sequences, decisions)] == [
        (0, [0, 1, 2, 3]),
        (1, [0, 1, 2, 3]),
        (2, [0, 1, 2, 3]),
    ]
    frames = grid_settings(registry, {"max_points": ["2000", "3000"], "w": ["1", "3"]})
    tasks = plan_tasks(
        registry,
        sequences,
        frames,
        done={(str(sequences[0].path.resolve()), sequences[0].name, frames[0].recipe)},
    )
    assert [(i, chosen) for i, _, chosen in tasks] == [
        (0, [1]),
        (0, [2, 3]),
        (1, [0, 1]),
        (1, [2, 3]),
        (2, [0, 1]),
        (2, [2, 3]),
    ]


# -- what a sweep computes ------------------------------------------------------------------------------


def test_rows_equal_separate_runs(registry, sequences, tmp_path):
    """Decision, registration and prealignment settings sharing one cache give what fresh runs give."""
    settings = grid_settings(
        registry,
        {"prealign": ["true", "false"], "x": ["auto", "0.03"], "min_part_share": ["0.15", "0.4"]},
        params={"k": "3"},
    )
    sequences = sequences[1:]  # an articulated and a carried object
    table = sweep(registry, sequences, settings, out=tmp_path / "t.parquet")
    assert len(table) == len(sequences) * len(settings) == 16
    assert table["error"].isna().all(), table["error"].dropna().tolist()
    assert list(zip(table.sequence, table.setting)) == [
        (s.name, st.label) for s in sequences for st in settings
    ]
    assert not any(s.frame.cache_info().currsize for s in sequences), "frames kept after the sweep"
    seen = set()
    for row in table.itertuples():
        seq = next(s for s in sequences if s.name == row.sequence)
        config = next(st for st in settings if st.label == row.setting).config(registry)
        fresh = Pipeline(registry, config).run(seq)
        truthful = [p for p in fresh.pairs if p.truth and p.decision != "skipped"]
        assert (row.label, row.AM, row.RM, row.NM) == (
            fresh.label,
            *(fresh.fractions[d] for d in ("AM", "RM", "NM")),
        )
        assert (row.pair_correct, row.pair_total) == (
            sum(p.decision == p.truth for p in truthful),
            len(truthful),
        )
        assert row.decisions == "".join({"skipped": "-"}.get(p.decision, p.decision[0]) for p in fresh.pairs)
        assert row.skipped_pairs == sum(p.decision == "skipped" for p in fresh.pairs)
        assert json.loads(row.params) == json.loads(json.dumps(fresh.params, default=str))
        seen.add((row.label, row.pair_correct))
    assert len(seen) > 1, "the settings should not all give the same outcome"


def test_failing_sequence_is_recorded_and_the_rest_goes_on(registry, sequences, tmp_path):
    settings = grid_settings(registry, {"k": ["3", "9"]})  # 8 frames: k = 9 cannot run
    table = sweep(registry, sequences, settings, out=tmp_path / "t.csv")
    failed = table[table.setting == "k=9"]
    assert len(failed) == len(sequences) and failed["label"].isna().all() and not failed["correct"].any()
    assert all(
        e.endswith(f"{s}: sequence has 8 frames; k = 9 needs at least 10")
        for s, e in zip(failed.sequence, failed.error)
    )
    assert table[table.setting == "k=3"]["error"].isna().all()
    assert list(summary(table)["errors"]) == [0, len(sequences)]
    assert results(read_table(tmp_path / "t.csv")).equals(results(table)), "the CSV reads back as written"


def test_resume_skips_done_rows_and_force_redoes_them(registry, sequences, tmp_path):
    out = tmp_path / "t.parquet"
    settings = grid_settings(registry, {"w": ["1", "3"]})
    first = sweep(registry, sequences[:2], settings, out=out)
    again = sweep(registry, sequences, settings, out=out)  # one more sequence: only its rows run
    assert len(again) == 6
    assert again.iloc[:4].equals(first), "rows already done are kept exactly, timings included"
    forced = sweep(registry, sequences, settings, out=out, force=True)
    assert results(forced).equals(results(again)) and not forced["seconds"].equals(again["seconds"])


def test_two_worker_local_cluster_gives_the_serial_table(registry, sequences, tmp_path):
    distributed = pytest.importorskip(
        "distributed", reason="Dask is in the test extra: pip install -e '.[test]'"
    )
    settings = grid_settings(registry, {"noise_factor": ["2", "4"], "k": ["2", "4"]})
    serial = sweep(registry, sequences, settings, out=tmp_path / "serial.parquet", workers=2)
    with (
        distributed.LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None) as cluster,
        distributed.Client(cluster) as client,
    ):
        assert len(client.scheduler_info()["workers"]) == 2
        on_dask = sweep(registry, sequences, settings, out=tmp_path / "dask.parquet", scheduler=client)
    assert len(on_dask) == 12
    assert results(on_dask).equals(results(serial))


def polled(path: Path) -> pd.DataFrame:
    """The table at ``path`` while a sweep may replace it: the reader opens the file more than once, and
    a table renamed over it in between reads as damaged; it is then read again."""
    for _ in range(20):
        try:
            return read_table(path)
        except InputError:
            time.sleep(0.05)
    return read_table(path)


def test_interrupted_sweep_resumes_to_the_same_table(root, tmp_path):
    """Kill the command (SIGKILL: nothing gets to clean up) once the first rows are written; run it again."""
    script = Path(sys.executable).with_name("artclass")
    argv = [
        str(script),
        "sweep",
        str(root),
        "--grid",
        "x=auto,0.03,0.05",
        "--grid",
        "w=1,3",
        "--workers",
        "1",
    ]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    whole = tmp_path / "whole.parquet"
    subprocess.run([*argv, "--out", str(whole)], check=True, capture_output=True, timeout=600, env=env)
    out = tmp_path / "cut.parquet"
    proc = subprocess.Popen(
        [*argv, "--out", str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env
    )
    try:
        deadline = time.monotonic() + 300
        while not (out.exists() and len(polled(out)) >= 2) and proc.poll() is None:
            assert time.monotonic() < deadline, "no row was written"
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(timeout=60)
    cut = read_table(out)
    assert 2 <= len(cut) < 18, f"killed after {len(cut)} of 18 rows"
    assert proc.returncode == -signal.SIGKILL
    done = subprocess.run([*argv, "--out", str(out)], capture_output=True, text=True, timeout=600, env=env)
    assert done.returncode == 0, done.stderr
    resumed = read_table(out)
    assert resumed.iloc[: len(cut)][list(TIMING)].equals(cut[list(TIMING)]), (
        "the finished rows were not run again"
    )
    assert results(resumed).equals(results(read_table(whole)))


# -- the command ----------------------------------------------------------------------------------------


def test_sweep_command(capsys, root, tmp_path):
    out = tmp_path / "results.parquet"
    status = main(
        ["sweep", str(root), "--grid", "min_part_share=0.15,0.4", "--grid", "k=3,4", "--out", str(out)]
    )
    stdout, err = capsys.readouterr()
    assert status == 0, err
    table = read_table(out)
    assert len(table) == 12 and swept_names(table) == ["min_part_share", "k"]
    lines = stdout.splitlines()
    assert lines[0].split() == [
        "setting",
        "sequences",
        "errors",
        "accuracy",
        "pair_accuracy",
        "AM",
        "RM",
        "NM",
        "seconds",
    ]
    assert [line.split(",")[0].strip() for line in lines[1:5]] == ["min_part_share=0.15"] * 2 + [
        "min_part_share=0.4"
    ] * 2
    for line, (_, row) in zip(lines[1:5], summary(table).iterrows()):
        assert f"{row.accuracy:.1%}" in line and line.split()[2] == str(len(OBJECTS))
    html = out.with_suffix(".html").read_text()
    assert "min_part_share" in html and "<script src=" not in html, "plotly.js is inside: no internet needed"
    assert len(html) > 1_000_000
    status = main(
        [
            "sweep",
            str(root),
            "--grid",
            "min_part_share=0.15,0.4",
            "--grid",
            "k=3,4",
            "--out",
            str(out),
            "--json",
        ]
    )
    stdout, err = capsys.readouterr()
    assert status == 0, err
    assert [r["setting"] for r in json.loads(stdout)["summary"]] == list(summary(table)["setting"])
    assert read_table(out).equals(table), "a second run with nothing left to do changes nothing"


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--grid", "k"], "--grid 'k': expected NAME=V1,V2,..."),
        (["--grid", "k=0,3"], "setting k=0: parameter k = 0 is out of bounds"),
        (["--grid", "rule=nope"], "unknown rule 'nope'"),
        (["--grid", "k=3", "--out", "results.xlsx"], "the table is written as .parquet or .csv"),
        (["--grid", "k=3", "--workers", "0"], "workers = 0 must be a positive integer"),
    ],
)
def test_sweep_bad_options_give_one_line(capsys, root, tmp_path, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    status = main(["sweep", str(root), *argv])
    out, err = capsys.readouterr()
    assert status == 2 and out == "" and err.count("\n") == 1 and message in err, err
    assert not list(tmp_path.iterdir()), "nothing was written"


@pytest.mark.parametrize("command", ["sweep", "evaluate"])
def test_scheduler_without_dask_says_how_to_install_it(capsys, root, tmp_path, monkeypatch, command):
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if Dask were not installed
    grid = ["--grid", "k=3", "--out", str(tmp_path / "t.parquet")] if command == "sweep" else []
    status = main([command, str(root), *grid, "--scheduler", "local"])
    _, err = capsys.readouterr()
    assert status == 2 and err.count("\n") == 1 and "pip install 'artclass[dask]'" in err, err


# -- the table and the figure ---------------------------------------------------------------------------


def test_figure_has_a_panel_per_swept_name(registry, sequences, tmp_path):
    settings = grid_settings(registry, {"w": ["1", "3", "5"], "rule": ["dense", "paper"]})
    table = sweep(registry, sequences, settings, out=tmp_path / "t.parquet")
    fig = sweep_figure(table)
    titles = [a.text for a in fig.layout.annotations]
    assert titles == ["w", "rule"]
    summ = summary(table)
    # Panel w: one sequence-accuracy line per rule, x the numeric values of w, y the setting's accuracy.
    w_lines = [t for t in fig.data if t.xaxis == "x" and t.name.startswith("sequence accuracy")]
    assert sorted(t.name for t in w_lines) == [
        "sequence accuracy, rule=dense",
        "sequence accuracy, rule=paper",
    ]
    for t in w_lines:
        rule = t.name.split("=")[1]
        expected = summ[summ.rule == rule].assign(w=lambda d: d.w.astype(int)).sort_values("w")
        assert list(t.x) == list(expected.w) and list(t.y) == pytest.approx(list(expected.accuracy))
    rule_lines = [t for t in fig.data if t.xaxis == "x2"]
    assert len(rule_lines) == 6 and fig.layout.xaxis2.type == "category"


def test_table_reader_names_the_file(tmp_path):
    bad = tmp_path / "x.parquet"
    bad.write_text("not parquet")
    with pytest.raises(ArtclassError, match=r"x.parquet.*not a readable sweep table"):
        read_table(bad)
    write_table(pd.DataFrame(dict(a=[1])), tmp_path / "y.parquet")
    with pytest.raises(ArtclassError, match="not a sweep table: no column path, sequence, recipe"):
        read_table(tmp_path / "y.parquet")


# -- the app ---------------------------------------------------------------------------------------------


def test_evaluate_page_opens_a_sweep_table(registry, sequences, root, tmp_path, monkeypatch):
    from streamlit.testing.v1 import AppTest

    monkeypatch.syspath_prepend(str(ROOT))
    monkeypatch.setenv("ARTCLASS_SAMPLE_DATA", str(root))
    monkeypatch.delenv("ARTCLASS_DATA_ROOTS", raising=False)
    monkeypatch.setenv("ARTCLASS_UPLOAD_DIR", str(tmp_path / "uploads"))
    table = sweep(
        registry,
        sequences,
        grid_settings(registry, {"w": ["1", "5"]}, params={"k": "7"}),
        out=tmp_path / "t.parquet",
    )
    app = AppTest.from_file(str(ROOT / "app" / "streamlit_app.py"), default_timeout=300)
    app.run()
    app.switch_page("app_pages/evaluate.py").run()
    app.radio(key="ev_source").set_value("Open a sweep table").run()
    assert not app.exception and not app.error
    assert not app.get("plotly_chart"), "no figure before a table is uploaded"
    app.get("file_uploader")[0].set_value(
        ("t.parquet", (tmp_path / "t.parquet").read_bytes(), "application/octet-stream")
    ).run()
    assert not app.exception and not app.error, [e.value for e in app.error]
    shown = json.loads(app.get("plotly_chart")[0].proto.spec)
    assert shown == json.loads(sweep_figure(table).to_json()), "the page shows the figure the command writes"
    app.get("file_uploader")[0].set_value(("t.csv", b"not,a,sweep\n1,2,3\n", "text/csv")).run()
    assert not app.exception
    errors = [e.value for e in app.error]
    assert len(errors) == 1 and errors[0].startswith("t.csv: not a readable sweep table ("), errors


def test_docs_name_every_column(registry, sequences, tmp_path):
    text = (ROOT / "docs" / "datasets-and-clusters.md").read_text()
    table = sweep(
        registry,
        sequences[:1],
        grid_settings(registry, {"w": ["1"]}, params={"k": "7"}),
        out=tmp_path / "t.parquet",
    )
    undocumented = [c for c in table.columns if c != "w" and f"`{c}`" not in text]
    assert not undocumented, f"docs/datasets-and-clusters.md does not describe the columns {undocumented}"
    assert "datasets-and-clusters.md" in (ROOT / "docs" / "index.md").read_text()
