"""The TUM RGB-D layout (Sturm et al., IROS 2012), as the dataset ships it.

::

    SEQ/rgb.txt            lines "timestamp filename" (seconds; "#" starts a comment)
    SEQ/depth.txt          the same for depth
    SEQ/associations.txt   optional lines "timestamp rgb_file timestamp depth_file" (ORB-SLAM2's input)
    SEQ/rgb/*.png          8-bit colour, 640x480
    SEQ/depth/*.png        16-bit depth registered to the colour image; metres = value / 5000
    SEQ/groundtruth.txt    optional "timestamp tx ty tz qx qy qz qw": world_from_camera (motion capture)
    SEQ/meta.json          optional (or camera.json): "fx", "fy", "cx", "cy", "depth_scale" (units per
                           metre, default 5000), "label" (articulated | rigid | static), "object"

Colour and depth frames are the pairs ``associations.txt`` lists, when the folder has one (the file
TUM's ``associate.py`` writes, and ORB-SLAM2 reads: recordings made with other tools may carry
timestamps that cannot be associated); otherwise they are associated as ``associate.py`` does:
candidate pairs closer than ``max_time_diff_s`` (0.02 s), taken greedily from the closest, each frame
used once.

Intrinsics: the reader's ``fx, fy, cx, cy`` when given (``--param fx=615 ...``); else
``meta.json``/``camera.json`` when present; otherwise the calibrated values of the Kinect named in
the folder name (``rgbd_dataset_freiburg1_*`` -> fr1, as published on the TUM website); otherwise the
ROS default (525, 525, 319.5, 239.5). ``meta["intrinsics_source"]`` says which was used. The depth
scale likewise: ``depth_scale``, else meta.json's, else TUM's 5000 units a metre (a RealSense
recording saved in millimetres has 1000).

There is no label unless meta.json gives one (TUM RGB-D films static scenes, not handled objects),
and no per-pair truth: the ground truth is the camera's trajectory, not an object's pose. It is
available as :meth:`TumSequence.world_from_camera`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from artclass_core import Frame, InputError, Intrinsics, Params, Reader, Sequence, param
from artclass_core.io import read_depth, read_json, read_rgb, require_number
from artclass_core.types import LABELS

# Calibrated intrinsics of the three Kinects (fx, fy, cx, cy), from the TUM RGB-D "file formats" page.
FREIBURG_INTRINSICS: dict[str, tuple[float, float, float, float]] = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
ROS_DEFAULT_INTRINSICS = (525.0, 525.0, 319.5, 239.5)
TUM_DEPTH_SCALE = 5000.0
CONFIG_FILES = ("meta.json", "camera.json")
ASSOCIATIONS = "associations.txt"


def associate(times_a: np.ndarray, times_b: np.ndarray, *, max_diff_s: float) -> list[tuple[int, int]]:
    """Match two lists of timestamps one to one, as TUM's ``associate.py`` does.

    Every pair closer than ``max_diff_s`` (strictly) is a candidate; candidates are taken greedily from the
    closest, and each index is used at most once.

    Parameters
    ----------
    times_a, times_b : ndarray, shape (N,) and (M,), seconds
    max_diff_s : largest accepted time difference, seconds

    Returns
    -------
    list of (index into a, index into b), sorted by index into a
    """
    a = np.asarray(times_a, dtype=float)
    b = np.asarray(times_b, dtype=float)
    order_b = np.argsort(b, kind="stable")
    b_sorted = b[order_b]
    candidates = []
    for ia, t in enumerate(a):
        lo = np.searchsorted(b_sorted, t - max_diff_s, side="left")
        hi = np.searchsorted(b_sorted, t + max_diff_s, side="right")
        for k in range(lo, hi):
            diff = abs(b_sorted[k] - t)
            if diff < max_diff_s:
                candidates.append((diff, ia, int(order_b[k])))
    candidates.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    matches = []
    for _diff, ia, ib in candidates:
        if ia not in used_a and ib not in used_b:
            used_a.add(ia)
            used_b.add(ib)
            matches.append((ia, ib))
    return sorted(matches)


def read_list(path: Path, *, columns: int) -> list[list[str]]:
    """The data lines of a TUM text file (``#`` comments and blank lines dropped), split on whitespace.

    Each line must have at least ``columns`` fields and start with a number (the timestamp).
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"unreadable text file ({exc})", path=path) from None
    rows = []
    for n, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        try:
            float(fields[0])
            if len(fields) < columns:
                raise ValueError
        except ValueError:
            raise InputError(
                f"line {n} is not 'timestamp{' filename' if columns == 2 else ' values...'}': {line[:60]!r}",
                path=path,
            ) from None
        rows.append(fields)
    return rows


