"""ROS 1 and ROS 2 bags, and the RealSense SDK's recordings, read with ``rosbags`` (pure Python).

::

    REC.bag              a ROS 1 bag, or a RealSense Viewer / rs-record recording (SDK 2.5x and older)
    REC/                 a ROS 2 bag folder: metadata.yaml and its .db3 or .mcap files
    REC.db3, REC.mcap    a ROS 2 storage file on its own (newer RealSense SDKs record a .db3)

Topics: a colour and a depth image topic (``sensor_msgs/Image`` or ``CompressedImage``), found by
name (``color``, ``colour``, ``rgb`` / ``depth``; a depth topic aligned to colour first, raw images
before compressed ones) or named by the parameters ``colour_topic`` and ``depth_topic``. Both the
usual ROS topics (``/camera/color/image_raw`` with ``/camera/aligned_depth_to_color/image_raw``)
and the RealSense SDK's own layout (``/device_0/sensor_*/Color_0/image/data`` ...) are recognised.

Encodings: colour ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``, ``mono8`` (or JPEG / PNG compressed);
depth ``16UC1`` and ``mono16`` (millimetres, or the RealSense recording's ``Depth Units``),
``32FC1`` (metres), or ``compressedDepth`` PNG.

Pairing: colour and depth messages are paired by their header stamps, within ``max_time_diff_s``, as
TUM's ``associate.py`` does. ``start_s`` and ``stop_s`` choose a window in the bag's own time (the
time each message was recorded), counted from the first colour or depth image; ``every`` keeps every
n-th pair.

Intrinsics: the ``sensor_msgs/CameraInfo`` topic next to the colour topic (``K``); or the parameters
``fx``, ``fy``, ``cx``, ``cy``. Lens distortion is not undone.

Registration: depth is taken as registered to the colour image when its topic says so
(``aligned_depth_to_color``, ``depth_registered``) or both images carry the same ``frame_id``.
Otherwise (a RealSense recording without the aligned stream, a ROS bag of ``/camera/depth/...``)
each depth image is moved into the colour camera with the extrinsics the bag holds (the RealSense
streams' ``tf`` topics, or ``/tf_static``) and the depth camera's own ``CameraInfo``, keeping the
nearest surface where several depth pixels land on one colour pixel.

The bag is read in two streaming passes: one over the image topics' message headers when it is
opened (the stamps; images are not kept), and one reading each pair when it is asked for. Memory
does not grow with the bag's length.
"""

from __future__ import annotations

import struct
import threading
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numba import njit

from artclass_core import Frame, InputError, Intrinsics, Params, Reader, Sequence, param

from .tum import associate

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
#: Colour encodings: channels of the message and how to reach RGB order.
COLOUR_ENCODINGS = {
    "rgb8": (3, None),
    "bgr8": (3, cv2.COLOR_BGR2RGB),
    "rgba8": (4, cv2.COLOR_RGBA2RGB),
    "bgra8": (4, cv2.COLOR_BGRA2RGB),
    "mono8": (1, cv2.COLOR_GRAY2RGB),
}
#: Depth encodings: numpy type and metres per unit (None: the recording's depth units).
DEPTH_ENCODINGS = {"16UC1": ("u2", None), "mono16": ("u2", None), "32FC1": ("f4", 1.0)}
MILLIMETRE = 0.001  # metres per unit of 16-bit depth in ROS (REP 118)
SUFFIXES = (".bag", ".db3", ".mcap")
ALIGNED_WORDS = ("aligned_depth_to_colo", "depth_registered")
# A reader cursor that would have to skip more messages than this to reach the one asked for starts
# afresh at it instead (the bag's index finds a time at once).
MAX_SKIP = 16


def _intrinsic(what: str, *, bounds: tuple[float, float]) -> Any:
    """A colour camera intrinsic parameter, in pixels; by default the bag's CameraInfo's."""
    return param(None, unit="px", bounds=bounds, auto="the bag's CameraInfo", help=f"{what} (colour camera).")


@dataclass(frozen=True)
class BagParams(Params):
    colour_topic: str = param("", help="The colour image topic; empty: found by its name.")
    depth_topic: str = param("", help="The depth image topic; empty: found by its name.")
    max_time_diff_s: float = param(
        0.02,
        unit="s",
        bounds=(0.0, 1.0),
        help="Colour and depth images further apart in time (header stamps) than this are not paired.",
    )
    start_s: float = param(
        0.0,
        unit="s",
        bounds=(0.0, 1e6),
        help="Skip the recording's first seconds (bag time, from the first image).",
    )
    stop_s: float | None = param(
        None,
        unit="s",
        bounds=(0.0, 1e6),
        auto="the end of the recording",
        help="Read up to this many seconds after the first image (bag time).",
    )
    every: int = param(1, unit="frames", bounds=(1, 10000), help="Keep every n-th colour-depth pair.")
    fx: float | None = _intrinsic("Focal length along x", bounds=(1e-3, 1e5))
    fy: float | None = _intrinsic("Focal length along y", bounds=(1e-3, 1e5))
    cx: float | None = _intrinsic("Principal point's column", bounds=(-1e5, 1e5))
    cy: float | None = _intrinsic("Principal point's row", bounds=(-1e5, 1e5))


