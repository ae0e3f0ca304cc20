"""Image decoding: the common PNG layouts are decoded here (libdeflate and a compiled pass that undoes
the row filters) or by imagecodecs' libpng, everything else by OpenCV, and the pixels are the same
either way."""

from __future__ import annotations

import struct
import zlib

import cv2
import imagecodecs
import numpy as np
import pytest

from artclass_core import InputError
from artclass_core.io import _decode_plain_png, _decode_png, read_depth, read_label, read_mask, read_rgb

RNG = np.random.default_rng(7)
RGB = RNG.integers(0, 256, (48, 64, 3), dtype=np.uint8)
GREY = RNG.integers(0, 256, (48, 64), dtype=np.uint8)
DEPTH = RNG.integers(0, 65536, (48, 64), dtype=np.uint16)


def png(image: np.ndarray) -> bytes:
    """PNG bytes of an RGB (H, W, 3) or single-channel image."""
    return cv2.imencode(".png", image[..., ::-1] if image.ndim == 3 else image)[1].tobytes()


def chunk(kind: bytes, body: bytes) -> bytes:
    """A PNG chunk: length, type, body, CRC."""
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def with_transparency(data: bytes, payload: bytes) -> bytes:
    """The PNG with a tRNS chunk (``payload``) inserted after its header."""
    chunk = b"tRNS" + payload
    end_of_header = 8 + 8 + 13 + 4  # signature, IHDR's length and type, its 13 bytes, its CRC
    trns = struct.pack(">I", len(payload)) + chunk + struct.pack(">I", zlib.crc32(chunk))
    return data[:end_of_header] + trns + data[end_of_header:]


def opencv(data: bytes, flags: int) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)


@pytest.mark.parametrize(
    "image, read, flags",
    [
        (RGB, read_rgb, cv2.IMREAD_COLOR_RGB),
        (GREY, read_mask, cv2.IMREAD_UNCHANGED),
        (GREY, read_label, cv2.IMREAD_UNCHANGED),
        (DEPTH, read_depth, cv2.IMREAD_UNCHANGED),
    ],
)
def test_the_common_layouts_are_decoded_by_imagecodecs_to_opencvs_pixels(image, read, flags, tmp_path):
    data = png(image)
    decoded = _decode_png(data, flags)
    assert decoded is not None, "this layout should not be left to OpenCV"
    reference = opencv(data, flags)
    assert decoded.dtype == reference.dtype and np.array_equal(decoded, reference)
    path = tmp_path / "image.png"
    path.write_bytes(data)
    kwargs = {"units_per_metre": 1000.0} if read is read_depth else {}
    if read is read_depth:
        expected = reference.astype(np.float32) / np.float32(1000.0)
    elif read is read_mask:
        expected = reference > 0
    else:
        expected = reference
    assert np.array_equal(read(path, **kwargs), expected)


@pytest.mark.parametrize(
    "name, data, flags",
    [
        ("grey with a transparent level", with_transparency(png(GREY), b"\x00\x07"), cv2.IMREAD_UNCHANGED),
        (
            "16-bit grey with a transparent level",
            with_transparency(png(DEPTH), b"\x00\x07"),
            cv2.IMREAD_UNCHANGED,
        ),
        ("RGB with a transparent colour", with_transparency(png(RGB), b"\x00\x01" * 3), cv2.IMREAD_COLOR_RGB),
        ("RGB asked unchanged (OpenCV gives BGR)", png(RGB), cv2.IMREAD_UNCHANGED),
        ("grey asked as colour", png(GREY), cv2.IMREAD_COLOR_RGB),
        ("JPEG", cv2.imencode(".jpg", RGB)[1].tobytes(), cv2.IMREAD_COLOR_RGB),
    ],
)
def test_other_layouts_and_formats_are_left_to_opencv(name, data, flags, tmp_path):
    assert _decode_png(data, flags) is None
    path = tmp_path / "image.bin"
    path.write_bytes(data)
    if flags == cv2.IMREAD_COLOR_RGB:
        assert np.array_equal(read_rgb(path), opencv(data, flags))
    else:
        reference = opencv(data, flags)
        assert np.array_equal(
            read_mask(path), (reference if reference.ndim == 2 else reference.max(axis=2)) > 0
        )


