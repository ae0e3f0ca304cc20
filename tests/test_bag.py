"""The bag reader on bags written here with rosbags' writers, from synthetic sequences: ROS 1, ROS 2
(sqlite3 and MCAP) and the RealSense SDK's own ROS 1 layout read back to the folder format's frames
and decisions; depth registered with the extrinsics a bag holds; the reader's parameters on the
command line; and the one-line errors of bad bags."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from artclass_core import InputError, Intrinsics, open_sequences
from artclass_core.cli import main
from artclass_plugins.readers.bag import BagParams, BagReader, BagWriter, register_depth, write_bag

N_FRAMES = 12
SIZE = dict(width=160, height=120)


def run_cli(capsys, *argv) -> tuple[int, str, str]:
    status = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return status, out, err


def classify_json(capsys, where, *more) -> dict:
    """``artclass classify WHERE --json`` with the mask-free segmenter on one worker, as data."""
    argv = [
        "classify",
        where,
        "--json",
        "--no-cells",
        "--workers",
        1,
        "--segmenter",
        "depth_threshold",
        *more,
    ]
    status, out, err = run_cli(capsys, *argv)
    assert status == 0, err
    return json.loads(out)


@pytest.fixture(scope="module")
def laptop(rendered, registry):
    """A small articulated sequence in the folder format, and its frames."""
    folder = rendered("laptop", "articulate", n_frames=N_FRAMES, **SIZE)
    seq = open_sequences(registry, folder)[0]
    return folder, seq, [seq[i] for i in range(len(seq))]


LAYOUTS = {  # name: (file name, write_bag keywords)
    "ros1": ("rec.bag", {}),
    "ros2-sqlite3": ("rec", {}),
    "ros2-mcap": ("rec", dict(storage="mcap")),
    "realsense-ros1": ("rec.bag", dict(layout="realsense")),
    "ros2-bgr8-32FC1": ("rec", dict(colour_encoding="bgr8", depth_encoding="32FC1")),
    "ros1-bgra8": ("rec.bag", dict(colour_encoding="bgra8")),
    "ros1-rgba8": ("rec.bag", dict(colour_encoding="rgba8")),
}


@pytest.mark.parametrize("layout", LAYOUTS)
def test_bag_frames_are_the_folder_frames(laptop, registry, tmp_path, layout):
    """Every colour and depth pixel, the intrinsics and the frame times come back as written."""
    _folder, seq, frames = laptop
    name, kw = LAYOUTS[layout]
    path = write_bag(frames, tmp_path / name, intrinsics=seq.intrinsics, **kw)
    (bag,) = open_sequences(registry, path)
    assert bag.meta["dataset"] == "bag" and len(bag) == len(frames)
    assert bag.intrinsics == seq.intrinsics
    for i, want in enumerate(frames):
        got = bag[i]
        assert np.array_equal(got.rgb, want.rgb), f"colour of frame {i}"
        assert np.array_equal(got.depth_m, want.depth_m), f"depth of frame {i}"
        assert got.time_s == pytest.approx(i / 30.0)
    registered = bag.meta["depth_registered_by"]
    assert registered == (
        "/device_0/sensor_0/Depth_0/tf/0" if "realsense" in layout else "recorded registered"
    )


def test_mono8_colour_is_grey(laptop, registry, tmp_path):
    _folder, seq, frames = laptop
    (bag,) = open_sequences(
        registry, write_bag(frames, tmp_path / "m.bag", intrinsics=seq.intrinsics, colour_encoding="mono8")
    )
    rgb = bag[3].rgb
    assert rgb.shape == frames[3].rgb.shape and np.array_equal(rgb[..., 0], rgb[..., 2])
    grey = frames[3].rgb.astype(float) @ [0.299, 0.587, 0.114]
    assert np.abs(rgb[..., 0] - grey).max() <= 1.0


@pytest.mark.parametrize(
    "layout",
    [
        pytest.param("ros1", marks=pytest.mark.slow),
        pytest.param("ros2-sqlite3", marks=pytest.mark.slow),
        pytest.param("ros2-mcap", marks=pytest.mark.slow),
        pytest.param("realsense-ros1", marks=pytest.mark.slow),
    ],
)
def test_classify_bag_decides_as_the_folder(laptop, tmp_path, capsys, layout):
    """``artclass classify REC.bag`` (or a ROS 2 folder) gives the label and every pair decision that
    the same frames give in the folder layout (both mask-free)."""
    folder, seq, frames = laptop
    name, kw = LAYOUTS[layout]
    path = write_bag(frames, tmp_path / name, intrinsics=seq.intrinsics, **kw)
    a, b = (classify_json(capsys, where) for where in (folder, path))
    assert [(p["i"], p["j"], p["decision"]) for p in a["pairs"]] == [
        (p["i"], p["j"], p["decision"]) for p in b["pairs"]
    ]
    assert a["label"] == b["label"] == "articulated"
    assert a["filtered"] == b["filtered"]


def write_topics(
    path: Path, topics: dict[str, list[tuple[int, str, np.ndarray, str]]], *, info=None, tf=()
) -> Path:
    """A bag of image topics, each a list of (stamp ns, frame_id, array, encoding), written at their
    stamps; ``info``: (topic, Intrinsics) pairs for CameraInfo; ``tf``: (parent, child, 4x4
    T_parent_from_child) on /tf_static."""
    with BagWriter(path) as bag:
        T = bag.types
        for topic, k in info or ():
            bag.put(topic, "sensor_msgs/msg/CameraInfo", bag.camera_info(1, "", k), 1)
        transforms = []
        for parent, child, M in tf:
            q = Rotation.from_matrix(M[:3, :3]).as_quat()
            transform = T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=M[0, 3], y=M[1, 3], z=M[2, 3]),
                rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            )
            transforms.append(
                T["geometry_msgs/msg/TransformStamped"](
                    header=bag.header(0, parent), child_frame_id=child, transform=transform
                )
            )
        if transforms:
            bag.put(
                "/tf_static", "tf2_msgs/msg/TFMessage", T["tf2_msgs/msg/TFMessage"](transforms=transforms), 1
            )
        messages = sorted(
            (t, topic, fid, a, enc) for topic, items in topics.items() for t, fid, a, enc in items
        )
        for t, topic, fid, a, enc in messages:
            bag.put(topic, "sensor_msgs/msg/Image", bag.image(t, fid, a, enc), t)
    return path


def _mm(depth_m):
    return np.rint(depth_m * 1000).astype(np.uint16)


def test_pairs_by_stamp_within_the_tolerance(laptop, registry, tmp_path):
    """Depth stamped 7 ms after its colour image still pairs with it; a colour image whose depth
    message is missing is left out, and one whose depth is 25 ms off is not paired (0.02 s)."""
    _folder, seq, frames = laptop
    t = [10**9 + round(i * 1e9 / 30) for i in range(len(frames))]
    colour = [(t[i], "c", f.rgb, "rgb8") for i, f in enumerate(frames)]
    depth = [
        (t[i] + 7_000_000 + (18_000_000 if i == 5 else 0), "c", _mm(f.depth_m), "16UC1")
        for i, f in enumerate(frames)
        if i != 3
    ]
    path = write_topics(
        tmp_path / "j.bag",
        {"/cam/color/image": colour, "/cam/depth/image": depth},
        info=[("/cam/color/camera_info", seq.intrinsics)],
    )
    (bag,) = open_sequences(registry, path)
    kept = [i for i in range(len(frames)) if i not in (3, 5)]
    assert len(bag) == len(kept)
    for n, i in enumerate(kept):
        assert np.array_equal(bag[n].rgb, frames[i].rgb) and np.array_equal(bag[n].depth_m, frames[i].depth_m)
    # a wider tolerance takes the late one too
    assert len(BagReader(BagParams(max_time_diff_s=0.04)).sequences(path)[0]) == len(frames) - 1


def test_window_and_stride(laptop, tmp_path, capsys):
    """start_s, stop_s and every choose the pairs; on the command line they reach the bag reader as
    any reader's parameters do (a window past the end is the reader's one-line error)."""
    _folder, seq, frames = laptop
    path = write_bag(frames, tmp_path / "w.bag", intrinsics=seq.intrinsics)
    # frames at i / 30 s after the first: 0.05 <= t < 0.3 keeps frames 2 .. 8
    (bag,) = BagReader(BagParams(start_s=0.05, stop_s=0.3)).sequences(path)
    assert len(bag) == 7 and np.array_equal(bag[0].rgb, frames[2].rgb)
    (bag,) = BagReader(BagParams(start_s=0.05, every=2)).sequences(path)
    assert len(bag) == 5 and np.array_equal(bag[1].rgb, frames[4].rgb)
    status, out, err = run_cli(capsys, "classify", path, "--param", "start_s=100", "--param", "k=2")
    assert status == 2 and "no message on /camera/color/image_raw in the chosen time window" in err


@pytest.mark.slow
def test_window_on_the_command_line(laptop, tmp_path, capsys):
    _folder, seq, frames = laptop
    path = write_bag(frames, tmp_path / "w.bag", intrinsics=seq.intrinsics)
    window = ["--param", "start_s=0.05", "--param", "stop_s=0.3", "--param", "k=2"]
    status, out, err = run_cli(capsys, "classify", path, "--json", "--no-cells", "--workers", 1, *window)
    assert status == 0, err
    assert json.loads(out)["sequence"]["n_frames"] == 7


def _two_colour_topics(tmp_path, frames) -> Path:
    t = [10**9 + i * 33_000_000 for i in range(len(frames))]
    return write_topics(
        tmp_path / "two",
        {
            "/a/rgb": [(t[i], "c", f.rgb, "rgb8") for i, f in enumerate(frames)],
            "/b/rgb": [(t[i], "c", 255 - f.rgb, "rgb8") for i, f in enumerate(frames)],
            "/a/depth": [(t[i], "c", _mm(f.depth_m), "16UC1") for i, f in enumerate(frames)],
        },
    )


def test_named_topics_and_given_intrinsics(laptop, tmp_path):
    """Two colour topics: the named one is read; without CameraInfo the intrinsics are given."""
    _folder, seq, frames = laptop
    path = _two_colour_topics(tmp_path, frames)
    k = seq.intrinsics
    (bag,) = BagReader(BagParams(colour_topic="/b/rgb", fx=k.fx, fy=k.fy, cx=k.cx, cy=k.cy)).sequences(path)
    assert bag.meta["colour_topic"] == "/b/rgb" and bag.meta["intrinsics_source"] == "params"
    assert bag.intrinsics == k and np.array_equal(bag[2].rgb, 255 - frames[2].rgb)
    with pytest.raises(InputError, match="no image topic '/c/rgb'"):
        BagReader(BagParams(colour_topic="/c/rgb")).sequences(path)


@pytest.mark.slow
def test_named_topics_on_the_command_line(laptop, tmp_path, capsys):
    _folder, seq, frames = laptop
    path = _two_colour_topics(tmp_path, frames)
    k = seq.intrinsics
    named = ["colour_topic=/b/rgb", f"fx={k.fx}", f"fy={k.fy}", f"cx={k.cx}", f"cy={k.cy}", "k=2"]
    argv = [a for item in named for a in ("--param", item)]
    status, out, err = run_cli(capsys, "classify", path, "--json", "--no-cells", "--workers", 1, *argv)
    assert status == 0, err
    assert json.loads(out)["sequence"]["n_frames"] == len(frames)


# -- depth not registered to colour ---------------------------------------------------------------


def test_register_depth_moves_a_square_by_the_baseline():
    """A square 0.5 m away in front of a wall at 1 m, seen from a camera 5 cm to the right: the
    square moves 5 cm x fx / 0.5 m to the left, the wall half as far, the nearer surface wins."""
    k = Intrinsics(200.0, 200.0, 79.5, 59.5, width=160, height=120)
    depth = np.full((120, 160), 1.0, np.float32)
    depth[50:70, 70:90] = 0.5
    T = np.eye(4)
    T[0, 3] = -0.05  # colour camera 5 cm along +x: points are 5 cm further left in it
    out = register_depth(depth, depth_intrinsics=k, colour_intrinsics=k, T_colour_from_depth=T)
    shift = round(200 * 0.05 / 0.5)  # 20 px
    assert np.all(out[50:70, 70 - shift : 90 - shift] == np.float32(0.5))
    assert np.all(out[50:70, 80:150] == np.float32(1.0))  # the wall right of it, 10 px to the left
    assert np.all(out[50:70, 90 - shift : 80] == 0)  # the wall the square hid from the depth camera
    assert np.all(out[:, 150:] == 0)  # nothing lands beyond the wall's moved edge


def test_depth_registered_with_tf_static(laptop, registry, tmp_path):
    """A ROS bag of /camera/depth/image_rect_raw in its own frame is registered to colour with the
    chain camera_link -> both optical frames on /tf_static, exactly as register_depth does it."""
    _folder, seq, frames = laptop
    T_link_from_colour = np.eye(4)
    T_link_from_colour[:3, 3] = [0.0, 0.015, 0.0]
    T_link_from_depth = np.eye(4)
    T_link_from_depth[:3, :3] = Rotation.from_euler("y", 2, degrees=True).as_matrix()
    t = [10**9 + i * 33_000_000 for i in range(4)]
    path = write_topics(
        tmp_path / "tf",
        {
            "/camera/color/image_raw": [
                (t[i], "camera_color_optical_frame", frames[i].rgb, "rgb8") for i in range(4)
            ],
            "/camera/depth/image_rect_raw": [
                (t[i], "camera_depth_optical_frame", _mm(frames[i].depth_m), "16UC1") for i in range(4)
            ],
        },
        info=[("/camera/color/camera_info", seq.intrinsics), ("/camera/depth/camera_info", seq.intrinsics)],
        tf=[
            ("camera_link", "camera_color_optical_frame", T_link_from_colour),
            ("camera_link", "camera_depth_optical_frame", T_link_from_depth),
        ],
    )
    (bag,) = open_sequences(registry, path)
    assert bag.meta["depth_registered_by"] == "/tf_static"
    want = register_depth(
        frames[2].depth_m,
        depth_intrinsics=seq.intrinsics,
        colour_intrinsics=seq.intrinsics,
        T_colour_from_depth=np.linalg.inv(T_link_from_colour) @ T_link_from_depth,
    )
    got = bag[2].depth_m
    assert np.array_equal(got, want)
    assert not np.array_equal(got, frames[2].depth_m)  # it did move


# -- bad bags: one line, exit status 2 --------------------------------------------------------------


def _bad_bags(tmp_path: Path, seq, frames) -> dict[str, tuple[Path, str]]:
    """name: (bag, words the error must hold)."""
    k = seq.intrinsics
    out = {}
    good = write_bag(frames[:6], tmp_path / "good.bag", intrinsics=k)
    cut = tmp_path / "truncated.bag"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    out["truncated"] = (cut, "not a readable bag")
    t = [10**9 + i * 33_000_000 for i in range(6)]
    out["no depth topic"] = (
        write_topics(
            tmp_path / "nodepth.bag",
            {"/camera/color/image_raw": [(t[i], "c", frames[i].rgb, "rgb8") for i in range(6)]},
            info=[("/camera/color/camera_info", k)],
        ),
        "no depth image topic",
    )
    small = [f.depth_m[::2, ::2] for f in frames[:6]]
    out["mismatched sizes"] = (
        write_topics(
            tmp_path / "sizes.bag",
            {
                "/camera/color/image_raw": [(t[i], "c", frames[i].rgb, "rgb8") for i in range(6)],
                "/camera/aligned_depth_to_color/image_raw": [
                    (t[i], "c", _mm(small[i]), "16UC1") for i in range(6)
                ],
            },
            info=[("/camera/color/camera_info", k)],
        ),
        "160x120 but depth images",
    )
    out["unknown encoding"] = (
        write_topics(
            tmp_path / "enc.bag",
            {
                "/camera/color/image_raw": [(t[i], "c", frames[i].rgb[..., :2], "yuv422") for i in range(6)],
                "/camera/aligned_depth_to_color/image_raw": [
                    (t[i], "c", _mm(frames[i].depth_m), "16UC1") for i in range(6)
                ],
            },
            info=[("/camera/color/camera_info", k)],
        ),
        "unknown colour encoding 'yuv422'",
    )
    out["no CameraInfo"] = (
        write_bag(frames[:6], tmp_path / "noinfo.bag", intrinsics=k, camera_info=False),
        "no CameraInfo for /camera/color/image_raw: record /camera/color/camera_info",
    )
    out["depth not registered, no extrinsics"] = (
        write_topics(
            tmp_path / "notf.bag",
            {
                "/camera/color/image_raw": [(t[i], "color", frames[i].rgb, "rgb8") for i in range(6)],
                "/camera/depth/image_rect_raw": [
                    (t[i], "depth", _mm(frames[i].depth_m), "16UC1") for i in range(6)
                ],
            },
            info=[("/camera/color/camera_info", k), ("/camera/depth/camera_info", k)],
        ),
        "record /tf_static, or depth aligned to colour (/camera/aligned_depth_to_color/image_raw)",
    )
    return out


BAD = [
    "truncated",
    "no depth topic",
    "mismatched sizes",
    "unknown encoding",
    "no CameraInfo",
    "depth not registered, no extrinsics",
]


@pytest.fixture(scope="module")
def bad_bags(laptop, tmp_path_factory):
    _folder, seq, frames = laptop
    return _bad_bags(tmp_path_factory.mktemp("bad"), seq, frames)


@pytest.mark.parametrize("case", BAD)
def test_bad_bag_is_one_line_and_exit_2(bad_bags, capsys, case):
    path, words = bad_bags[case]
    before = path.read_bytes() if path.is_file() else None
    status, out, err = run_cli(capsys, "classify", path, "--workers", 1)
    assert status == 2
    assert out == "" and len(err.strip().splitlines()) == 1, err
    assert str(path) in err and words in err, err
    assert before is None or path.read_bytes() == before, "a bad bag is never written to"


def test_damaged_message_is_an_input_error(laptop, registry, tmp_path):
    """A bag whose index is whole but one image message is cut short fails on that frame, naming it."""
    _folder, seq, frames = laptop
    t = [10**9 + i * 33_000_000 for i in range(6)]
    colour = [(t[i], "c", frames[i].rgb if i != 4 else frames[i].rgb[:60], "rgb8") for i in range(6)]
    path = write_topics(
        tmp_path / "short.bag",
        {
            "/camera/color/image_raw": colour,
            "/camera/aligned_depth_to_color/image_raw": [
                (t[i], "c", _mm(frames[i].depth_m), "16UC1") for i in range(6)
            ],
        },
        info=[("/camera/color/camera_info", seq.intrinsics)],
    )
    (bag,) = open_sequences(registry, path)
    assert np.array_equal(bag[3].rgb, frames[3].rgb)
    with pytest.raises(InputError, match="160x60"):
        bag[4]


def test_partial_intrinsics_are_refused(laptop, tmp_path):
    _folder, seq, frames = laptop
    path = write_bag(frames[:6], tmp_path / "p.bag", intrinsics=seq.intrinsics)
    with pytest.raises(InputError, match="all four intrinsics"):
        BagReader(BagParams(fx=100.0)).sequences(path)


def test_other_files_are_not_bags(tmp_path, registry):
    (tmp_path / "notes.txt").write_text("x")
    assert BagReader().sequences(tmp_path) == [] and BagReader().sequences(tmp_path / "notes.txt") == []


def test_the_depth_cameras_info_is_not_taken_for_colour(laptop, tmp_path):
    """A bag with CameraInfo for the depth camera only: the colour camera's intrinsics are missing,
    not silently the depth camera's."""
    _folder, seq, frames = laptop
    t = [10**9 + i * 33_000_000 for i in range(4)]
    path = write_topics(
        tmp_path / "depthinfo.bag",
        {
            "/camera/color/image_raw": [(t[i], "c", frames[i].rgb, "rgb8") for i in range(4)],
            "/camera/depth/image_raw": [(t[i], "c", _mm(frames[i].depth_m), "16UC1") for i in range(4)],
        },
        info=[("/camera/depth/camera_info", seq.intrinsics)],
    )
    with pytest.raises(InputError, match="no CameraInfo for /camera/color/image_raw"):
        BagReader().sequences(path)