# -- opening a bag --------------------------------------------------------------------------------


def is_bag(path: Path) -> bool:
    """A ROS 1 bag, a ROS 2 storage file or a ROS 2 bag folder (by name; not read)."""
    path = Path(path)
    if path.is_file():
        return path.suffix.lower() in SUFFIXES
    return path.is_dir() and (path / "metadata.yaml").is_file()


def _errors() -> tuple[type[BaseException], ...]:
    """What ``rosbags`` raises on a damaged or foreign file."""
    import apsw
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error
    from rosbags.serde import SerdeError

    return (
        AnyReaderError,
        Reader1Error,
        Reader2Error,
        SerdeError,
        apsw.Error,
        OSError,
        EOFError,
        struct.error,
        ValueError,
        KeyError,
        AssertionError,
    )


def open_reader(path: Path):
    """An open ``rosbags`` ``AnyReader`` (close it when done); a file that is not a readable bag
    raises :class:`InputError` naming it."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    ros1 = Path(path).suffix.lower() == ".bag"
    # A recording without message definitions (the RealSense SDK's .db3) is read with the standard ones.
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    try:
        reader = AnyReader([Path(path)], default_typestore=store)
        reader.open()
    except _errors() as exc:
        raise InputError(f"not a readable bag ({_one_line(exc)})", path=path) from None
    return reader


@contextmanager
def open_bag(path: Path) -> Iterator[Any]:
    """:func:`open_reader` for a ``with`` block; a damaged message in it raises :class:`InputError`."""
    reader = open_reader(path)
    try:
        yield reader
    except _errors() as exc:
        raise InputError(f"damaged bag ({_one_line(exc)})", path=path) from None
    finally:
        reader.close()


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) < 160 else text[:157] + "..."


# -- topics ---------------------------------------------------------------------------------------


@dataclass
class ImageTopic:
    """One image topic of a bag: its connections, and the first message's layout."""

    name: str
    msgtype: str
    connections: list
    count: int
    encoding: str = ""
    frame_id: str = ""
    width: int = 0
    height: int = 0
    times_ns: list[int] = field(default_factory=list)  # bag time of each message in the window
    stamps_ns: list[int] = field(default_factory=list)  # header stamp of each

    @property
    def compressed(self) -> bool:
        return self.msgtype == COMPRESSED

    @property
    def realsense_stream(self) -> str | None:
        """``/device_0/sensor_1/Color_0`` for a topic of the RealSense SDK's layout, else None."""
        parts = self.name.split("/")
        if len(parts) > 4 and parts[1].startswith("device_") and parts[2].startswith("sensor_"):
            return "/".join(parts[:4])
        return None


def _image_topics(reader) -> dict[str, ImageTopic]:
    return {
        name: ImageTopic(name, info.msgtype, list(info.connections), info.msgcount)
        for name, info in reader.topics.items()
        if info.msgtype in (IMAGE, COMPRESSED) and info.msgcount
    }


def _depth_rank(t: ImageTopic) -> tuple:
    name = t.name.lower()
    aligned = any(w in name for w in ALIGNED_WORDS)
    return (not aligned, t.compressed, -t.count, t.name)


def _colour_rank(t: ImageTopic) -> tuple:
    return (t.compressed, -t.count, t.name)


def _is_depth(name: str) -> bool:
    return "depth" in name.lower()


def _is_colour(name: str) -> bool:
    name = name.lower()
    return not _is_depth(name) and any(w in name for w in ("color", "colour", "rgb"))


def choose_topics(reader, params: BagParams, *, path: Path) -> tuple[ImageTopic, ImageTopic]:
    """The colour and depth image topics: those named by ``params``, else the best by name."""
    topics = _image_topics(reader)
    listed = ", ".join(sorted(topics)) or "none"

    def pick(kind: str, named: str, test, rank) -> ImageTopic:
        if named:
            if named not in topics:
                raise InputError(f"no image topic {named!r} (image topics: {listed})", path=path)
            return topics[named]
        found = sorted((t for n, t in topics.items() if test(n)), key=rank)
        if not found:
            raise InputError(
                f"no {kind} image topic (image topics: {listed}); name one with --param {kind}_topic=...",
                path=path,
            )
        return found[0]

    return (
        pick("colour", params.colour_topic, _is_colour, _colour_rank),
        pick("depth", params.depth_topic, _is_depth, _depth_rank),
    )


def _stamp_ns(msg) -> int:
    stamp = msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def first_time(reader, colour: ImageTopic, depth: ImageTopic) -> int:
    """Bag time (ns) of the first colour or depth image."""
    for _connection, t_ns, _raw in reader.messages(connections=colour.connections + depth.connections):
        return t_ns
    return reader.start_time


def index_topics(
    reader, colour: ImageTopic, depth: ImageTopic, *, start_ns: int, stop_ns: int | None
) -> None:
    """Fill each topic's bag times and header stamps over the window, and its first message's layout,
    in one pass over the two topics (the images are not kept)."""
    by_connection = {id(c): colour for c in colour.connections}
    by_connection.update({id(c): depth for c in depth.connections})
    for connection, t_ns, raw in reader.messages(
        connections=colour.connections + depth.connections, start=start_ns, stop=stop_ns
    ):
        topic = by_connection[id(connection)]
        msg = reader.deserialize(raw, connection.msgtype)
        if not topic.times_ns:
            topic.frame_id = msg.header.frame_id
            if topic.compressed:
                topic.encoding = msg.format
            else:
                topic.encoding, topic.width, topic.height = msg.encoding, int(msg.width), int(msg.height)
        topic.times_ns.append(t_ns)
        topic.stamps_ns.append(_stamp_ns(msg))