@pytest.mark.parametrize("image, read", [(RGB, read_rgb), (GREY, read_mask), (DEPTH, read_depth)])
@pytest.mark.parametrize("keep", [0.5, 0.95])
def test_a_truncated_png_is_the_same_input_error_as_before(image, read, keep, tmp_path):
    data = png(image)
    path = tmp_path / "cut.png"
    path.write_bytes(data[: int(len(data) * keep)])
    kwargs = {"units_per_metre": 1000.0} if read is read_depth else {}
    with pytest.raises(InputError, match="cut.png.*unreadable or truncated image"):
        read(path, **kwargs)


@pytest.mark.parametrize("read", [read_rgb, read_mask, read_depth])
def test_a_png_whose_header_claims_billions_of_pixels_is_an_input_error(read, tmp_path):
    header = struct.pack(">IIBBBBB", 60000, 60000, 16, 0, 0, 0, 0)  # 16-bit grey, 3.6e9 pixels
    path = tmp_path / "huge.png"
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(b"\0" * 16))
        + chunk(b"IEND", b"")
    )
    kwargs = {"units_per_metre": 1000.0} if read is read_depth else {}
    with pytest.raises(InputError, match="huge.png.*too large"):
        read(path, **kwargs)


def paeth(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    pa, pb, pc = np.abs(b - c), np.abs(a - c), np.abs(a + b - 2 * c)
    return np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))


def filtered_png(image: np.ndarray, *, interlace: int = 0, idat_bytes: int = 500) -> bytes:
    """PNG bytes of ``image`` whose rows use each of the five filter types in turn, its data split
    into several IDAT chunks (an encoder written from the PNG specification)."""
    depth = 16 if image.dtype == np.uint16 else 8
    colour = 2 if image.ndim == 3 else 0
    h, w = image.shape[:2]
    rows = (image.astype(">u2") if depth == 16 else image).view(np.uint8).reshape(h, -1).astype(np.int32)
    bpp = rows.shape[1] // w
    lines = []
    for y in range(h):
        x = rows[y]
        up = rows[y - 1] if y else np.zeros_like(x)
        left = np.concatenate([np.zeros(bpp, np.int32), x[:-bpp]])
        corner = np.concatenate([np.zeros(bpp, np.int32), up[:-bpp]])
        kind = y % 5
        predictor = [0 * x, left, up, (left + up) // 2, paeth(left, up, corner)][kind]
        lines.append(bytes([kind]) + ((x - predictor) % 256).astype(np.uint8).tobytes())
    data = zlib.compress(b"".join(lines))
    header = struct.pack(">IIBBBBB", w, h, depth, colour, 0, 0, interlace)
    idat = b"".join(chunk(b"IDAT", data[i : i + idat_bytes]) for i in range(0, len(data), idat_bytes))
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + idat + chunk(b"IEND", b"")


@pytest.mark.parametrize("image", [RGB, GREY, DEPTH], ids=["rgb", "grey", "16-bit grey"])
def test_every_row_filter_is_undone_as_libpng_does(image):
    data = filtered_png(image)
    decoded = _decode_plain_png(data)
    assert decoded is not None and decoded.dtype == image.dtype
    np.testing.assert_array_equal(decoded, image)
    np.testing.assert_array_equal(decoded, imagecodecs.png_decode(data))


def test_opencvs_own_pngs_are_decoded_here():
    for image in (RGB, GREY, DEPTH):
        decoded = _decode_plain_png(png(image))
        assert decoded is not None
        np.testing.assert_array_equal(decoded, image)


def test_a_png_with_a_wrong_crc_is_left_to_libpng_and_is_unreadable(tmp_path):
    data = bytearray(filtered_png(RGB))
    data[-13] ^= 1  # the last IDAT chunk's CRC
    assert _decode_plain_png(bytes(data)) is None
    path = tmp_path / "crc.png"
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match="crc.png.*unreadable"):
        read_rgb(path)


def test_interlaced_and_transparent_pngs_are_left_to_libpng():
    assert _decode_plain_png(filtered_png(GREY, interlace=1)) is None
    assert _decode_plain_png(with_transparency(png(GREY), b"\x00\x07")) is None
    assert _decode_plain_png(png(GREY)[:-12]) is None  # no IEND
