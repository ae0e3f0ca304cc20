"""Small fixture datasets written into a temporary folder, one writer per on-disk layout.

Every writer renders the same little scene at 64x48 pixels: a wall 1.0 m from the camera, a box
whose front face is 0.8 m away, and a flap hinged on the box's right edge that turns by
``angles_rad[i]`` about the vertical axis in frame i. The depth is exact (ray-cast analytically),
so a reader's metres can be checked against it. Everything is deterministic.

Writers return the folder they wrote; :func:`layout_root` writes one of each under a common root.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import scipy.io

WIDTH, HEIGHT = 64, 48
FX = FY = 60.0
CX, CY = 31.5, 23.5
WALL_M, BOX_M, FLAP_LENGTH_M = 1.0, 0.8, 0.12
BOX_U, BOX_V = (14, 38), (12, 36)  # pixel ranges [start, stop) of the box's front face


@dataclass
class Render:
    rgb: np.ndarray  # (H, W, 3) uint8, RGB order
    depth_m: np.ndarray  # (H, W) float64, metres
    box: np.ndarray  # (H, W) bool
    flap: np.ndarray  # (H, W) bool

    @property
    def mask(self) -> np.ndarray:
        return self.box | self.flap


def render(angle_rad: float, *, seed: int = 0) -> Render:
    """The fixture scene with the flap turned by ``angle_rad`` (0 = flush with the box front)."""
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH]
    depth = np.full((HEIGHT, WIDTH), WALL_M)
    rows = (v >= BOX_V[0]) & (v < BOX_V[1])
    box = rows & (u >= BOX_U[0]) & (u < BOX_U[1])
    depth[box] = BOX_M
    # Flap: points (x_h + s cos a, y, BOX_M - s sin a), s in [0, L]; solve the ray of each column for s.
    x_hinge = (BOX_U[1] - CX) / FX * BOX_M
    ray = (u - CX) / FX
    c, s_ = np.cos(angle_rad), np.sin(angle_rad)
    s = (ray * BOX_M - x_hinge) / (c + ray * s_)
    flap = rows & (u >= BOX_U[1]) & (s >= 0) & (s <= FLAP_LENGTH_M)
    depth[flap] = BOX_M - s[flap] * s_
    rng = np.random.default_rng(seed)
    rgb = np.empty((HEIGHT, WIDTH, 3), np.uint8)
    rgb[:] = (120, 120, 120)
    rgb[box] = (200, 40, 40)
    rgb[flap] = (40, 40, 200)
    rgb = np.clip(rgb.astype(int) + rng.integers(-10, 11, rgb.shape), 0, 255).astype(np.uint8)
    return Render(rgb, depth, box, flap)


def angles(n_frames: int, *, moving: bool = True) -> np.ndarray:
    """Flap angle per frame: 0 to 0.6 rad over the sequence, or constant 0.2 rad."""
    return np.linspace(0.0, 0.6, n_frames) if moving else np.full(n_frames, 0.2)


def write_png(path: Path, image: np.ndarray) -> None:
    """Write an RGB (H, W, 3) or single-channel image as PNG (cv2 wants BGR)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    if not cv2.imwrite(str(path), image):
        raise OSError(f"could not write {path}")


# -- the native folder format -----------------------------------------------------------------------
def write_folder(
    root: Path,
    name: str = "folder_seq",
    *,
    n_frames: int = 8,
    masks: bool = True,
    label: str | None = "articulated",
    depth_scale: float = 1000.0,
    moving: bool = True,
) -> Path:
    """meta.json + rgb/, depth/ (uint16, ``depth_scale`` units per metre), mask/ and truth.json."""
    seq = Path(root) / name
    a = angles(n_frames, moving=moving)
    for i, angle in enumerate(a):
        r = render(angle, seed=i)
        write_png(seq / "rgb" / f"{i:06d}.png", r.rgb)
        write_png(seq / "depth" / f"{i:06d}.png", np.round(r.depth_m * depth_scale).astype(np.uint16))
        if masks:
            write_png(seq / "mask" / f"{i:06d}.png", r.mask.astype(np.uint8) * 255)
    meta = dict(fx=FX, fy=FY, cx=CX, cy=CY, depth_scale=depth_scale, object="flap_box")
    if label:
        meta["label"] = label
    (seq / "meta.json").write_text(json.dumps(meta, indent=1))
    (seq / "truth.json").write_text(json.dumps(dict(joint_type="revolute", joint_positions=a.tolist())))
    return seq