def _first(reader, topic: str, msgtype: str | None = None):
    """The first message of ``topic`` (deserialised), or None."""
    info = reader.topics.get(topic)
    if info is None or (msgtype and info.msgtype != msgtype):
        return None
    for connection, _t, raw in reader.messages(connections=info.connections):
        return reader.deserialize(raw, connection.msgtype)
    return None


def _shared(a: str, b: str) -> int:
    """How many leading parts of two topic names agree."""
    n = 0
    for x, y in zip(a.split("/"), b.split("/")):
        if x != y:
            break
        n += 1
    return n


def _nearest_topic(reader, near: str, msgtype: str, *, not_nearer: str = "") -> str | None:
    """The topic of ``msgtype`` sharing the longest leading path with ``near`` (its first part at
    least), e.g. ``/camera/color/camera_info`` for ``/camera/color/image_raw``; one that shares more
    with ``not_nearer`` (the other image topic) belongs to that one and is not taken."""
    found = [
        (_shared(name, near), -len(name), name)
        for name, info in reader.topics.items()
        if info.msgtype == msgtype and info.msgcount
    ]
    found = [f for f in found if f[0] >= 2 and (not not_nearer or f[0] >= _shared(f[2], not_nearer))]
    return max(found)[2] if found else None


# -- camera models --------------------------------------------------------------------------------


def _field(msg, name: str):
    """A message field under its ROS 2 (lower-case) or ROS 1 (upper-case) name."""
    return getattr(msg, name, None) if hasattr(msg, name) else getattr(msg, name.upper())


def camera_info(reader, image: ImageTopic, *, other: ImageTopic, path: Path) -> tuple[Intrinsics, str] | None:
    """The intrinsics of ``image`` from the ``CameraInfo`` topic nearest it (not one nearer ``other``,
    the other image topic), and that topic; None if the bag has none."""
    topic = _nearest_topic(reader, image.name, CAMERA_INFO, not_nearer=other.name)
    msg = None if topic is None else _first(reader, topic)
    if msg is None:
        return None
    K = np.asarray(_field(msg, "k"), dtype=float)
    width, height = int(msg.width), int(msg.height)
    if image.width and width and (width, height) != (image.width, image.height):
        raise InputError(
            f"CameraInfo on {topic} is for {width}x{height} images, but {image.name} holds "
            f"{image.width}x{image.height}",
            path=path,
        )
    intrinsics = Intrinsics(K[0], K[4], K[2], K[5], width=image.width or width, height=image.height or height)
    return intrinsics, topic


def _rs_depth_units(reader, depth: ImageTopic) -> float | None:
    """The RealSense recording's depth units (metres per unit), from its depth sensor's option topic."""
    sensor = depth.realsense_stream.rsplit("/", 1)[0]
    for topic in (f"{sensor}/option/Depth Units/value", f"{sensor}/option/Depth_Units/value"):
        msg = _first(reader, topic)
        if msg is not None:
            return float(msg.data)
    return None


