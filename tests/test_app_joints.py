"""The analyse page's parts and joints: the parts in colour, the joint axis as a 3D arrow and the
joint state over the video, through ``streamlit.testing.v1.AppTest`` on a bundled sample."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from streamlit.testing.v1 import AppTest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from artclass_core import Config, Pipeline, load_registry, open_sequences  # noqa: E402

APP = str(ROOT / "app" / "streamlit_app.py")
LAPTOP = ROOT / "sample_data" / "laptop_articulate"


def _spec(at: AppTest, key: str) -> dict:
    (element,) = [e for e in at.get("plotly_chart") if e.key == key]
    return json.loads(element.proto.spec)


def _values(value) -> np.ndarray:
    """A trace's data array as plotted: a list, or Plotly's typed-array form {dtype, bdata}."""
    if isinstance(value, dict) and "bdata" in value:
        import base64

        return np.frombuffer(base64.b64decode(value["bdata"]), dtype=np.dtype(value["dtype"]))
    return np.array([np.nan if v is None else v for v in value], float)


@pytest.fixture(scope="module")
def laptop_page():
    import os

    old = os.environ.get("ARTCLASS_SAMPLE_DATA")
    os.environ["ARTCLASS_SAMPLE_DATA"] = str(ROOT / "sample_data")
    try:
        at = AppTest.from_file(APP, default_timeout=300).run()
        at.selectbox(key="an_sample").set_value(LAPTOP.name).run()
    finally:
        if old is None:
            os.environ.pop("ARTCLASS_SAMPLE_DATA")
        else:
            os.environ["ARTCLASS_SAMPLE_DATA"] = old
    assert not at.exception, [e.value for e in at.exception]
    assert not at.error, [e.value for e in at.error]
    return at


@pytest.fixture(scope="module")
def expected():
    registry = load_registry()
    seq = open_sequences(registry, LAPTOP)[0]
    result = Pipeline(registry, Config()).run(seq, keep_clouds=True)
    finder = registry.create("part_finder", "tracks")
    return finder.find(result, estimator=registry.create("joint_estimator", "bic"))


def test_the_page_says_which_joint_in_one_line(laptop_page, expected):
    assert "Parts and joints" in [h.value for h in laptop_page.subheader]
    assert any(expected.summary() in m.value for m in laptop_page.markdown)
    assert expected.joints and expected.joints[0].estimate.type == "revolute"


def test_parts_in_colour_and_the_axis_as_an_arrow(laptop_page, expected):
    spec = _spec(laptop_page, "an_joints_3d")
    points = {t["name"]: t for t in spec["data"] if t["type"] == "scatter3d" and t.get("mode") == "markers"}
    assert set(points) == {"base", "part1"}
    assert points["base"]["marker"]["color"] != points["part1"]["marker"]["color"]
    (cone,) = [t for t in spec["data"] if t["type"] == "cone"]
    arrow = np.array([_values(cone[c])[0] for c in "uvw"])
    direction = expected.joints[0].estimate.axis_direction
    assert abs(arrow @ direction) / np.linalg.norm(arrow) == pytest.approx(1.0, abs=1e-6)  # along the axis
    image = _spec(laptop_page, "an_joints_image")
    assert image["data"][0]["type"] == "image"


def test_the_joint_state_over_the_video(laptop_page, expected):
    spec = _spec(laptop_page, "an_joints_states")
    (line,) = [t for t in spec["data"] if t.get("mode") == "lines+markers"]
    plotted = _values(line["y"])
    states = np.degrees(expected.joints[0].estimate.states)
    np.testing.assert_allclose(plotted, states, atol=1e-6)
    assert np.nanmax(plotted) > 10  # the lid opens by tens of degrees
