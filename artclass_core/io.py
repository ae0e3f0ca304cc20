"""Image loading shared by the readers: every failure names the file and the problem."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .errors import InputError

# Decoding straight to RGB order saves the copy of a BGR-to-RGB conversion.
_COLOR_RGB = getattr(cv2, "IMREAD_COLOR_RGB", None)


class _QuietOpenCV:
    """OpenCV's log silenced while any thread decodes an image: OpenCV logs its own warning for a
    truncated file, and the InputError of :func:`_read` is the one message shown.

    The log level is process-wide, so the first decoder in silences it and the last one out restores
    it; each thread saving and restoring the level itself would, when two decodes overlap, leave the
    log silenced for good."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._decoding = 0
        self._level = cv2.utils.logging.LOG_LEVEL_WARNING

    @contextmanager
    def __call__(self) -> Iterator[None]:
        with self._lock:
            if self._decoding == 0:
                self._level = cv2.utils.logging.getLogLevel()
                cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
            self._decoding += 1
        try:
            yield
        finally:
            with self._lock:
                self._decoding -= 1
                if self._decoding == 0:
                    cv2.utils.logging.setLogLevel(self._level)


_quiet_opencv = _QuietOpenCV()


def _read(path: Path, flags: int) -> np.ndarray:
    if not path.is_file():
        raise InputError("file not found", path=path)
    # Read as bytes: Python's file read lets other threads run meanwhile; numpy's fromfile does not.
    data = np.frombuffer(path.read_bytes(), dtype=np.uint8)
    with _quiet_opencv():
        image = cv2.imdecode(data, flags) if data.size else None
    if image is None:
        raise InputError("unreadable or truncated image", path=path)
    return image


def read_rgb(path: Path) -> np.ndarray:
    """8-bit colour image as (H, W, 3) uint8 in RGB order."""
    if _COLOR_RGB is None:  # OpenCV before 4.10 decodes to BGR only
        return cv2.cvtColor(_read(Path(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    return _read(Path(path), _COLOR_RGB)


def read_depth(path: Path, *, units_per_metre: float) -> np.ndarray:
    """16-bit depth image as (H, W) float32 metres (0 = no reading)."""
    path = Path(path)
    image = _read(path, cv2.IMREAD_UNCHANGED)
    if image.dtype != np.uint16 or image.ndim != 2:
        raise InputError(
            f"depth must be a single-channel 16-bit image, got {image.dtype} with "
            f"{1 if image.ndim == 2 else image.shape[2]} channel(s)",
            path=path,
        )
    return image.astype(np.float32) / np.float32(units_per_metre)


def read_mask(path: Path) -> np.ndarray:
    """Mask image as (H, W) bool: non-zero = object."""
    image = _read(Path(path), cv2.IMREAD_UNCHANGED)
    return (image if image.ndim == 2 else image.max(axis=2)) > 0


def read_label(path: Path) -> np.ndarray:
    """Single-channel integer label image (e.g. per-pixel object ids) as (H, W), dtype as stored."""
    path = Path(path)
    image = _read(path, cv2.IMREAD_UNCHANGED)
    if image.ndim != 2 or image.dtype.kind not in "ui":
        raise InputError(
            f"label image must be a single-channel integer image, got {image.dtype} with "
            f"{1 if image.ndim == 2 else image.shape[2]} channel(s)",
            path=path,
        )
    return image


def read_json(path: Path) -> dict[str, Any]:
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid JSON ({exc})", path=path) from None
    if not isinstance(data, dict):
        raise InputError("expected a JSON object", path=path)
    return data


def require_number(data: dict, key: str, *, path: Path, positive: bool = True) -> float:
    """``data[key]`` as a finite float, or an InputError naming the file and the key."""
    try:
        value = float(data[key])
    except KeyError:
        raise InputError(
            f"missing {key!r} (camera intrinsics and depth scale are required)", path=path
        ) from None
    except (TypeError, ValueError):
        raise InputError(f"{key!r} is not a number: {data[key]!r}", path=path) from None
    if not np.isfinite(value) or (positive and value <= 0):
        raise InputError(f"{key!r} must be a positive finite number, got {value}", path=path)
    return value