def _transform(translation, rotation) -> np.ndarray:
    """4x4 matrix of a ``geometry_msgs`` translation and quaternion."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([rotation.x, rotation.y, rotation.z, rotation.w]).as_matrix()
    T[:3, 3] = [translation.x, translation.y, translation.z]
    return T


def _rs_extrinsics(reader, stream: str) -> dict[str, np.ndarray]:
    """``{reference: T_stream_from_reference}`` of a RealSense stream, from its ``tf`` topics: a
    ``geometry_msgs/Transform`` (ROS 1 recordings) or the text ``rotation=9 numbers (column-major);
    translation=3 numbers`` (ROS 2 recordings)."""
    out = {}
    for name in reader.topics:
        if not name.startswith(f"{stream}/tf/"):
            continue
        msg = _first(reader, name)
        if msg is None:
            continue
        if hasattr(msg, "translation"):
            T = _transform(msg.translation, msg.rotation)
        else:
            values = dict(item.split("=", 1) for item in str(msg.data).split(";") if "=" in item)
            T = np.eye(4)
            T[:3, :3] = np.array([float(v) for v in values["rotation"].split(",")]).reshape(3, 3).T
            T[:3, 3] = [float(v) for v in values["translation"].split(",")]
        out[name.rsplit("/", 1)[1]] = T
    return out


def _tf_static(reader) -> dict[tuple[str, str], np.ndarray]:
    """``{(parent, child): T_parent_from_child}`` of every transform on ``/tf_static``."""
    info = reader.topics.get("/tf_static")
    out = {}
    if info is None:
        return out
    for connection, _t, raw in reader.messages(connections=info.connections):
        for tf in reader.deserialize(raw, connection.msgtype).transforms:
            out[(tf.header.frame_id.lstrip("/"), tf.child_frame_id.lstrip("/"))] = _transform(
                tf.transform.translation, tf.transform.rotation
            )
    return out


def _chain(edges: dict[tuple[str, str], np.ndarray], target: str, source: str) -> np.ndarray | None:
    """T_target_from_source through a tree of ``{(parent, child): T_parent_from_child}``; None if the
    two frames are not connected."""
    links: dict[str, list[tuple[str, np.ndarray]]] = {}
    for (parent, child), T in edges.items():
        links.setdefault(child, []).append((parent, T))
        links.setdefault(parent, []).append((child, np.linalg.inv(T)))
    seen, todo = {source}, deque([(source, np.eye(4))])
    while todo:
        frame, T_frame_from_source = todo.popleft()
        if frame == target:
            return T_frame_from_source
        for other, T_other_from_frame in links.get(frame, ()):
            if other not in seen:
                seen.add(other)
                todo.append((other, T_other_from_frame @ T_frame_from_source))
    return None


def depth_to_colour(reader, colour: ImageTopic, depth: ImageTopic) -> tuple[np.ndarray, str] | None:
    """``T_colour_from_depth`` (4x4, metres) from the bag's extrinsics and where it was found; None
    when the bag holds none."""
    if colour.realsense_stream and depth.realsense_stream:
        to_colour = _rs_extrinsics(reader, colour.realsense_stream)
        to_depth = _rs_extrinsics(reader, depth.realsense_stream)
        for ref in sorted(set(to_colour) & set(to_depth)):
            return to_colour[ref] @ np.linalg.inv(to_depth[ref]), f"{depth.realsense_stream}/tf/{ref}"
    if colour.frame_id and depth.frame_id:
        T = _chain(_tf_static(reader), colour.frame_id.lstrip("/"), depth.frame_id.lstrip("/"))
        if T is not None:
            return T, "/tf_static"
    return None


def is_registered(colour: ImageTopic, depth: ImageTopic) -> bool:
    """Whether the depth images are already in the colour camera (see the module docstring)."""
    if any(w in depth.name.lower() for w in ALIGNED_WORDS):
        return True
    return depth.realsense_stream is None and depth.frame_id == colour.frame_id


# -- images ---------------------------------------------------------------------------------------


def _pixels(msg, channels: int, dtype: str, *, topic: str) -> np.ndarray:
    """The (H, W[, C]) array of a raw ``sensor_msgs/Image`` (rows padded to ``step`` allowed)."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    item = np.dtype(dtype).itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < w * channels * item or data.size < h * step:
        raise InputError(
            f"an image on {topic} holds {data.size} bytes, too few for {w}x{h} {msg.encoding} (step {step})"
        )
    rows = data[: h * step].reshape(h, step)[:, : w * channels * item]
    order = ">" if msg.is_bigendian else "<"
    image = rows.view(np.dtype(dtype).newbyteorder(order)).reshape(
        (h, w, channels) if channels > 1 else (h, w)
    )
    return image.astype(np.dtype(dtype).newbyteorder("="), copy=False)


def decode_colour(msg, *, topic: str) -> np.ndarray:
    """RGB image (H, W, 3) uint8 of a colour ``Image`` or ``CompressedImage`` message."""
    if hasattr(msg, "format"):  # CompressedImage: JPEG or PNG, decoded as OpenCV does (BGR)
        if not any(f in msg.format.lower() for f in ("jpeg", "jpg", "png")) and msg.format:
            raise InputError(f"unknown colour image format {msg.format!r} on {topic} (expected JPEG or PNG)")
        bgr = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise InputError(f"a compressed image on {topic} could not be decoded ({msg.format})")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    _known("colour", msg.encoding, COLOUR_ENCODINGS, topic=topic)
    channels, conversion = COLOUR_ENCODINGS[msg.encoding]
    image = _pixels(msg, channels, "u1", topic=topic)
    return np.ascontiguousarray(image) if conversion is None else cv2.cvtColor(image, conversion)


def decode_depth(msg, *, units_m: float, topic: str) -> np.ndarray:
    """Depth (H, W) float32 in metres of a depth ``Image`` or ``CompressedImage`` message (0 = none).

    ``units_m`` are the metres per unit of 16-bit depth."""
    if hasattr(msg, "format"):
        return _decode_compressed_depth(msg, units_m=units_m, topic=topic)
    _known("depth", msg.encoding, DEPTH_ENCODINGS, topic=topic)
    dtype, scale = DEPTH_ENCODINGS[msg.encoding]
    values = _pixels(msg, 1, dtype, topic=topic)
    if scale is None:
        return metres(values, units_m)
    depth = values.astype(np.float32)
    depth[~np.isfinite(depth)] = 0.0
    return depth


def metres(values: np.ndarray, units_m: float) -> np.ndarray:
    """Depth in metres (float32) of 16-bit depth values of ``units_m`` metres each.

    Depth units come as float32 (a RealSense ``Depth Units`` of 0.001 is 0.0010000000475): they are
    taken to 6 significant digits, and the values divided by the units per metre as the folder reader
    does, so that the same millimetres give the same metres whichever way they were stored."""
    units_per_metre = 1.0 / float(f"{units_m:.6g}")
    return values.astype(np.float32) / np.float32(units_per_metre)


