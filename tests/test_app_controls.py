"""``app/controls.py``: the sidebar's sliders, built from the parameter metadata."""

from __future__ import annotations

import pytest

from app import controls
from artclass_core import PipelineParams, describe


# -- controls.py: sliders from the metadata ----------------------------------------------------------------
def test_slider_options_hold_every_default_within_bounds(registry):
    classes = [PipelineParams] + [
        registry.get(kind, name).Params
        for kind in ("segmenter", "preprocessor", "registrar", "rule")
        for name in registry.names(kind)
    ]
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
    x = controls.slider_options(specs["cell_size_m"])  # 0.1 mm .. 10 m: logarithmic
    assert x[0] == pytest.approx(1e-4) and x[-1] == 10.0 and 0.03 in x and 40 < len(x) < 80
    alpha = controls.slider_options(specs["alpha"])  # a fraction: even steps of 0.01
    assert alpha[:3] == [0.0, 0.01, 0.02] and alpha[-1] == 1.0 and 0.3 in alpha
    k = controls.slider_options(specs["k"])
    assert k[:21] == list(range(1, 22)) and k[-1] == 1000
    assert controls.nearest_option(x, 0.0317) == 0.03
    assert controls.format_value(specs["cell_size_m"], 0.005) == "5 mm"
    assert controls.format_value(specs["k"], 5) == "5 frames"
    assert controls.format_value(specs["cell_size_m"], None) == "auto"
    assert controls.label(specs["alpha"]) == "α · alpha" and controls.label(specs["k"]) == "k"
