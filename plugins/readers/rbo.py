"""The RBO dataset of articulated objects and interactions (Martín-Martín, Eppner and Brock, IJRR 2019),
in its CSV + images form: one folder per interaction.

::

    INTERACTION/                          e.g. microwave01_o/
        camera_rgb/<n>-<t>.png            8-bit colour; <t> = time stamp in seconds (Unix epoch)
        camera_depth_registered/<n>-<t>.txt
                                          depth registered to the colour image, a whitespace-separated
                                          matrix (numpy.loadtxt), metres, NaN = no reading
        camera_rgb_camera_info.csv        ROS CSV export of sensor_msgs/CameraInfo: field.height,
                                          field.width, field.K0..K8 (row-major 3x3 K); also accepted:
                                          camera_depth_registered_camera_info.csv or any *camera_info.csv
        <object>_joint_states.csv         ROS CSV export of sensor_msgs/JointState: header row, time in
                                          nanoseconds in the third column (field.header.stamp), then
                                          field.name0.., field.position0.. (rad or m)

Depth unit. The dataset's own viewer (``rbo_visualizer.py``) shows the loaded matrix with a
0..3.0 colour range, i.e. metres, and other readers of the dataset treat it as metres. To be safe
against a re-export in millimetres the unit is checked on every frame: a frame whose median valid
depth exceeds 20 is taken to be in millimetres (no RGB-D camera of this kind sees 20 m, and no
object is 20 mm away), and ``meta["depth_unit"]`` says "metres (millimetres detected per frame)".

Frames. Each colour image is paired with the depth map closest in time (within ``max_time_diff_s``,
greedily and one to one, see :func:`artclass_plugins.readers.tum.associate`); colour images without
depth are dropped. The joint positions are interpolated linearly at each frame's time.

Ground truth. ``articulated`` when a joint's interpolated position spans more than
``label_joint_range`` over the frames, else ``static`` (``rigid`` is accepted too: the joint states
cannot tell whether the object was moved as a whole or the camera moved). Per pair: ``AM`` when a
joint moved more than ``joint_eps`` between frames i and j, else ``NM`` (no joint motion; RBO's joint
states say nothing about motion of the whole object). No masks: use a segmenter such as
depth_threshold.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from artclass_core import Frame, InputError, Intrinsics, Params, Reader, Sequence, param
from artclass_core.io import read_rgb, require_number

from .tum import associate

CAMERA_INFO_FILES = ("camera_rgb_camera_info.csv", "camera_depth_registered_camera_info.csv")
STAMP_RE = re.compile(r"-(\d+(?:\.\d*)?)$")
MM_MEDIAN_THRESHOLD = 20.0


def stamp_seconds(path: Path) -> float:
    """Time stamp of an RBO frame file ``<n>-<t>.<ext>``, in seconds (a stamp in ns is converted)."""
    match = STAMP_RE.search(path.stem)
    if not match:
        raise InputError("file name has no '-<timestamp>' before the extension", path=path)
    t = float(match.group(1))
    return t / 1e9 if t > 1e14 else t


def read_depth_txt(path: Path) -> np.ndarray:
    """An RBO depth matrix as (H, W) float32 metres (0 = no reading); see the module docstring on units."""
    path = Path(path)
    if not path.is_file():
        raise InputError("file not found", path=path)
    try:
        depth = np.loadtxt(path, dtype=np.float32, ndmin=2)
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"not a numeric depth matrix ({str(exc).splitlines()[0]})", path=path) from None
    if depth.size == 0:
        raise InputError("empty depth matrix", path=path)
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    valid = depth[depth > 0]
    if valid.size and float(np.median(valid)) > MM_MEDIAN_THRESHOLD:
        depth /= np.float32(1000.0)
    return depth


def read_camera_info(path: Path) -> dict[str, float]:
    """fx, fy, cx, cy (and width, height when given) from a ROS CameraInfo CSV export."""
    path = Path(path)
    try:
        with path.open(newline="") as fh:
            row = next(csv.DictReader(fh), None)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"unreadable CSV ({exc})", path=path) from None
    if row is None:
        raise InputError("no data row (expected a ROS CameraInfo CSV export with field.K0..K8)", path=path)
    keys = ("field.K0", "field.K4", "field.K2", "field.K5")
    if not any(k in row for k in keys) and "field.P0" in row:
        keys = ("field.P0", "field.P5", "field.P2", "field.P6")
    fx, fy, cx, cy = (require_number(row, k, path=path, positive=k in keys[:2]) for k in keys)
    out = dict(fx=fx, fy=fy, cx=cx, cy=cy)
    for k in ("width", "height"):
        if row.get(f"field.{k}") not in (None, "", "0"):
            out[k] = require_number(row, f"field.{k}", path=path)
    return out


def read_joint_states(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Times (s, sorted) and positions per joint name from a ROS JointState CSV export."""
    path = Path(path)
    try:
        with path.open(newline="") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"unreadable CSV ({exc})", path=path) from None
    if len(rows) < 2:
        raise InputError("no joint states (expected a header row and data rows)", path=path)
    header = [h.strip() for h in rows[0]]
    pos_cols = {
        int(m.group(1)): c for c, h in enumerate(header) if (m := re.fullmatch(r"field\.position(\d+)", h))
    }
    name_cols = {
        int(m.group(1)): c for c, h in enumerate(header) if (m := re.fullmatch(r"field\.name(\d+)", h))
    }
    if not pos_cols:
        raise InputError("no field.position<k> column in the header", path=path)
    time_col = header.index("field.header.stamp") if "field.header.stamp" in header else 2
    times, values = [], []
    names = {
        k: (rows[1][name_cols[k]] if k in name_cols and name_cols[k] < len(rows[1]) else f"joint{k}")
        for k in sorted(pos_cols)
    }
    for n, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        try:
            times.append(float(row[time_col]) / 1e9)
            values.append([float(row[pos_cols[k]]) for k in sorted(pos_cols)])
        except (ValueError, IndexError):
            raise InputError(
                f"line {n}: time (column {time_col + 1}, ns) or a joint position is not a number", path=path
            ) from None
    t = np.asarray(times)
    order = np.argsort(t, kind="stable")
    v = np.asarray(values, dtype=float)[order]
    if not np.all(np.isfinite(v)):
        raise InputError("a joint position is not finite", path=path)
    return t[order], {names[k]: v[:, c] for c, k in enumerate(sorted(pos_cols))}


