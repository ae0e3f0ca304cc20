"""The notebooks under notebooks/ are stored without outputs and run from top to bottom.

Each notebook is executed with nbclient in a ``python3`` kernel of the interpreter running the tests
(ipykernel installs that kernel spec into the virtual environment; its command ``python`` is replaced
by this interpreter), with the notebooks folder as working directory. A cell that raises fails the
test. Every cell has a time limit, and all notebooks together share one overall budget, so a hang
cannot stall CI. The elapsed time per notebook is printed (``pytest -s``), not asserted.
"""

from __future__ import annotations

import base64
import re
import sys
import time
from pathlib import Path

import nbformat
import numpy as np
import pytest
from jupyter_client.kernelspec import KernelSpecManager
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK_DIR = ROOT / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))
SAMPLE_DATA = ROOT / "sample_data"
CELL_TIMEOUT_S = 600
TOTAL_BUDGET_S = 1200  # for all notebooks together (about 2.5 min on the development machine)
PLOTLY = "application/vnd.plotly.v1+json"

_deadline: dict[str, float] = {}


def _remaining_s() -> float:
    start = _deadline.setdefault("start", time.monotonic())
    return TOTAL_BUDGET_S - (time.monotonic() - start)


def _figures(nb) -> list[dict]:
    """The Plotly figures a notebook displayed, as JSON dicts."""
    return [
        out["data"][PLOTLY]
        for cell in nb.cells
        if cell.cell_type == "code"
        for out in cell.get("outputs", [])
        if PLOTLY in out.get("data", {})
    ]


def _array(value) -> np.ndarray:
    """A Plotly JSON array: a list, or a typed array ``{"dtype": ..., "bdata": base64}`` (plotly >= 6)."""
    if isinstance(value, dict) and "bdata" in value:
        data = np.frombuffer(base64.b64decode(value["bdata"]), dtype=np.dtype(value["dtype"]))
        shape = value.get("shape")
        if isinstance(shape, str):  # plotly writes e.g. "3, 4"
            shape = [int(s) for s in shape.split(",") if s.strip()]
        return data.reshape(shape) if shape else data
    return np.asarray(value)


def _text(nb) -> str:
    parts = []
    for cell in nb.cells:
        for out in cell.get("outputs", []) if cell.cell_type == "code" else []:
            parts.append(out.get("text", "") or out.get("data", {}).get("text/plain", ""))
    return "\n".join(parts)


def _snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    return {
        str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns)
        for p in sorted(folder.rglob("*"))
    }


def test_there_are_notebooks():
    assert [p.name for p in NOTEBOOKS] == [
        "01_quickstart.ipynb",
        "02_parameter_study.ipynb",
        "03_write_a_plugin.ipynb",
    ]


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_stored_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    dirty = [n for n, c in enumerate(nb.cells) if c.cell_type == "code" and (c.outputs or c.execution_count)]
    assert not dirty, (
        f"{path.name}: cells {dirty} have outputs or execution counts; strip them "
        f"(e.g. `jupyter nbconvert --clear-output --inplace {path.relative_to(ROOT)}`)"
    )
    assert nb.metadata.get("kernelspec", {}).get("name") == "python3"
    assert "widgets" not in nb.metadata


def test_kernel_is_this_interpreter():
    """The ``python3`` kernel spec that nbclient will start runs the interpreter running the tests."""
    spec = KernelSpecManager().get_kernel_spec("python3")
    assert spec.argv[0] in (
        "python",
        "python3",
        f"python{sys.version_info[0]}.{sys.version_info[1]}",
        sys.executable,
    ), f"the python3 kernel spec at {spec.resource_dir} starts {spec.argv[0]}, not this environment's python"