# -- YCB-Video ----------------------------------------------------------------------------------------
YCBV_IDS = (14, 21)  # 025_mug on the box, 061_foam_brick on the flap
YCBV_FACTOR = 10000
CAMERA_STEP_M = 0.0006  # the camera moves this far along x per frame


def ycbv_pose(i: int, k: int) -> np.ndarray:
    """3x4 camera_from_object of object k (0 = box, 1 = flap) in frame i (the camera drifts along x)."""
    T = np.zeros((3, 4))
    T[:3, :3] = np.eye(3)
    T[:, 3] = (-0.05 + 0.1 * k - CAMERA_STEP_M * i, 0.0, BOX_M)
    return T


def write_ycbv(
    root: Path, name: str = "0000", *, n_frames: int = 8, drop: tuple[str, ...] = (), n_objects: int = 2
) -> Path:
    """A YCB-Video scene folder: NNNNNN-{color,depth,label}.png, -meta.mat, -box.txt.

    ``drop`` names meta.mat variables to leave out (e.g. ``("intrinsic_matrix",)``); with
    ``n_objects=1`` only the box is annotated (the flap's pixels are background).
    """
    scene = Path(root) / name
    scene.mkdir(parents=True, exist_ok=True)
    K = np.array([[FX, 0, CX], [0, FY, CY], [0, 0, 1]])
    for i, angle in enumerate(angles(n_frames, moving=False)):
        r = render(angle, seed=i)
        stem = scene / f"{i + 1:06d}"
        write_png(Path(f"{stem}-color.png"), r.rgb)
        write_png(Path(f"{stem}-depth.png"), np.round(r.depth_m * YCBV_FACTOR).astype(np.uint16))
        label = np.zeros((HEIGHT, WIDTH), np.uint8)
        label[r.box] = YCBV_IDS[0]
        if n_objects > 1:
            label[r.flap] = YCBV_IDS[1]
        write_png(Path(f"{stem}-label.png"), label)
        meta = dict(
            intrinsic_matrix=K,
            factor_depth=np.array([[YCBV_FACTOR]], np.uint16),
            cls_indexes=np.array(YCBV_IDS[:n_objects], np.uint8).reshape(-1, 1),
            poses=np.stack([ycbv_pose(i, k) for k in range(n_objects)], axis=2),
            rotation_translation_matrix=np.hstack([np.eye(3), [[CAMERA_STEP_M * i], [0], [0]]]),
        )
        for key in drop:
            meta.pop(key)
        scipy.io.savemat(f"{stem}-meta.mat", meta)
        Path(f"{stem}-box.txt").write_text("025_mug 14 12 38 36\n061_foam_brick 38 12 50 36\n")
    return scene


# -- RBO ----------------------------------------------------------------------------------------------
RBO_T0 = 1500000000.0
RBO_RATE_HZ = 30.0
RBO_DEPTH_OFFSET_S = 0.004  # depth stamps lag the colour stamps a little, as in a real recording


def write_rbo(
    root: Path,
    name: str = "flapbox01_o",
    *,
    n_frames: int = 8,
    moving: bool = True,
    camera_info: bool = True,
    depth_unit_per_metre: float = 1.0,
) -> Path:
    """An RBO interaction folder: camera_rgb/, camera_depth_registered/ (text matrices, metres, NaN holes),
    camera_rgb_camera_info.csv and flapbox_joint_states.csv (100 Hz, nanoseconds, one revolute joint)."""
    seq = Path(root) / name
    (seq / "camera_depth_registered").mkdir(parents=True, exist_ok=True)
    a = angles(n_frames, moving=moving)
    for i, angle in enumerate(a):
        t = RBO_T0 + i / RBO_RATE_HZ
        r = render(angle, seed=i)
        write_png(seq / "camera_rgb" / f"{i:06d}-{t:.6f}.png", r.rgb)
        depth = r.depth_m * depth_unit_per_metre
        depth[:2, :2] = np.nan  # the sensor's holes
        np.savetxt(
            seq / "camera_depth_registered" / f"{i:06d}-{t + RBO_DEPTH_OFFSET_S:.6f}.txt", depth, fmt="%.6f"
        )
    # One extra colour frame at the end without a depth matrix: a reader must drop it.
    t_extra = RBO_T0 + n_frames / RBO_RATE_HZ + 0.5
    write_png(seq / "camera_rgb" / f"{n_frames:06d}-{t_extra:.6f}.png", render(a[-1]).rgb)
    if camera_info:
        write_camera_info(seq / "camera_rgb_camera_info.csv")
    t_end = RBO_T0 + (n_frames - 1) / RBO_RATE_HZ
    stamps = np.arange(RBO_T0 - 0.05, t_end + 0.05, 0.01)
    # The joint turns at a constant rate (or stands still), sampled before, between and after the frames.
    position = np.polyval(
        np.polyfit(RBO_T0 + np.arange(n_frames) / RBO_RATE_HZ - RBO_T0, a, 1), stamps - RBO_T0
    )
    with (seq / "flapbox_joint_states.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(
            [
                "%time",
                "field.header.seq",
                "field.header.stamp",
                "field.header.frame_id",
                "field.name0",
                "field.position0",
                "field.velocity0",
                "field.effort0",
            ]
        )
        for n, (t, p) in enumerate(zip(stamps, position)):
            ns = int(round(t * 1e9))
            w.writerow([ns, n, ns, "", "j_0_1", f"{p:.6f}", 0.0, 0.0])
    return seq