@dataclass(frozen=True)
class RboParams(Params):
    max_time_diff_s: float = param(
        0.02,
        unit="s",
        bounds=(0.0, 1.0),
        help="A colour image is paired with the closest depth map no further apart in "
        "time than this; colour images without one are dropped.",
    )
    joint_eps: float = param(
        0.01,
        unit="rad or m",
        bounds=(0.0, 10.0),
        help="Pair truth: AM when a joint moved more than this between frames i and j "
        "(0.01 rad = 0.57 deg for a revolute joint, 1 cm for a prismatic one).",
    )
    label_joint_range: float = param(
        0.05,
        unit="rad or m",
        bounds=(0.0, 10.0),
        help="Sequence truth: articulated when a joint's position spans more than this "
        "over the frames, else static.",
    )


class RboSequence(Sequence):
    """One RBO interaction."""

    def __init__(
        self,
        path: Path,
        *,
        rgb: list[Path],
        depth: list[Path],
        times_s: np.ndarray,
        intrinsics: Intrinsics,
        joints: dict[str, np.ndarray] | None,
        label: str | None,
        object_name: str,
        params: RboParams,
        meta: dict,
    ):
        super().__init__(
            name=path.name,
            path=path,
            intrinsics=intrinsics,
            n_frames=len(rgb),
            label=label,
            object_name=object_name,
            has_masks=False,
            accepted_labels=("static", "rigid") if label == "static" else None,
            meta=meta,
        )
        self.rgb_files, self.depth_files, self.times_s = rgb, depth, times_s
        self.joints = joints  # name -> (n_frames,) position at each frame's time, NaN outside the record
        self.params = params

    def load(self, i: int) -> Frame:
        rgb = read_rgb(self.rgb_files[i])
        depth = read_depth_txt(self.depth_files[i])
        if rgb.shape[:2] != depth.shape:
            raise InputError(
                f"depth matrix is {depth.shape[1]}x{depth.shape[0]} but the colour image "
                f"{self.rgb_files[i].name} is {rgb.shape[1]}x{rgb.shape[0]}",
                path=self.depth_files[i],
            )
        return Frame(
            i, self.rgb_files[i].stem, rgb, depth, None, time_s=float(self.times_s[i] - self.times_s[0])
        )

    def joint_positions(self, i: int) -> dict[str, float]:
        """Interpolated joint positions (rad or m) at frame i; empty without joint states."""
        return {} if self.joints is None else {n: float(v[i]) for n, v in self.joints.items()}

    def pair_truth(self, i: int, j: int) -> str | None:
        if not self.joints:
            return None
        a = np.array([v[i] for v in self.joints.values()])
        b = np.array([v[j] for v in self.joints.values()])
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            return None
        return "AM" if np.max(np.abs(b - a)) > self.params.joint_eps else "NM"


