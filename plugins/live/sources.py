"""Where live frames come from: a RealSense camera, a RealSense recording played back by the SDK, or
any sequence a reader opens (a bag, a folder), played frame by frame.

A source has a ``name``, a ``path``, the colour camera's ``intrinsics``, ``n_frames`` (None when it
is not known in advance, as for a camera) and ``frames()``, which yields :class:`Frame` objects
numbered 0, 1, 2 ... in the order they arrive, depth registered to colour, in metres.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

import numpy as np

from artclass_core import Frame, InputError, Intrinsics, Sequence
from artclass_core.plugins import Registry
from artclass_core.sequences import open_sequences

from ..readers.bag import is_bag, metres, open_bag

REALSENSE_HINT = "pip install 'artclass[realsense]'"
NO_FRAME_S = 5.0  # a camera that sends nothing for this long is taken to be gone


class FrameSource(Protocol):
    name: str
    path: Path
    intrinsics: Intrinsics
    n_frames: int | None

    def frames(self) -> Iterator[Frame]: ...

    def close(self) -> None: ...


class SequenceSource:
    """The frames of a sequence any reader opens, one after another (as fast as they are read)."""

    def __init__(self, sequence: Sequence):
        self.sequence = sequence
        self.name, self.path, self.intrinsics = sequence.name, sequence.path, sequence.intrinsics
        self.n_frames: int | None = len(sequence)

    def frames(self) -> Iterator[Frame]:
        for i in range(len(self.sequence)):
            yield self.sequence[i]

    def close(self) -> None:
        self.sequence.forget_frames()


def has_realsense() -> bool:
    """Whether the RealSense SDK's Python package (``pyrealsense2``) is installed."""
    return importlib.util.find_spec("pyrealsense2") is not None


def is_realsense_recording(path: Path) -> bool:
    """A bag in the RealSense SDK's own layout (it has a ``/file_version`` topic)."""
    if not is_bag(path):
        return False
    with open_bag(path) as reader:
        return "/file_version" in reader.topics