def write_camera_info(path: Path, *, fx: float = FX) -> None:
    """A ROS CameraInfo CSV export (the columns rostopic echo -p writes)."""
    K = [fx, 0, CX, 0, FY, CY, 0, 0, 1]
    P = [fx, 0, CX, 0, 0, FY, CY, 0, 0, 0, 1, 0]
    header = (
        [
            "%time",
            "field.header.seq",
            "field.header.stamp",
            "field.header.frame_id",
            "field.height",
            "field.width",
            "field.distortion_model",
        ]
        + [f"field.D{i}" for i in range(5)]
        + [f"field.K{i}" for i in range(9)]
        + [f"field.R{i}" for i in range(9)]
        + [f"field.P{i}" for i in range(12)]
    )
    row = (
        [int(RBO_T0 * 1e9), 0, int(RBO_T0 * 1e9), "camera_rgb_optical_frame", HEIGHT, WIDTH, "plumb_bob"]
        + [0.0] * 5
        + K
        + [1, 0, 0, 0, 1, 0, 0, 0, 1]
        + P
    )
    with path.open("w", newline="") as fh:
        csv.writer(fh).writerows([header, row])


# -- TUM RGB-D ----------------------------------------------------------------------------------------
TUM_T0 = 1305031102.0
TUM_SCALE = 5000


def write_tum(
    root: Path,
    name: str = "rgbd_dataset_freiburg1_flapbox",
    *,
    n_frames: int = 8,
    config: dict | None = None,
    groundtruth: bool = True,
) -> Path:
    """A TUM RGB-D folder: rgb.txt, depth.txt (with comments), rgb/, depth/ (1/5000 m) and groundtruth.txt.

    Colour at 30 Hz; depth 10 ms later, plus one unpaired depth frame. ``config`` is written as meta.json.
    """
    seq = Path(root) / name
    rgb_lines = ["# color images", "# file: 'fixture.bag'", "# timestamp filename"]
    depth_lines = ["# depth maps", "# file: 'fixture.bag'", "# timestamp filename"]
    gt_lines = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    for i, angle in enumerate(angles(n_frames)):
        t = TUM_T0 + i / 30.0
        r = render(angle, seed=i)
        write_png(seq / "rgb" / f"{t:.6f}.png", r.rgb)
        write_png(seq / "depth" / f"{t + 0.01:.6f}.png", np.round(r.depth_m * TUM_SCALE).astype(np.uint16))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{t + 0.01:.6f} depth/{t + 0.01:.6f}.png")
        gt_lines.append(f"{t + 0.002:.4f} {0.001 * i:.4f} 0.0000 0.0000 0.0000 0.0000 0.0000 1.0000")
    t_lonely = TUM_T0 + n_frames / 30.0 + 1.0
    write_png(seq / "depth" / f"{t_lonely:.6f}.png", np.full((HEIGHT, WIDTH), TUM_SCALE, np.uint16))
    depth_lines.append(f"{t_lonely:.6f} depth/{t_lonely:.6f}.png")
    (seq / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (seq / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if groundtruth:
        (seq / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    if config is not None:
        (seq / "meta.json").write_text(json.dumps(config))
    return seq


# -- everything at once -------------------------------------------------------------------------------
def layout_root(root: Path) -> dict[str, Path]:
    """One fixture of each layout under ``root`` (in sub-folders); returns reader name -> folder."""
    root = Path(root)
    return dict(
        folder=write_folder(root / "native"),
        ycbv=write_ycbv(root / "ycbv"),
        rbo=write_rbo(root / "rbo"),
        tum=write_tum(root / "tum"),
    )


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative path -> contents), to prove a run wrote nothing there."""
    folder = Path(folder)
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}