def _decode_compressed_depth(msg, *, units_m: float, topic: str) -> np.ndarray:
    """image_transport's ``compressedDepth`` (a 12-byte header, then a 16-bit PNG: depth units, or for
    32FC1 the quantised inverse depth A / (v - B)) or a plain 16-bit PNG."""
    fmt = msg.format.replace(" ", "")
    data = np.asarray(msg.data, dtype=np.uint8)
    if "compressedDepth" in fmt and "rvl" not in fmt.lower():
        quant_a, quant_b = struct.unpack("<ff", data[4:12].tobytes()) if data.size >= 12 else (0.0, 0.0)
        data = data[12:]
    elif not fmt.lower().startswith("16uc1;png") and fmt.lower() not in ("png", "16uc1"):
        raise InputError(
            f"unknown depth image format {msg.format!r} on {topic} (expected compressedDepth PNG)"
        )
    values = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if values is None or values.dtype != np.uint16:
        raise InputError(f"a compressed depth image on {topic} is not a 16-bit PNG ({msg.format})")
    if fmt.startswith("32FC1"):
        with np.errstate(divide="ignore"):
            depth = np.where(values > 0, quant_a / (values.astype(np.float32) - quant_b), 0.0)
        return np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
    return metres(values, units_m)


@njit(cache=True, nogil=True)
def _splat_nearest(depth, K_depth, K_colour, T, out):
    """Move every depth pixel into the colour image by T (colour from depth), keeping the nearest."""
    h, w = depth.shape
    for v in range(h):
        for u in range(w):
            z = depth[v, u]
            if not z > 0:
                continue
            x = (u - K_depth[2]) / K_depth[0] * z
            y = (v - K_depth[3]) / K_depth[1] * z
            px = T[0, 0] * x + T[0, 1] * y + T[0, 2] * z + T[0, 3]
            py = T[1, 0] * x + T[1, 1] * y + T[1, 2] * z + T[1, 3]
            pz = T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3]
            if not pz > 0:
                continue
            uc = int(np.rint(K_colour[0] * px / pz + K_colour[2]))
            vc = int(np.rint(K_colour[1] * py / pz + K_colour[3]))
            if 0 <= uc < out.shape[1] and 0 <= vc < out.shape[0]:
                if out[vc, uc] == 0 or pz < out[vc, uc]:
                    out[vc, uc] = pz


def register_depth(
    depth_m: np.ndarray,
    *,
    depth_intrinsics: Intrinsics,
    colour_intrinsics: Intrinsics,
    T_colour_from_depth: np.ndarray,
) -> np.ndarray:
    """Depth seen from the colour camera: each depth pixel's point moved by ``T_colour_from_depth`` and
    projected into the colour image, the nearest kept where several land on one pixel.

    Parameters
    ----------
    depth_m : ndarray, shape (H_d, W_d), float32, metres, 0 = no reading
    depth_intrinsics, colour_intrinsics : pinhole models of the two cameras
    T_colour_from_depth : ndarray, shape (4, 4), metres

    Returns
    -------
    ndarray, shape (H_c, W_c), float32, metres, 0 where no depth pixel lands
    """
    out = np.zeros((colour_intrinsics.height, colour_intrinsics.width), np.float32)
    camera = lambda k: np.array([k.fx, k.fy, k.cx, k.cy], dtype=np.float64)  # noqa: E731
    _splat_nearest(
        np.ascontiguousarray(depth_m, dtype=np.float32),
        camera(depth_intrinsics),
        camera(colour_intrinsics),
        np.ascontiguousarray(T_colour_from_depth, dtype=np.float64),
        out,
    )
    return out


# -- the sequence ---------------------------------------------------------------------------------


class _Cursor:
    """Reads one topic's messages by position in its list, going on from the last one read where it
    can (a long bag is read once, in order), or starting afresh at the message's time."""

    def __init__(self, topic: ImageTopic):
        self.topic = topic
        self.messages: Iterator | None = None
        self.next = 0  # position of the message the iterator gives next

    def read(self, reader, k: int) -> tuple[Any, bytes]:
        times = self.topic.times_ns
        if self.messages is None or not self.next <= k <= self.next + MAX_SKIP:
            first = times.index(times[k])  # the first message of that time: the iterator starts there
            # this reader's own connections of the topic (those found when indexing belong to another)
            connections = [c for c in reader.connections if c.topic == self.topic.name]
            self.messages = reader.messages(connections=connections, start=times[k])
            self.next = first
        for connection, t_ns, raw in self.messages:
            self.next += 1
            if self.next - 1 == k:
                if t_ns != times[k]:
                    break
                return connection, raw
        self.messages = None
        raise InputError(f"message {k} of {self.topic.name} is not where the bag's index put it")


