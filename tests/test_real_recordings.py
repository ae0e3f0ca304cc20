"""Real recordings of rigid objects (../shared/data): the default pipeline never calls them articulated."""

from __future__ import annotations

import pytest

from artclass_core import Config, Pipeline, load_registry, open_sequences

pytestmark = pytest.mark.slow  # 49 frames at 640x480 per run


@pytest.mark.parametrize("k", [1, 2, 5])
def test_a_cabinet_circled_by_the_camera_is_never_articulated(shared_data, k):
    """TUM RGB-D's fr3 cabinet: a Kinect circling a static cabinet, key frames 6-26 cm and 2-15 degrees
    apart (at k = 5, 16-68 degrees): one rigid body, whatever the pairs show."""
    registry = load_registry()
    (seq,) = open_sequences(registry, shared_data / "real_moving" / "tum_fr3_cabinet")
    result = Pipeline(registry, Config().with_overrides(registry, dict(k=k))).run(seq, workers=2)
    assert result.label == "rigid", result.reason
    decided = [p for p in result.pairs if p.decision in ("AM", "RM", "NM")]
    assert sum(p.decision == "RM" for p in decided) > 0.8 * len(decided)
