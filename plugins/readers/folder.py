"""The native folder format.

::

    SEQ/meta.json     {"fx", "fy", "cx", "cy", "depth_scale" (depth units per metre),
                       optional "label" (articulated | rigid | static), "object", ...}
    SEQ/rgb/*.png     8-bit colour
    SEQ/depth/*.png   16-bit depth, matched to rgb/ by sorted file name
    SEQ/mask/*.png    optional, non-zero = object
    SEQ/truth.json    optional per-frame ground truth: "joint_positions" (rad or m, per frame) and
                      "object_poses" (4x4 camera_from_object, per frame), for per-pair truth;
                      optional "part_visibility" (per frame: "share" of the object's pixels that are
                      the moving part, "axis_distance_m" its visible points reach from the joint axis)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from artclass_core import Frame, InputError, Intrinsics, Reader, Sequence
from artclass_core.geometry import rotation_angle_rad
from artclass_core.io import read_depth, read_json, read_mask, read_rgb, require_number
from artclass_core.types import LABELS

IMAGE_SUFFIXES = (".png",)
# Per-pair truth bands (no motion at or below the first value, motion above the second, no truth in
# between): about 1x and 3x the depth noise of a structured-light sensor at 1 m, for a 10 cm part.
REVOLUTE_BAND_RAD = (np.radians(0.5), np.radians(3.0))
PRISMATIC_BAND_M = (0.001, 0.005)
MOVE_BAND_M = (0.001, 0.005)
TURN_BAND_RAD = (np.radians(0.5), np.radians(2.0))
# A joint motion is only "seen" when the moving part covers this share of the object's pixels in both
# frames: a lid seen edge-on, or a handle hidden behind the other, shows the sensor no articulation.
VISIBLE_PART_SHARE = 0.05


def _images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES) if folder.is_dir() else []


Threshold = float | tuple[float, float]


def _exceeds(value: float, eps: Threshold) -> bool | None:
    """True above the band, False at or below it, None (ambiguous) inside it."""
    low, high = eps if isinstance(eps, tuple) else (eps, eps)
    return True if value > high else False if value <= low else None


def pair_truth_from_states(joint_a, joint_b, pose_a, pose_b, *, joint_eps: Threshold, move_eps_m: Threshold,
                           turn_eps_rad: Threshold) -> str | None:
    """AM when the joint moved, else RM when the object moved, else NM; None when unknown or ambiguous.

    ``pose_*`` are 4x4 camera_from_object. The object "moved" when its points (taken 10 cm from the
    origin, a typical object radius) moved by more than ``move_eps_m`` or it turned more than
    ``turn_eps_rad``. A threshold given as ``(low, high)`` is a band: a change inside it is neither
    clearly a motion nor clearly none (e.g. a 1 degree turn of a 10 cm lid moves it by less than the
    sensor noise), and the pair gets no truth rather than a label no sensor could confirm.
    """
    if joint_a is not None and joint_b is not None:
        joint = _exceeds(abs(joint_b - joint_a), joint_eps)
        if joint is not False:
            return "AM" if joint else None
    if pose_a is None or pose_b is None:
        return None if joint_a is None or joint_b is None else "NM"
    A, B = np.asarray(pose_a, float), np.asarray(pose_b, float)
    delta = B @ np.linalg.inv(A)
    moved = _exceeds(float(np.linalg.norm(delta[:3, 3] + (delta[:3, :3] - np.eye(3)) @ A[:3, 3])), move_eps_m)
    turned = _exceeds(rotation_angle_rad(delta[:3, :3]), turn_eps_rad)
    if moved or turned:
        return "RM"
    return "NM" if moved is False and turned is False else None


class FolderSequence(Sequence):
    def __init__(self, path: Path, meta: dict, rgb: list[Path], depth: list[Path], masks: list[Path],
                 truth: dict | None, width: int, height: int):
        meta_path = path / "meta.json"
        intr = Intrinsics(*(require_number(meta, k, path=meta_path) for k in ("fx", "fy", "cx", "cy")),
                          width=width, height=height)
        self.depth_scale = require_number(meta, "depth_scale", path=meta_path)
        label = meta.get("label")
        if label is not None and label not in LABELS:
            raise InputError(f"label {label!r} is not one of {', '.join(LABELS)}", path=meta_path)
        super().__init__(name=path.name, path=path, intrinsics=intr, n_frames=len(rgb), label=label,
                         object_name=meta.get("object"), has_masks=bool(masks), meta=meta)
        self.rgb_files, self.depth_files, self.mask_files, self.truth = rgb, depth, masks, truth

    def load(self, i: int) -> Frame:
        rgb = read_rgb(self.rgb_files[i])
        depth = read_depth(self.depth_files[i], units_per_metre=self.depth_scale)
        mask = read_mask(self.mask_files[i]) if self.mask_files else None
        for what, image, path in (("colour", rgb, self.rgb_files[i]),
                                  ("mask", mask, self.mask_files[i] if self.mask_files else None)):
            if image is not None and image.shape[:2] != depth.shape:
                raise InputError(f"{what} image is {image.shape[1]}x{image.shape[0]} but its depth image "
                                 f"{self.depth_files[i].name} is {depth.shape[1]}x{depth.shape[0]}", path=path)
        return Frame(i, self.rgb_files[i].stem, rgb, depth, mask)

    def pair_truth(self, i: int, j: int) -> str | None:
        if not self.truth:
            return None
        joints = self.truth.get("joint_positions") or [None] * len(self)
        poses = self.truth.get("object_poses") or [None] * len(self)
        revolute = self.truth.get("joint_type") != "prismatic"
        joint_eps = REVOLUTE_BAND_RAD if revolute else PRISMATIC_BAND_M
        a, b = joints[i], joints[j]
        seen = self.truth.get("part_visibility")
        if seen and a is not None and b is not None and _exceeds(abs(b - a), joint_eps):
            # The joint moved: judge it by what the sensor can see of it, how far the visible part went.
            if min(seen[i]["share"], seen[j]["share"]) < VISIBLE_PART_SHARE:
                return None
            reach = min(seen[i]["axis_distance_m"], seen[j]["axis_distance_m"])
            a, b = 0.0, 2.0 * reach * np.sin(abs(b - a) / 2.0) if revolute else abs(b - a)
            joint_eps = PRISMATIC_BAND_M
        return pair_truth_from_states(a, b, poses[i], poses[j], joint_eps=joint_eps,
                                      move_eps_m=MOVE_BAND_M, turn_eps_rad=TURN_BAND_RAD)


class FolderReader(Reader):
    """Reads the native folder format (see module docstring)."""

    name = "folder"
    description = "native format: meta.json + rgb/, depth/ (16-bit), optional mask/ and truth.json"

    def sequences(self, path: Path) -> list[Sequence]:
        path = Path(path)
        if not (path.is_dir() and (path / "meta.json").is_file() and (path / "depth").is_dir()):
            return []
        if (path / "rgb.txt").is_file() and (path / "depth.txt").is_file():
            return []   # a TUM RGB-D folder whose meta.json only gives intrinsics: the tum reader's
        meta = read_json(path / "meta.json")
        rgb, depth, masks = _images(path / "rgb"), _images(path / "depth"), _images(path / "mask")
        if not rgb:
            raise InputError("no colour images in rgb/", path=path)
        if len(rgb) != len(depth):
            raise InputError(f"{len(rgb)} colour images but {len(depth)} depth images", path=path)
        if masks and len(masks) != len(rgb):
            raise InputError(f"{len(masks)} masks for {len(rgb)} frames", path=path / "mask")
        truth = read_json(path / "truth.json") if (path / "truth.json").is_file() else None
        first = read_depth(depth[0], units_per_metre=1.0)
        return [FolderSequence(path, meta, rgb, depth, masks, truth, width=first.shape[1], height=first.shape[0])]