@dataclass(frozen=True)
class TumParams(Params):
    max_time_diff_s: float = param(
        0.02,
        unit="s",
        bounds=(0.0, 1.0),
        help="Colour and depth frames further apart in time than this are not paired "
        "(TUM's associate.py default).",
    )
    fx: float | None = param(
        None,
        unit="px",
        bounds=(1.0, 1e5),
        auto="meta.json, the Kinect named in the folder name, or 525",
        help="Focal length along x of the colour camera, pixels.",
    )
    fy: float | None = param(
        None, unit="px", bounds=(1.0, 1e5), auto="as fx", help="Focal length along y, pixels."
    )
    cx: float | None = param(
        None, unit="px", bounds=(-1e5, 1e5), auto="as fx", help="Principal point, x, pixels."
    )
    cy: float | None = param(
        None, unit="px", bounds=(-1e5, 1e5), auto="as fx", help="Principal point, y, pixels."
    )
    depth_scale: float | None = param(
        None,
        unit="1/m",
        bounds=(1e-3, 1e7),
        auto="meta.json's depth_scale, else 5000",
        help="Depth image units per metre (TUM: 5000; a RealSense saved in millimetres: 1000).",
    )


class TumSequence(Sequence):
    """One TUM RGB-D sequence folder."""

    def __init__(
        self,
        path: Path,
        *,
        rgb: list[tuple[float, Path]],
        depth: list[tuple[float, Path]],
        intrinsics: Intrinsics,
        depth_scale: float,
        config: dict,
        groundtruth: np.ndarray | None,
        max_time_diff_s: float,
        meta: dict,
    ):
        label = config.get("label")
        super().__init__(
            name=path.name,
            path=path,
            intrinsics=intrinsics,
            n_frames=len(rgb),
            label=label,
            object_name=config.get("object"),
            has_masks=False,
            meta=meta,
        )
        self.rgb, self.depth, self.depth_scale = rgb, depth, depth_scale
        self.start_time_s = rgb[0][0]
        self.groundtruth = groundtruth
        self.max_time_diff_s = max_time_diff_s

    def load(self, i: int) -> Frame:
        t, rgb_file = self.rgb[i]
        _, depth_file = self.depth[i]
        rgb = read_rgb(rgb_file)
        depth = read_depth(depth_file, units_per_metre=self.depth_scale)
        if rgb.shape[:2] != depth.shape:
            raise InputError(
                f"colour image is {rgb.shape[1]}x{rgb.shape[0]} but its depth image "
                f"{depth_file.name} is {depth.shape[1]}x{depth.shape[0]}",
                path=rgb_file,
            )
        return Frame(i, rgb_file.stem, rgb, depth, None, time_s=t - self.start_time_s)

    def world_from_camera(self, i: int) -> np.ndarray | None:
        """4x4 pose of the colour camera in the motion-capture frame at frame i (nearest ground-truth
        sample within ``max_time_diff_s``), or None without ground truth there."""
        if self.groundtruth is None or not len(self.groundtruth):
            return None
        t = self.rgb[i][0]
        k = int(np.argmin(np.abs(self.groundtruth[:, 0] - t)))
        if abs(self.groundtruth[k, 0] - t) > self.max_time_diff_s:
            return None
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(self.groundtruth[k, 4:8]).as_matrix()
        T[:3, 3] = self.groundtruth[k, 1:4]
        return T


def _timed_files(path: Path, list_file: str) -> list[tuple[float, Path]]:
    rows = read_list(path / list_file, columns=2)
    return [(float(r[0]), path / r[1]) for r in rows]