class BagSequence(Sequence):
    """The colour-depth pairs of one bag, read on demand (see the module docstring)."""

    def __init__(
        self,
        path: Path,
        *,
        colour: ImageTopic,
        depth: ImageTopic,
        pairs: list[tuple[int, int]],
        intrinsics: Intrinsics,
        depth_units_m: float,
        registration: tuple[Intrinsics, np.ndarray] | None,
        meta: dict,
    ):
        super().__init__(
            name=path.stem if path.is_file() else path.name,
            path=path,
            intrinsics=intrinsics,
            n_frames=len(pairs),
            meta=meta,
        )
        self.colour, self.depth, self.pairs = colour, depth, pairs
        self.depth_units_m = depth_units_m
        self.registration = registration
        self.t0_ns = colour.stamps_ns[pairs[0][0]]
        self._lock = threading.Lock()
        self._reader = None
        self._cursors = (_Cursor(colour), _Cursor(depth))

    def _raw(self, i: int) -> tuple[Any, Any]:
        """The deserialised colour and depth messages of pair i (the bag stays open between calls)."""
        with self._lock:
            if self._reader is None:
                self._reader = open_reader(self.path)
            try:
                out = []
                for cursor, k in zip(self._cursors, self.pairs[i]):
                    connection, raw = cursor.read(self._reader, k)
                    out.append(self._reader.deserialize(raw, connection.msgtype))
                return tuple(out)
            except _errors() as exc:
                self._close()
                raise InputError(f"damaged bag ({_one_line(exc)})", path=self.path) from None

    def _close(self) -> None:
        if self._reader is not None:
            self._reader, reader = None, self._reader
            for cursor in self._cursors:
                cursor.messages = None
            reader.close()

    def forget_frames(self) -> None:
        super().forget_frames()
        with self._lock:
            self._close()

    def load(self, i: int) -> Frame:
        colour_msg, depth_msg = self._raw(i)
        rgb = decode_colour(colour_msg, topic=self.colour.name)
        depth = decode_depth(depth_msg, units_m=self.depth_units_m, topic=self.depth.name)
        if self.registration is not None:
            depth_intrinsics, T = self.registration
            if depth.shape != (depth_intrinsics.height, depth_intrinsics.width):
                raise InputError(
                    f"a depth image on {self.depth.name} is {depth.shape[1]}x{depth.shape[0]}, its "
                    f"CameraInfo says {depth_intrinsics.width}x{depth_intrinsics.height}",
                    path=self.path,
                )
            depth = register_depth(
                depth,
                depth_intrinsics=depth_intrinsics,
                colour_intrinsics=self.intrinsics,
                T_colour_from_depth=T,
            )
        stamp = self.colour.stamps_ns[self.pairs[i][0]]
        return Frame(i, f"{i:06d}", rgb, depth, None, time_s=(stamp - self.t0_ns) * 1e-9)


class BagReader(Reader):
    """Reads a ROS 1 or ROS 2 bag, or a RealSense recording (see the module docstring)."""

    name = "bag"
    description = (
        "ROS 1 / ROS 2 bag or RealSense recording (.bag, .db3, .mcap): colour and depth image topics"
    )
    Params = BagParams

    def sequences(self, path: Path) -> list[Sequence]:
        path = Path(path)
        if not is_bag(path):
            return []
        p = self.params
        given = [v for v in (p.fx, p.fy, p.cx, p.cy) if v is not None]
        if given and len(given) < 4:
            raise InputError("give all four intrinsics (fx, fy, cx, cy) or none", path=path)
        with open_bag(path) as reader:
            colour, depth = choose_topics(reader, p, path=path)
            first_ns = first_time(reader, colour, depth)
            start_ns = first_ns + round(p.start_s * 1e9)
            stop_ns = None if p.stop_s is None else first_ns + round(p.stop_s * 1e9)
            index_topics(reader, colour, depth, start_ns=start_ns, stop_ns=stop_ns)
            for topic in (colour, depth):
                if not topic.times_ns:
                    raise InputError(f"no message on {topic.name} in the chosen time window", path=path)
            _check_encodings(colour, depth, path=path)
            pairs = associate(
                np.array(colour.stamps_ns) * 1e-9,
                np.array(depth.stamps_ns) * 1e-9,
                max_diff_s=p.max_time_diff_s,
            )[:: p.every]
            if not pairs:
                raise InputError(
                    f"no colour image on {colour.name} has a depth image on {depth.name} within "
                    f"{p.max_time_diff_s:g} s (header stamps)",
                    path=path,
                )
            intrinsics, source = self._intrinsics(reader, colour, depth, path=path)
            units = DEPTH_ENCODINGS.get(depth.encoding, (None, None))[1] or MILLIMETRE
            if depth.realsense_stream:
                units = _rs_depth_units(reader, depth) or units
            registration, registered_by = self._registration(reader, colour, depth, intrinsics, path=path)
        meta = dict(
            dataset="bag",
            colour_topic=colour.name,
            depth_topic=depth.name,
            colour_encoding=colour.encoding,
            depth_encoding=depth.encoding,
            intrinsics_source=source,
            depth_units_m=units,
            depth_registered_by=registered_by,
            n_colour=len(colour.times_ns),
            n_depth=len(depth.times_ns),
            n_pairs=len(pairs),
        )
        return [
            BagSequence(
                path,
                colour=colour,
                depth=depth,
                pairs=pairs,
                intrinsics=intrinsics,
                depth_units_m=units,
                registration=registration,
                meta=meta,
            )
        ]

    def _intrinsics(
        self, reader, colour: ImageTopic, depth: ImageTopic, *, path: Path
    ) -> tuple[Intrinsics, str]:
        p = self.params
        if p.fx is not None:
            if not colour.width:
                raise InputError(
                    f"the colour images on {colour.name} are compressed: their size needs a CameraInfo",
                    path=path,
                )
            return Intrinsics(p.fx, p.fy, p.cx, p.cy, width=colour.width, height=colour.height), "params"
        found = camera_info(reader, colour, other=depth, path=path)
        if found is None:
            namespace = colour.name.rsplit("/", 1)[0]
            raise InputError(
                f"no CameraInfo for {colour.name}: record {namespace}/camera_info, or give the "
                f"intrinsics (--param fx=... fy=... cx=... cy=...)",
                path=path,
            )
        intrinsics, topic = found
        colour.width, colour.height = intrinsics.width, intrinsics.height
        return intrinsics, topic

    def _registration(
        self, reader, colour: ImageTopic, depth: ImageTopic, intrinsics: Intrinsics, *, path: Path
    ) -> tuple[tuple[Intrinsics, np.ndarray] | None, str]:
        """``((depth intrinsics, T_colour_from_depth), source)`` for depth to register, or ``(None, why
        not)`` for depth already registered."""
        if is_registered(colour, depth):
            if depth.width and (depth.width, depth.height) != (intrinsics.width, intrinsics.height):
                raise InputError(
                    f"colour images on {colour.name} are {intrinsics.width}x{intrinsics.height} but depth "
                    f"images on {depth.name} are {depth.width}x{depth.height}",
                    path=path,
                )
            return None, "recorded registered"
        found = depth_to_colour(reader, colour, depth)
        depth_info = camera_info(reader, depth, other=colour, path=path)
        if found is None or depth_info is None:
            namespace = "/" + colour.name.strip("/").split("/")[0]
            wanted = (
                f"{depth.realsense_stream}/tf/0 (the SDK's extrinsics)"
                if depth.realsense_stream
                else f"/tf_static, or depth aligned to colour ({namespace}/aligned_depth_to_color/image_raw)"
            )
            what = "extrinsics between them" if found is None else f"CameraInfo for {depth.name}"
            raise InputError(
                f"depth on {depth.name} is not registered to the colour image on {colour.name}, and the bag "
                f"holds no {what}: record {wanted}",
                path=path,
            )
        T, source = found
        return (depth_info[0], T), source


