"""Image loading shared by the readers: every failure names the file and the problem.

The common PNG layouts (8-bit RGB colour, 8- or 16-bit grey depth, masks and labels) are decoded
here when they are plain (not interlaced, no transparency chunk): the chunks' CRCs checked and their
image data inflated by libdeflate (imagecodecs), two to three times as fast as zlib, and the
rows' PNG filters undone in one compiled pass. Any other such PNG goes to imagecodecs' libpng build,
and every other file (other layouts, other formats) to OpenCV. All three give the same pixels, and
all let other threads run while they decode.
"""

from __future__ import annotations

import functools
import json
import struct
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
    ``_PNG_LAYOUTS`` (:func:`_decode_plain_png`, or imagecodecs' libpng for one it leaves); None for
    any other file, and for one neither can decode or hold in memory (OpenCV then decodes it, or finds
    it broken, as it always did).

    A transparency chunk makes imagecodecs add an alpha channel that OpenCV leaves out: such a file
    (rare in depth, masks and colour) is left to OpenCV too."""
    layouts, channels = _PNG_LAYOUTS.get(flags, (set(), 0))
    if not data.startswith(_PNG_SIGNATURE) or len(data) < 26 or (data[24], data[25]) not in layouts:
        return None
    image = _decode_plain_png(data)
    if image is None:
        try:
            image = imagecodecs.png_decode(data)
        except (imagecodecs.PngError, MemoryError):
            return None
    return image if image.shape[2:] == ((channels,) if channels else ()) else None


# Bytes per pixel of the layouts :func:`_decode_plain_png` decodes, by (bit depth, colour type).
_BYTES_PER_PIXEL = {(8, 0): 1, (16, 0): 2, (8, 2): 3}
# Deflate expands its input at most about 1032 times: a header that claims more pixels than the data
# can hold is a broken file, left to the decoders that report it.
_MOST_INFLATION = 1032


def _decode_plain_png(data: bytes) -> np.ndarray | None:
    """A plain PNG (8-bit RGB or 8- or 16-bit grey, not interlaced, without a tRNS chunk, every
    chunk's CRC right) as (H, W, 3) uint8, (H, W) uint8 or (H, W) uint16 (native byte order); None
    for any other file or when anything in it is amiss (another decoder then decides)."""
    if len(data) < 33 or data[12:16] != b"IHDR":
        return None
    width, height, depth, colour, compression, method, interlace = struct.unpack(">IIBBBBB", data[16:29])
    bpp = _BYTES_PER_PIXEL.get((depth, colour))
    compressed = _image_data(data)
    if bpp is None or compression or method or interlace or not width or not height or not compressed:
        return None
    row = width * bpp
    size = height * (row + 1)
    if size > _MOST_INFLATION * len(compressed):
        return None
    try:
        raw = imagecodecs.deflate_decode(compressed, out=size)
    except (imagecodecs.DeflateError, MemoryError):
        return None
    rows = np.empty((height, row), np.uint8)
    if len(raw) != size or not _unfilter()(np.frombuffer(raw, np.uint8).reshape(height, row + 1), bpp, rows):
        return None
    if depth == 16:
        return rows.view(">u2").astype(np.uint16)
    return rows.reshape(height, width, 3) if bpp == 3 else rows


def _image_data(data: bytes) -> bytes | None:
    """The PNG's image data (its IDAT chunks joined), up to its IEND chunk; None when a chunk's CRC is
    wrong, a chunk runs past the end, there is no IEND or there is a tRNS chunk."""
    view, parts, pos = memoryview(data), [], len(_PNG_SIGNATURE)
    while pos + 12 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        stop = pos + 12 + length
        if stop > len(data) or kind == b"tRNS":
            return None
        if (
            imagecodecs.deflate_crc32(view[pos + 4 : stop - 4])
            != struct.unpack(">I", data[stop - 4 : stop])[0]
        ):
            return None
        if kind == b"IEND":
            return b"".join(parts)
        if kind == b"IDAT":
            parts.append(view[pos + 8 : stop - 4])
        pos = stop
    return None


@functools.cache
def _unfilter():
    """The compiled loop that undoes the PNG row filters, compiled (Numba) on first use: importing
    Numba takes a few tenths of a second that a command which reads no PNG need not wait for."""
    from numba import njit

    @njit(cache=True, nogil=True)
    def unfilter(raw, bpp, out):
        """``out`` (H, N) := the rows of ``raw`` (H, 1 + N: each row's filter type, then its
        filtered bytes) with their filters (none, sub, up, average, Paeth) undone, ``bpp`` bytes a
        pixel; False at an unknown filter type. Before the first row and left of the first pixel,
        the bytes count as 0: there, average predicts half the byte above and Paeth the byte above."""
        h, n = out.shape
        zeros = np.zeros(n, np.uint8)
        for y in range(h):
            kind, line, cur = raw[y, 0], raw[y, 1:], out[y]
            up = out[y - 1] if y > 0 else zeros
            if kind == 0:
                cur[:] = line
            elif kind == 1:
                cur[:bpp] = line[:bpp]
                for x in range(bpp, n):
                    cur[x] = (line[x] + cur[x - bpp]) & 255
            elif kind == 2:
                for x in range(n):
                    cur[x] = (line[x] + up[x]) & 255
            elif kind == 3:
                for x in range(bpp):
                    cur[x] = (line[x] + up[x] // 2) & 255
                for x in range(bpp, n):
                    cur[x] = (line[x] + (np.int32(cur[x - bpp]) + up[x]) // 2) & 255
            elif kind == 4:
                for x in range(bpp):
                    cur[x] = (line[x] + up[x]) & 255
                for x in range(bpp, n):
                    a, b, c = np.int32(cur[x - bpp]), np.int32(up[x]), np.int32(up[x - bpp])
                    pa, pb, pc = abs(b - c), abs(a - c), abs(a + b - 2 * c)
                    cur[x] = (line[x] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
            else:
                return False
        return True

    return unfilter


def warm_up() -> None:
    """Load the compiled loop of :func:`_decode_plain_png` (import Numba and its cached machine code),
    so that the first frame read does not pay a few tenths of a second for it."""
    _unfilter()(np.frombuffer(bytes(2), np.uint8).reshape(1, 2), 1, np.empty((1, 1), np.uint8))


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