class RboReader(Reader):
    """Reads one RBO interaction folder (see module docstring)."""

    name = "rbo"
    description = (
        "RBO articulated-objects interaction: camera_rgb/*.png, camera_depth_registered/*.txt (m), "
        "*camera_info.csv, *_joint_states.csv"
    )
    Params = RboParams

    def sequences(self, path: Path) -> list[Sequence]:
        path = Path(path)
        if not (
            path.is_dir() and (path / "camera_rgb").is_dir() and (path / "camera_depth_registered").is_dir()
        ):
            return []
        rgb = sorted(
            (p for p in (path / "camera_rgb").iterdir() if p.suffix.lower() == ".png"), key=stamp_seconds
        )
        depth = sorted(
            (p for p in (path / "camera_depth_registered").iterdir() if p.suffix.lower() == ".txt"),
            key=stamp_seconds,
        )
        if not rgb:
            raise InputError("no colour images (*.png)", path=path / "camera_rgb")
        if not depth:
            raise InputError("no depth matrices (*.txt)", path=path / "camera_depth_registered")
        dt = self.params.max_time_diff_s
        t_rgb = np.array([stamp_seconds(p) for p in rgb])
        pairs = associate(t_rgb, [stamp_seconds(p) for p in depth], max_diff_s=dt)
        if not pairs:
            raise InputError(f"no colour image has a depth matrix within {dt:g} s", path=path)
        times = t_rgb[[a for a, _ in pairs]]

        info_path = next((path / n for n in CAMERA_INFO_FILES if (path / n).is_file()), None)
        info_path = info_path or next(iter(sorted(path.glob("*camera_info.csv"))), None)
        if info_path is None:
            raise InputError(
                f"no camera intrinsics: expected {CAMERA_INFO_FILES[0]} (ROS CameraInfo CSV "
                f"with field.K0..K8)",
                path=path,
            )
        info = read_camera_info(info_path)
        first = read_rgb(rgb[pairs[0][0]])
        width, height = int(info.get("width", first.shape[1])), int(info.get("height", first.shape[0]))
        if (width, height) != (first.shape[1], first.shape[0]):
            raise InputError(
                f"camera info is for {width}x{height} images but {rgb[pairs[0][0]].name} is "
                f"{first.shape[1]}x{first.shape[0]}",
                path=info_path,
            )
        intrinsics = Intrinsics(info["fx"], info["fy"], info["cx"], info["cy"], width=width, height=height)

        joint_files = sorted(path.glob("*_joint_states.csv"))
        joints, label = None, None
        object_name = re.match(r"[A-Za-z]*", path.name).group(0) or path.name
        if joint_files:
            object_name = joint_files[0].name[: -len("_joint_states.csv")] or object_name
            t_js, states = read_joint_states(joint_files[0])
            inside = (times >= t_js[0] - 0.1) & (times <= t_js[-1] + 0.1)
            joints = {n: np.where(inside, np.interp(times, t_js, v), np.nan) for n, v in states.items()}
            spans = [np.nanmax(v) - np.nanmin(v) for v in joints.values() if np.any(np.isfinite(v))]
            if spans:
                label = "articulated" if max(spans) > self.params.label_joint_range else "static"
        meta = dict(
            dataset="rbo",
            depth_unit="metres (millimetres detected per frame)",
            camera_info=info_path.name,
            joint_states=joint_files[0].name if joint_files else None,
            n_rgb=len(rgb),
            n_depth=len(depth),
            n_associated=len(pairs),
        )
        return [
            RboSequence(
                path,
                rgb=[rgb[a] for a, _ in pairs],
                depth=[depth[b] for _, b in pairs],
                times_s=times,
                intrinsics=intrinsics,
                joints=joints,
                label=label,
                object_name=object_name,
                params=self.params,
                meta=meta,
            )
        ]
