"""The hand detector on real photographs (tests/data/hands, see its README), its errors, and the
fetch of its two models from one wheel.

The models come from the user model cache when they are already there (``artclass models fetch
palm_detection hand_landmark`` at set-up), otherwise this session fetches them once into a temporary
folder; that needs the PyPI registry, and a failure fails the tests with pip's message (it is not
skipped).
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from artclass_core import InputError, ParamError, PluginError
from artclass_plugins.segmenters import onnx_models
from artclass_plugins.segmenters.hand_detector import (
    LANDMARK_NAMES,
    HandDetector,
    HandDetectorParams,
    hands_mask,
)

PHOTOS = Path(__file__).parent / "data" / "hands"
MODEL_NAMES = ("palm_detection", "hand_landmark")
# Where the hands are, boxes x0, y0, x1, y1 in pixels drawn by eye around each hand (fingers to
# wrist) in the photos, independently of the detector.
HANDS = {
    "hand_rock_09a619ab.jpg": [(30, 115, 90, 185)],
    "hand_four_06aa70cc.jpg": [(135, 105, 180, 170)],
    "hands_two_00c84257.jpg": [(95, 100, 160, 165), (50, 215, 145, 290)],
}
NO_HANDS = ["no_hand_coco_000000000072.jpg", "no_hand_coco_000000000078.jpg"]


@pytest.fixture(scope="session")
def model_paths(tmp_path_factory) -> dict[str, Path]:
    cached = [onnx_models.model_file(name) for name in MODEL_NAMES]
    try:
        for path, name in zip(cached, MODEL_NAMES):
            onnx_models.verify(path, onnx_models.MODELS[name])
        return dict(zip(MODEL_NAMES, cached))
    except PluginError:
        pass
    try:
        fetched = onnx_models.fetch_all(list(MODEL_NAMES), directory=tmp_path_factory.mktemp("models"))
    except PluginError as exc:
        pytest.fail(
            f"could not fetch the hand models (needs the PyPI registry; run `artclass models fetch "
            f"palm_detection hand_landmark`): {exc}"
        )
    return {name: path for name, (path, _) in zip(MODEL_NAMES, fetched)}


@pytest.fixture(scope="session")
def detector(model_paths) -> HandDetector:
    return HandDetector(_params(model_paths))


def _params(model_paths, **kw) -> HandDetectorParams:
    paths = dict(
        palm_model_path=str(model_paths["palm_detection"]),
        landmark_model_path=str(model_paths["hand_landmark"]),
    )
    return HandDetectorParams(**{**paths, **kw})


def _photo(name: str) -> np.ndarray:
    bgr = cv2.imread(str(PHOTOS / name))
    assert bgr is not None, f"cannot read {name}"
    return np.ascontiguousarray(bgr[..., ::-1])


def _inside(points: np.ndarray, box) -> np.ndarray:
    x0, y0, x1, y1 = box
    return (points[:, 0] >= x0) & (points[:, 0] <= x1) & (points[:, 1] >= y0) & (points[:, 1] <= y1)


# -- real photographs ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(HANDS))
def test_finds_each_hand_where_it_is(detector, name):
    rgb = _photo(name)
    hands = detector.detect(rgb)
    assert len(hands) == len(HANDS[name]), (
        f"{name}: {len(hands)} hands found, {len(HANDS[name])} in the photo"
    )
    assert [h.score for h in hands] == sorted((h.score for h in hands), reverse=True)
    for region in HANDS[name]:
        x0, y0, x1, y1 = region
        found = [h for h in hands if _inside(h.landmarks_px[:, :2], region).mean() >= 0.9]
        assert len(found) == 1, f"{name}: no hand (or several) has its landmarks in {region}"
        hand = found[0]
        assert 0.5 <= hand.score <= 1 and hand.presence >= 0.5 and hand.palm_score >= 0.5
        assert hand.landmarks_px.shape == (21, 3) and hand.landmarks_m.shape == (21, 3)
        assert _inside(hand.landmarks_px[:, :2], hand.box_px).all(), "landmarks outside the hand's box"
        # the mask covers the landmarks and stays on the hand: most of it inside the drawn box
        assert hand.mask.shape == rgb.shape[:2] and hand.mask.dtype == bool
        rows, cols = (
            np.round(hand.landmarks_px[:, 1]).astype(int),
            np.round(hand.landmarks_px[:, 0]).astype(int),
        )
        assert hand.mask[rows.clip(0, rgb.shape[0] - 1), cols.clip(0, rgb.shape[1] - 1)].all()
        inside = hand.mask[y0:y1, x0:x1].sum() / hand.mask.sum()
        assert inside >= 0.8, f"{name}: only {inside:.0%} of the hand mask is on the hand"
    union = hands_mask(hands, rgb.shape[:2])
    assert union.sum() == np.logical_or.reduce([h.mask for h in hands]).sum()


@pytest.mark.parametrize("name", NO_HANDS)
def test_finds_no_hand_in_photos_without_one(detector, name):
    assert detector.detect(_photo(name)) == []


def test_finds_no_hand_in_a_blank_image(detector):
    assert detector.detect(np.full((240, 320, 3), 128, np.uint8)) == []
    assert not hands_mask([], (240, 320)).any()


def test_same_image_same_hands(model_paths, detector):
    rgb = _photo("hands_two_00c84257.jpg")
    first, again = detector.detect(rgb), detector.detect(rgb.copy())
    two_threads = HandDetector(_params(model_paths, threads=2)).detect(rgb)
    for other, tol in ((again, 0.0), (two_threads, 1e-2)):
        assert len(other) == len(first)
        for a, b in zip(first, other):
            np.testing.assert_allclose(b.landmarks_px, a.landmarks_px, atol=tol)
            assert (a.mask == b.mask).mean() > 0.999


def test_landmark_names_follow_the_model():
    assert len(LANDMARK_NAMES) == 21 and len(set(LANDMARK_NAMES)) == 21
    assert (
        LANDMARK_NAMES[0] == "wrist"
        and LANDMARK_NAMES[4] == "thumb_tip"
        and LANDMARK_NAMES[20] == "little_tip"
    )


# -- bad input -------------------------------------------------------------------------------------


def test_missing_model_file_is_a_one_line_error_naming_it(model_paths, tmp_path):
    missing = tmp_path / "palm_detection_full.tflite"
    with pytest.raises(PluginError) as err:
        HandDetector(HandDetectorParams(palm_model_path=str(missing)))
    assert str(missing) in str(err.value) and "\n" not in str(err.value)


def test_missing_cached_model_names_the_fetch_command(monkeypatch, tmp_path):
    monkeypatch.setenv("ARTCLASS_MODELS", str(tmp_path))
    with pytest.raises(PluginError, match=r"artclass models fetch palm_detection") as err:
        HandDetector()
    assert str(tmp_path / "palm_detection_full.tflite") in str(err.value) and "\n" not in str(err.value)


def test_a_file_that_is_not_the_model_says_so(model_paths, tmp_path):
    junk = tmp_path / "junk.tflite"
    junk.write_bytes(b"not a model" * 100)
    with pytest.raises(PluginError, match="not a TensorFlow Lite model") as err:
        HandDetector(_params(model_paths, palm_model_path=str(junk)))
    assert str(junk) in str(err.value)
    swapped = _params(model_paths, palm_model_path=str(model_paths["hand_landmark"]))
    with pytest.raises(PluginError, match=r"not the palm_detection model.*\[1, 192, 192, 3\]"):
        HandDetector(swapped)


@pytest.mark.parametrize(
    "image", [np.zeros((4, 4), np.uint8), np.zeros((4, 4, 4), np.uint8), np.zeros((4, 4, 3), np.float32)]
)
def test_not_an_rgb_image_is_an_input_error(detector, image):
    with pytest.raises(InputError, match=r"\(H, W, 3\) uint8"):
        detector.detect(image)


def test_params_bounds_are_checked():
    with pytest.raises(ParamError, match="threads"):
        HandDetectorParams(threads=0)


# -- fetching both models from one wheel -----------------------------------------------------------


def test_fetch_all_downloads_the_shared_wheel_once(tmp_path, model_paths):
    calls = []

    def download(spec, dest):
        calls.append(spec.requirement)
        wheel = dest / "mediapipe-0.10.21-cp311-cp311-manylinux_2_28_x86_64.whl"
        with zipfile.ZipFile(wheel, "w") as z:
            for name in MODEL_NAMES:
                z.writestr(onnx_models.MODELS[name].member, model_paths[name].read_bytes())
        return wheel

    cache = tmp_path / "cache"
    results = onnx_models.fetch_all(list(MODEL_NAMES), directory=cache, download=download)
    assert calls == ["mediapipe==0.10.21"]
    assert [path.name for path, fetched in results] == [
        "palm_detection_full.tflite",
        "hand_landmark_full.tflite",
    ]
    assert all(fetched for _, fetched in results)
    assert "Apache License" in (cache / "palm_detection_full.LICENSE.txt").read_text()
    assert onnx_models.fetch_all(list(MODEL_NAMES), directory=cache, download=download) == [
        (path, False) for path, _ in results
    ]
    assert len(calls) == 1