def _execute(path: Path):
    budget = _remaining_s()
    if budget <= 0:
        pytest.fail(f"the notebooks' overall time budget of {TOTAL_BUDGET_S} s is used up before {path.name}")
    nb = nbformat.read(path, as_version=4)
    start = time.monotonic()
    client = NotebookClient(
        nb,
        kernel_name="python3",
        timeout=CELL_TIMEOUT_S,
        allow_errors=False,
        timeout_func=lambda cell: max(1, int(min(CELL_TIMEOUT_S, _remaining_s()))),
        resources={"metadata": {"path": str(NOTEBOOK_DIR)}},
    )
    client.execute()  # raises CellExecutionError, naming the cell, if a cell fails
    print(f"\n{path.name}: executed in {time.monotonic() - start:.1f} s")
    errors = [
        out for c in nb.cells if c.cell_type == "code" for out in c.outputs if out.output_type == "error"
    ]
    assert not errors
    return nb


@pytest.mark.slow
def test_01_quickstart():
    before = _snapshot(SAMPLE_DATA)
    nb = _execute(NOTEBOOK_DIR / "01_quickstart.ipynb")
    assert _snapshot(SAMPLE_DATA) == before, "the notebook wrote into sample_data/"
    text = _text(nb)
    assert "label: articulated  (ground truth: articulated)" in text
    assert "why: " in text and "moves about a revolute joint" in text  # the video-level reason
    figures = _figures(nb)
    names = [{t.get("name") for t in f["data"]} for f in figures]
    assert any("pair decision" in n for n in names), "no decision timeline was shown"
    arrows = [f for f in figures if any(t["type"] == "cone" for t in f["data"])]
    assert arrows, "no 3-D motion arrows were shown"
    cones = sum(len(_array(t["x"])) for t in arrows[0]["data"] if t["type"] == "cone")
    parts = [
        t for t in arrows[0]["data"] if t["type"] == "scatter3d" and t.get("name", "").startswith("motion ")
    ]
    assert cones >= 2 and len(parts) == cones, (
        f"{cones} arrows for {len(parts)} motions: an articulated pair has two"
    )
    assert any(t["type"] == "image" for f in figures for t in f["data"]), "no frame image was shown"


@pytest.mark.slow
def test_02_parameter_study():
    nb = _execute(NOTEBOOK_DIR / "02_parameter_study.ipynb")
    scratch = re.search(r"rendered \d+ sequences in \d+ s into (\S+)", _text(nb))
    assert scratch, "the notebook did not say where it rendered the sequences"
    assert not Path(scratch.group(1)).exists(), (
        f"the notebook left its generated data behind in {scratch.group(1)}"
    )
    figures = _figures(nb)
    titles = [f["layout"].get("title", {}).get("text", "") for f in figures]
    for what in ("q̄", "t̄", "Frame skip k", "Cell size x", "window w"):
        assert any(what in t for t in titles), f"no figure for {what}: {titles}"
    sweeps = [
        f
        for f in figures
        if "sequence accuracy" in str(f["layout"].get("annotations", ""))
        and any(t["type"] == "scatter" for t in f["data"])
    ]
    assert len(sweeps) >= 5
    for fig in sweeps:  # every curve point is a share in [0, 1]
        ys = np.concatenate([_array(t["y"]).astype(float) for t in fig["data"] if t["type"] == "scatter"])
        assert len(ys) and np.all((ys >= 0.0) & (ys <= 1.0)), ys


@pytest.mark.slow
def test_03_write_a_plugin():
    before = _snapshot(SAMPLE_DATA)
    nb = _execute(NOTEBOOK_DIR / "03_write_a_plugin.ipynb")
    assert _snapshot(SAMPLE_DATA) == before, "the notebook wrote into sample_data/"
    text = _text(nb)
    listed = next(line for line in text.splitlines() if line.startswith("registrars:"))
    assert "'numpy_icp'" in listed and "'icp_point_to_point'" in listed  # beside the built-in ones
    assert "numpy_icp comes from: notebook 03" in text
    assert any(t["type"] == "histogram" for f in _figures(nb) for t in f["data"])
