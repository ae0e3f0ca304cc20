"""Image reading from several threads at once, as the pipeline's workers do."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
import pytest

from artclass_core import InputError
from artclass_core.io import read_depth, read_rgb


def test_reads_on_several_threads_leave_opencvs_log_level_as_it_was(tmp_path):
    rng = np.random.default_rng(0)
    colour, depth = tmp_path / "rgb.png", tmp_path / "depth.png"
    cv2.imwrite(str(colour), rng.integers(0, 256, (120, 160, 3), dtype=np.uint8))
    cv2.imwrite(str(depth), rng.integers(0, 5000, (120, 160), dtype=np.uint16))
    before = cv2.utils.logging.getLogLevel()
    assert before != cv2.utils.logging.LOG_LEVEL_SILENT
    with ThreadPoolExecutor(4) as pool:
        images = list(
            pool.map(
                lambda i: read_rgb(colour) if i % 2 else read_depth(depth, units_per_metre=1000.0),
                range(400),
            )
        )
    assert cv2.utils.logging.getLogLevel() == before
    assert images[1].shape == (120, 160, 3) and images[0].dtype == np.float32


def test_a_truncated_image_is_one_input_error_naming_the_file(tmp_path):
    path = tmp_path / "cut.png"
    ok, data = cv2.imencode(".png", np.zeros((40, 40, 3), np.uint8))
    path.write_bytes(data.tobytes()[:60])
    with pytest.raises(InputError, match="cut.png"):
        read_rgb(path)
    assert cv2.utils.logging.getLogLevel() != cv2.utils.logging.LOG_LEVEL_SILENT
