"""Image loading shared by the readers: every failure names the file and the problem.

The common PNG layouts (8-bit RGB colour, 8- or 16-bit grey depth, masks and labels) are decoded by
imagecodecs' libpng build, whose zlib-ng inflates about a third faster than the zlib OpenCV links;
every other file (other layouts, other formats) by OpenCV. Both give the same pixels, and both let
other threads run while they decode.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import imagecodecs
import numpy as np

from .errors import InputError

# Decoding straight to RGB order saves the copy of a BGR-to-RGB conversion.
_COLOR_RGB = getattr(cv2, "IMREAD_COLOR_RGB", None)
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# The PNG layouts imagecodecs decodes, as (bit depth, colour type) of the header, for the OpenCV flags
# they stand in for, with the channels OpenCV gives for them (0: a single-channel (H, W) image).
_PNG_LAYOUTS = {
    _COLOR_RGB: ({(8, 2)}, 3),  # 8-bit RGB, decoded to RGB order as imagecodecs does
    cv2.IMREAD_UNCHANGED: ({(8, 0), (16, 0)}, 0),  # 8- or 16-bit grey
}


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
    data = path.read_bytes()
    image = _decode_png(data, flags)
    if image is None:
        with _quiet_opencv():
            try:
                image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags) if data else None
            except cv2.error:  # OpenCV refuses a header that claims more pixels than it will hold
                raise InputError(
                    "image too large to decode (its header claims more pixels than the decoder accepts)",
                    path=path,
                ) from None
    if image is None:
        raise InputError("unreadable or truncated image", path=path)
    return image


def _decode_png(data: bytes, flags: int) -> np.ndarray | None:
    """The image as OpenCV's ``imdecode(data, flags)`` gives it, for a PNG of a layout in
    ``_PNG_LAYOUTS``; None for any other file, and for one imagecodecs cannot decode or hold in memory
    (OpenCV then decodes it, or finds it broken, as it always did).

    A transparency chunk makes imagecodecs add an alpha channel that OpenCV leaves out: such a file
    (rare in depth, masks and colour) is left to OpenCV too."""
    layouts, channels = _PNG_LAYOUTS.get(flags, (set(), 0))
    if not data.startswith(_PNG_SIGNATURE) or len(data) < 26 or (data[24], data[25]) not in layouts:
        return None
    try:
        image = imagecodecs.png_decode(data)
    except (imagecodecs.PngError, MemoryError):
        return None
    return image if image.shape[2:] == ((channels,) if channels else ()) else None


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
