"""RealSense recordings made by the RealSense SDK itself (pyrealsense2's software device and recorder,
no camera): the bag reader reads them back exactly, decides as the folder does, and registers depth
to colour with the recording's extrinsics the way the SDK's own alignment does."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_bag import classify_json

from artclass_core import Intrinsics, open_sequences

rs = pytest.importorskip("pyrealsense2", reason="pyrealsense2 (the realsense extra) is not installed")

N_FRAMES = 12
SIZE = dict(width=160, height=120)


def sdk_record(frames, path: Path, intrinsics: Intrinsics, *, T_colour_from_depth=None) -> Path:
    """Record RGB-D frames as the RealSense SDK does (``rs.recorder`` on a software device): a colour
    stream (rgb8) and a depth stream (z16, 1 mm), with the given depth-to-colour extrinsics."""
    h, w = frames[0].depth_m.shape
    device = rs.software_device()
    depth_sensor, colour_sensor = device.add_sensor("Depth"), device.add_sensor("Color")
    model = rs.intrinsics()
    model.width, model.height, model.ppx, model.ppy = w, h, intrinsics.cx, intrinsics.cy
    model.fx, model.fy, model.model, model.coeffs = (
        intrinsics.fx,
        intrinsics.fy,
        rs.distortion.none,
        [0.0] * 5,
    )

    def stream(kind, uid, fmt, bpp):
        s = rs.video_stream()
        s.type, s.index, s.uid, s.width, s.height, s.fps, s.bpp, s.fmt = kind, 0, uid, w, h, 30, bpp, fmt
        s.intrinsics = model
        return s

    depth_profile = depth_sensor.add_video_stream(stream(rs.stream.depth, 0, rs.format.z16, 2), True)
    colour_profile = colour_sensor.add_video_stream(stream(rs.stream.color, 1, rs.format.rgb8, 3), True)
    depth_sensor.add_read_only_option(rs.option.depth_units, 0.001)
    T = np.eye(4) if T_colour_from_depth is None else T_colour_from_depth
    extrinsics = rs.extrinsics()
    extrinsics.rotation, extrinsics.translation = list(T[:3, :3].T.ravel()), list(T[:3, 3])
    depth_profile.register_extrinsics_to(colour_profile, extrinsics)
    recorder = rs.recorder(str(path), device)
    sensors = recorder.query_sensors()
    seen = []
    for s in sensors:
        s.open(s.get_stream_profiles()[0])
        s.start(lambda f: seen.append(1))
    started = time.monotonic()
    for n, frame in enumerate(frames):
        depth = np.rint(frame.depth_m * 1000).astype(np.uint16)
        for sensor, profile, data, bpp in (
            (depth_sensor, depth_profile, depth, 2),
            (colour_sensor, colour_profile, np.ascontiguousarray(frame.rgb), 3),
        ):
            f = rs.software_video_frame()
            f.pixels, f.stride, f.bpp = data.tobytes(), w * bpp, bpp
            f.timestamp, f.domain, f.frame_number = n * 1000 / 30, rs.timestamp_domain.hardware_clock, n
            f.profile = profile.as_video_stream_profile()
            sensor.on_video_frame(f)
        deadline = time.monotonic() + 10
        while len(seen) < 2 * (n + 1) and time.monotonic() < deadline:
            time.sleep(0.001)
        # the SDK stamps each message with its arrival: frames a camera's 1/30 s apart, as recorded live
        time.sleep(max(0.0, started + (n + 1) / 30 - time.monotonic()))
    for s in sensors:
        s.stop()
        s.close()
    del recorder, sensors  # the recorder writes the file out when it goes
    return path


@pytest.fixture(scope="module")
def laptop(rendered, registry):
    folder = rendered("laptop", "articulate", n_frames=N_FRAMES, **SIZE)
    seq = open_sequences(registry, folder)[0]
    return folder, seq, [seq[i] for i in range(len(seq))]


@pytest.fixture(scope="module")
def sdk_bag(laptop, tmp_path_factory):
    _folder, seq, frames = laptop
    return sdk_record(frames, tmp_path_factory.mktemp("sdk") / "laptop.db3", seq.intrinsics)


def test_sdk_recording_reads_back_exactly(laptop, sdk_bag, registry):
    """The SDK's own layout (compressed colour and depth, String options and extrinsics) gives back
    every pixel, the intrinsics and the depth units."""
    _folder, seq, frames = laptop
    (bag,) = open_sequences(registry, sdk_bag)
    assert bag.meta["colour_topic"] == "/device_0/sensor_1/Color_0/image/data/compressed"
    assert bag.meta["depth_topic"] == "/device_0/sensor_0/Depth_0/image/data/compressedDepth"
    assert bag.meta["depth_registered_by"].startswith("/device_0/sensor_0/Depth_0/tf/")
    assert bag.intrinsics == seq.intrinsics and len(bag) == len(frames)
    for i, want in enumerate(frames):
        assert np.array_equal(bag[i].rgb, want.rgb) and np.array_equal(bag[i].depth_m, want.depth_m), i


@pytest.mark.slow
def test_sdk_recording_decides_as_the_folder(laptop, sdk_bag, capsys):
    folder, _seq, _frames = laptop
    runs = [classify_json(capsys, where) for where in (folder, sdk_bag)]
    assert [p["decision"] for p in runs[0]["pairs"]] == [p["decision"] for p in runs[1]["pairs"]]
    assert runs[0]["label"] == runs[1]["label"] == "articulated"


def test_registration_agrees_with_the_sdks_alignment(laptop, registry, tmp_path):
    """Depth recorded 15 mm and a few degrees away from colour: the reader's registration puts the
    near surfaces where the SDK's rs.align puts them, far better than the inverse extrinsics or none
    (the SDK keeps the depth camera's z, the reader the colour camera's, so values differ by mm)."""
    from artclass_plugins.live.sources import RealSenseSource
    from artclass_plugins.readers.bag import register_depth

    _folder, seq, frames = laptop
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [1, -2, 0.5], degrees=True).as_matrix()
    T[:3, 3] = [0.015, 0.003, -0.002]
    path = sdk_record(frames, tmp_path / "moved.db3", seq.intrinsics, T_colour_from_depth=T)
    (bag,) = open_sequences(registry, path)
    assert np.allclose(bag.registration[1], T, atol=1e-6)
    source = RealSenseSource(path)
    try:
        played = next(iter(source.frames()))
    finally:
        source.close()
    i = next(i for i in range(len(bag)) if np.array_equal(bag[i].rgb, played.rgb))  # the SDK may skip one
    sdk = played.depth_m
    near = np.percentile(sdk[sdk > 0], 10)

    def iou(depth):
        a, b = (sdk > 0) & (sdk < near), (depth > 0) & (depth < near)
        return (a & b).sum() / (a | b).sum()

    raw = frames[i].depth_m
    inverse = register_depth(
        raw,
        depth_intrinsics=seq.intrinsics,
        colour_intrinsics=seq.intrinsics,
        T_colour_from_depth=np.linalg.inv(T),
    )
    ours, unmoved, wrong = iou(bag[i].depth_m), iou(raw), iou(inverse)
    assert ours > 0.7 and ours > unmoved + 0.1 and unmoved > wrong, (ours, unmoved, wrong)