class RealSenseSource:
    """A RealSense camera, or a RealSense recording played back by the SDK as if it were one; depth
    aligned to colour by the SDK (``rs.align``).

    A recording is played without real-time pacing, through a frame queue of ``QUEUE`` framesets, so
    that no frame is dropped while a slow consumer catches up (the SDK's pipeline keeps only the
    latest); the SDK may leave out a frame it cannot match into a set.

    Parameters
    ----------
    path : a recording to play back (``.bag`` or ``.db3``), or None for the first camera connected
    width, height, fps : the camera's colour and depth streams (not used for a recording)
    """

    QUEUE = 64

    def __init__(self, path: Path | None = None, *, width: int = 640, height: int = 480, fps: int = 30):
        if not has_realsense():
            raise InputError(f"the RealSense SDK's Python package is not installed: {REALSENSE_HINT}")
        import pyrealsense2 as rs

        self.path = Path(path) if path else Path("realsense")
        self.name = self.path.stem if path else "realsense"
        self.n_frames: int | None = None
        self.sensors, self.pipeline = [], None
        try:
            device = self._play(rs, path) if path else self._camera(rs, width, height, fps)
        except RuntimeError as exc:
            self.close()
            raise InputError(f"the RealSense SDK cannot open it ({exc})", path=path) from None
        colour = next(
            p
            for s in device.query_sensors()
            for p in s.get_stream_profiles()
            if p.stream_type() == rs.stream.color
        ).as_video_stream_profile()
        k = colour.get_intrinsics()
        self.intrinsics = Intrinsics(k.fx, k.fy, k.ppx, k.ppy, width=k.width, height=k.height)
        self.depth_units_m = device.first_depth_sensor().get_depth_scale()
        self.align = rs.align(rs.stream.color)
        self.order = {rs.format.rgb8: None, rs.format.bgr8: slice(None, None, -1)}.get(colour.format(), False)
        if self.order is False:
            self.close()
            raise InputError(f"colour stream format {colour.format()} is not rgb8 or bgr8", path=path)

    def _play(self, rs, path: Path):
        device = rs.context().load_device(str(path))
        self.playback = device.as_playback()
        self.playback.set_real_time(False)  # every recorded frame, at the speed they are classified
        queue = rs.syncer(self.QUEUE)
        self.sensors = list(device.query_sensors())
        self.playback.pause()  # until every sensor is started: none of the first frames goes unmatched
        for sensor in self.sensors:
            sensor.open(sensor.get_stream_profiles())
            sensor.start(queue)
        self.playback.resume()
        self._wait = queue.try_wait_for_frames
        return device

    def _camera(self, rs, width: int, height: int, fps: int):
        self.playback = None
        if not len(rs.context().query_devices()):
            raise InputError(
                "no RealSense camera is connected; plug one in, or play a recording with --source FILE"
            )
        config = rs.config()
        config.enable_stream(rs.stream.depth, width, height, rs.format.z16, fps)
        config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
        self.pipeline = rs.pipeline()
        profile = self.pipeline.start(config)
        self._wait = self.pipeline.try_wait_for_frames
        return profile.get_device()

    def frames(self) -> Iterator[Frame]:
        n, t0 = 0, None
        timeout_ms = int(1000 if self.playback else NO_FRAME_S * 1000)
        while True:
            ok, frameset = self._wait(timeout_ms)
            if not ok:
                if self.playback:  # the recording has ended
                    return
                raise InputError(f"the RealSense camera sent no frame for {NO_FRAME_S:g} s")
            if not (frameset.get_color_frame() and frameset.get_depth_frame()):
                continue
            frameset = self.align.process(frameset)
            colour, depth = frameset.get_color_frame(), frameset.get_depth_frame()
            rgb = np.asanyarray(colour.get_data())
            rgb = np.array(rgb if self.order is None else rgb[..., self.order])
            depth_m = metres(np.asanyarray(depth.get_data()), self.depth_units_m)
            t0 = colour.get_timestamp() if t0 is None else t0
            yield Frame(n, f"{n:06d}", rgb, depth_m, None, time_s=(colour.get_timestamp() - t0) / 1000)
            n += 1

    def close(self) -> None:
        for sensor in self.sensors:
            try:
                sensor.stop()
                sensor.close()
            except RuntimeError:  # not started
                pass
        self.sensors = []
        if self.pipeline is not None:
            try:
                self.pipeline.stop()
            except RuntimeError:  # already stopped
                pass
            self.pipeline = None


def open_source(
    registry: Registry,
    path: str | None,
    *,
    player: str = "auto",
    reader: str | None = None,
    reader_values: dict[str, str] | None = None,
) -> FrameSource:
    """The frame source of ``artclass live``.

    Parameters
    ----------
    path : a recording or sequence; None for a RealSense camera
    player : ``sdk`` plays a RealSense recording through the RealSense SDK, as a camera would send it;
        ``reader`` plays any sequence through artclass's readers (frame for frame what ``classify``
        reads); ``auto`` is ``sdk`` for a RealSense recording when the SDK is installed, else ``reader``
    reader, reader_values : the reader and its parameters, for ``player="reader"``
    """
    if path is None:
        if not has_realsense():
            raise InputError(
                f"no --source recording given, and no RealSense camera can be used: the RealSense SDK's "
                f"Python package is not installed ({REALSENSE_HINT})"
            )
        return RealSenseSource()
    if player == "auto":
        recording = has_realsense() and Path(path).exists() and is_realsense_recording(Path(path))
        player = "sdk" if recording else "reader"
    if player == "sdk":
        if not Path(path).is_file():
            raise InputError("not a RealSense recording file", path=path)
        return RealSenseSource(Path(path))
    sequences = open_sequences(registry, path, reader=reader, reader_values=reader_values)
    if len(sequences) > 1:
        raise InputError(
            f"holds {len(sequences)} sequences ({', '.join(s.name for s in sequences)}); choose one with PATH#NAME",
            path=path,
        )
    return SequenceSource(sequences[0])