def _check_encodings(colour: ImageTopic, depth: ImageTopic, *, path: Path) -> None:
    """A one-line error for an encoding the reader cannot decode, before any frame is read."""
    for kind, topic, table in (("colour", colour, COLOUR_ENCODINGS), ("depth", depth, DEPTH_ENCODINGS)):
        if not topic.compressed:
            _known(kind, topic.encoding, table, topic=topic.name, path=path)


def _known(kind: str, encoding: str, table: dict, *, topic: str, path: Path | None = None) -> None:
    """A one-line error for a ``kind`` (colour, depth) encoding not in ``table``."""
    if encoding not in table:
        raise InputError(
            f"unknown {kind} encoding {encoding!r} on {topic} (expected {', '.join(table)})", path=path
        )


# -- writing --------------------------------------------------------------------------------------

#: Topic layouts :func:`write_bag` can write: colour, depth, colour CameraInfo.
LAYOUTS = {
    "ros": (
        "/camera/color/image_raw",
        "/camera/aligned_depth_to_color/image_raw",
        "/camera/color/camera_info",
    ),
    # The RealSense SDK's own layout (ROS 1 recordings, file version 3): depth from the depth sensor,
    # not registered to colour, with each stream's CameraInfo and extrinsics.
    "realsense": (
        "/device_0/sensor_1/Color_0/image/data",
        "/device_0/sensor_0/Depth_0/image/data",
        "/device_0/sensor_1/Color_0/info/camera_info",
    ),
}