class TumReader(Reader):
    """Reads a TUM RGB-D sequence folder (see module docstring)."""

    name = "tum"
    description = (
        "TUM RGB-D folder: rgb.txt, depth.txt, rgb/, depth/ (16-bit, 1/5000 m), optional groundtruth.txt"
    )
    Params = TumParams

    def sequences(self, path: Path) -> list[Sequence]:
        path = Path(path)
        if not (path.is_dir() and (path / "rgb.txt").is_file() and (path / "depth.txt").is_file()):
            return []
        rgb, depth = _timed_files(path, "rgb.txt"), _timed_files(path, "depth.txt")
        if not rgb:
            raise InputError("lists no colour image", path=path / "rgb.txt")
        if not depth:
            raise InputError("lists no depth image", path=path / "depth.txt")
        dt = self.params.max_time_diff_s
        n_listed = len(rgb)
        if (path / ASSOCIATIONS).is_file():
            rows = read_list(path / ASSOCIATIONS, columns=4)
            rgb = [(float(r[0]), path / r[1]) for r in rows]
            depth = [(float(r[2]), path / r[3]) for r in rows]
            if not rgb:
                raise InputError("lists no frame", path=path / ASSOCIATIONS)
        else:
            pairs = associate([t for t, _ in rgb], [t for t, _ in depth], max_diff_s=dt)
            if not pairs:
                raise InputError(
                    f"no colour frame has a depth frame within {dt:g} s "
                    f"(rgb.txt and depth.txt timestamps do not overlap)",
                    path=path,
                )
            rgb = [rgb[a] for a, _ in pairs]
            depth = [depth[b] for _, b in pairs]

        config_path = next((path / n for n in CONFIG_FILES if (path / n).is_file()), None)
        config = read_json(config_path) if config_path else {}
        label = config.get("label")
        if label is not None and label not in LABELS:
            raise InputError(f"label {label!r} is not one of {', '.join(LABELS)}", path=config_path)
        given = tuple(getattr(self.params, k) for k in ("fx", "fy", "cx", "cy"))
        if any(v is not None for v in given):
            if None in given:
                raise InputError("give all four intrinsics fx, fy, cx, cy, or none", path=path)
            fx, fy, cx, cy = given
            source = "reader parameters"
        elif config_path and any(k in config for k in ("fx", "fy", "cx", "cy")):
            fx, fy, cx, cy = (
                require_number(config, k, path=config_path, positive=k in ("fx", "fy"))
                for k in ("fx", "fy", "cx", "cy")
            )
            source = config_path.name
        else:
            camera = re.search(r"freiburg([123])", path.name)
            if camera:
                source = f"freiburg{camera.group(1)}"
                fx, fy, cx, cy = FREIBURG_INTRINSICS[source]
            else:
                source = "ros_default"
                fx, fy, cx, cy = ROS_DEFAULT_INTRINSICS
        depth_scale = self.params.depth_scale or (
            require_number(config, "depth_scale", path=config_path)
            if "depth_scale" in config
            else TUM_DEPTH_SCALE
        )

        first = read_depth(depth[0][1], units_per_metre=depth_scale)
        intrinsics = Intrinsics(fx, fy, cx, cy, width=first.shape[1], height=first.shape[0])

        groundtruth = None
        if (path / "groundtruth.txt").is_file():
            rows = read_list(path / "groundtruth.txt", columns=8)
            try:
                groundtruth = np.array([[float(v) for v in r[:8]] for r in rows], dtype=float).reshape(-1, 8)
            except ValueError:
                raise InputError(
                    "expected 'timestamp tx ty tz qx qy qz qw' numbers on every line",
                    path=path / "groundtruth.txt",
                ) from None

        meta = dict(
            config,
            dataset="tum",
            intrinsics_source=source,
            depth_units_per_metre=depth_scale,
            n_rgb_listed=n_listed,
            n_associated=len(rgb),
            has_groundtruth=groundtruth is not None,
        )
        return [
            TumSequence(
                path,
                rgb=rgb,
                depth=depth,
                intrinsics=intrinsics,
                depth_scale=depth_scale,
                config=config,
                groundtruth=groundtruth,
                max_time_diff_s=dt,
                meta=meta,
            )
        ]
