"""benchmarks/replay.py: recorded runs decided again give what a fresh evaluation gives."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

from artclass_core import ArtclassError, Config, find_sequences
from artclass_core.evaluate import evaluate, markdown

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "replay.py"


@pytest.fixture(scope="module")
def replay():
    spec = importlib.util.spec_from_file_location("replay", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules["replay"] = module
    spec.loader.exec_module(module)
    return module


def _labels_only(report: str) -> str:
    """The report without what a replay cannot give again: the parts and joints (it has no clouds to
    score them on) and the time spent segmenting (a clock reading, a little different on every run)."""
    sections = report.split("\n## ")
    kept = "\n## ".join(s for s in sections if not s.startswith("Parts and joints"))
    return "\n".join(line for line in kept.split("\n") if not line.startswith("| segmenting, ms a frame |"))


@pytest.fixture(scope="module")
def runs(replay, registry, data_root, tmp_path_factory) -> Path:
    runs = tmp_path_factory.mktemp("replay") / "runs"
    replay.record(registry, str(data_root), runs, None, [])
    return runs


def test_decided_again_under_a_new_setting_equals_a_fresh_evaluation(replay, registry, data_root, runs):
    assert len(list(runs.glob("*.pkl"))) == len(find_sequences(registry, data_root)[0])
    reports = []
    for params in ([], ["noise_factor=12"], ["w=1", "min_part_share=0.3"]):
        fresh = Config().with_overrides(registry, dict(p.split("=", 1) for p in params))
        expected = markdown([evaluate(registry, find_sequences(registry, data_root)[0], fresh)])
        reports.append(_labels_only(replay.decide(registry, runs, params)))
        assert reports[-1] == _labels_only(expected)
    assert len(set(reports)) == 3  # each setting changes some decision


def test_a_registration_setting_cannot_change(replay, registry, runs):
    with pytest.raises(ArtclassError, match="k 5 -> 4"):
        replay.decide(registry, runs, ["k=4"])