class BagWriter:
    """Messages into a new bag, with rosbags' writers: a ROS 1 bag for a ``.bag`` path, else a ROS 2
    bag folder (``storage``: ``sqlite3`` or ``mcap``). Use it in a ``with`` block; ``types`` are the
    message classes of its type store (ROS 1 Noetic or ROS 2 Humble)."""

    def __init__(self, path: Path, *, storage: str = "sqlite3"):
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2
        from rosbags.typesys import Stores, get_typestore

        self.path = Path(path)
        self.ros1 = self.path.suffix == ".bag"
        store = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        self.store, self.types = store, store.types
        self.serialize = store.serialize_ros1 if self.ros1 else store.serialize_cdr
        self.writer = (
            Writer1(self.path)
            if self.ros1
            else Writer2(self.path, version=9, storage_plugin=StoragePlugin[storage.upper()])
        )
        self.connections: dict[str, Any] = {}

    def __enter__(self) -> BagWriter:
        self.writer.open()
        return self

    def __exit__(self, *exc) -> None:
        self.writer.close()

    def put(self, topic: str, msgtype: str, msg, t_ns: int) -> None:
        """Write ``msg`` on ``topic`` at bag time ``t_ns`` (ns)."""
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store)
        self.writer.write(self.connections[topic], t_ns, self.serialize(msg, msgtype))

    def header(self, t_ns: int, frame_id: str):
        T = self.types
        stamp = T["builtin_interfaces/msg/Time"](sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
        return T["std_msgs/msg/Header"](**({"seq": 0} if self.ros1 else {}), stamp=stamp, frame_id=frame_id)

    def image(self, t_ns: int, frame_id: str, array: np.ndarray, encoding: str):
        """A ``sensor_msgs/Image`` of ``array`` (H, W[, C]), stamped ``t_ns``."""
        data = np.ascontiguousarray(array)
        return self.types[IMAGE](
            header=self.header(t_ns, frame_id),
            height=data.shape[0],
            width=data.shape[1],
            encoding=encoding,
            is_bigendian=0,
            step=data.strides[0],
            data=data.view(np.uint8).reshape(-1),
        )

    def camera_info(self, t_ns: int, frame_id: str, k: Intrinsics):
        """A ``sensor_msgs/CameraInfo`` of the pinhole ``k`` (no distortion)."""
        T = self.types
        matrices = dict(
            d=np.zeros(5),
            k=np.array([k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1], float),
            r=np.eye(3).ravel(),
            p=np.array([k.fx, 0, k.cx, 0, 0, k.fy, k.cy, 0, 0, 0, 1, 0], float),
        )
        roi = T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        return T[CAMERA_INFO](
            header=self.header(t_ns, frame_id),
            height=k.height,
            width=k.width,
            distortion_model="plumb_bob",
            **{(name.upper() if self.ros1 else name): value for name, value in matrices.items()},
            binning_x=0,
            binning_y=0,
            roi=roi,
        )


def write_bag(
    frames,
    path: Path,
    *,
    intrinsics: Intrinsics,
    layout: str = "ros",
    colour_encoding: str = "rgb8",
    depth_encoding: str = "16UC1",
    fps: float = 30.0,
    camera_info: bool = True,
    storage: str = "sqlite3",
) -> Path:
    """Write RGB-D frames as a bag, for tests, benchmarks and sharing data: a ROS 1 bag for a ``.bag``
    path, else a ROS 2 bag folder.

    Parameters
    ----------
    frames : iterable of :class:`Frame` (``rgb`` (H, W, 3) uint8, ``depth_m`` (H, W) metres)
    intrinsics : the colour camera's (depth is registered to it)
    layout : a key of :data:`LAYOUTS`; ``realsense`` writes the depth as the depth sensor's stream with
        identity extrinsics and the colour camera's intrinsics, and ``Depth Units`` of 1 mm
    colour_encoding : one of :data:`COLOUR_ENCODINGS`
    depth_encoding : ``16UC1`` (millimetres, rounded) or ``32FC1`` (metres)
    fps : frame rate: frame i is stamped 1 s + i / fps (colour and depth alike)
    camera_info : write the CameraInfo topics
    storage : a ROS 2 bag's storage, ``sqlite3`` (.db3) or ``mcap``

    Returns
    -------
    the path of the bag written
    """
    colour_topic, depth_topic, info_topic = LAYOUTS[layout]
    frame_ids = ("camera_color_optical_frame",) * 2 if layout == "ros" else ("Color", "Depth")
    to_encoding = {"rgb8": None, "bgr8": cv2.COLOR_RGB2BGR, "rgba8": cv2.COLOR_RGB2RGBA}
    to_encoding.update(bgra8=cv2.COLOR_RGB2BGRA, mono8=cv2.COLOR_RGB2GRAY)
    # the SDK names its 16-bit depth (Z16) mono16
    depth_name = "mono16" if layout == "realsense" and depth_encoding == "16UC1" else depth_encoding
    with BagWriter(path, storage=storage) as bag:
        T = bag.types
        if layout == "realsense":
            identity = T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            )
            bag.put("/file_version", "std_msgs/msg/UInt32", T["std_msgs/msg/UInt32"](data=3), 0)
            units = T["std_msgs/msg/Float32"](data=MILLIMETRE)
            bag.put("/device_0/sensor_0/option/Depth Units/value", "std_msgs/msg/Float32", units, 0)
            for stream in ("/device_0/sensor_0/Depth_0", "/device_0/sensor_1/Color_0"):
                bag.put(f"{stream}/tf/0", "geometry_msgs/msg/Transform", identity, 0)
            if camera_info:
                depth_info = bag.camera_info(0, frame_ids[1], intrinsics)
                bag.put("/device_0/sensor_0/Depth_0/info/camera_info", CAMERA_INFO, depth_info, 0)
        if camera_info:
            bag.put(info_topic, CAMERA_INFO, bag.camera_info(0, frame_ids[0], intrinsics), 0)
        for n, frame in enumerate(frames):
            t_ns = round(n * 1e9 / fps) + 1_000_000_000
            conversion = to_encoding[colour_encoding]
            rgb = frame.rgb if conversion is None else cv2.cvtColor(frame.rgb, conversion)
            bag.put(colour_topic, IMAGE, bag.image(t_ns, frame_ids[0], rgb, colour_encoding), t_ns)
            if depth_encoding == "16UC1":
                depth = np.rint(frame.depth_m / MILLIMETRE).astype(np.uint16)
            else:
                depth = frame.depth_m.astype(np.float32)
            bag.put(depth_topic, IMAGE, bag.image(t_ns, frame_ids[1], depth, depth_name), t_ns)
    return Path(path)
