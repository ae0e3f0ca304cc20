"""The native folder format.

::

    SEQ/meta.json     {"fx", "fy", "cx", "cy", "depth_scale" (depth units per metre),
                       optional "label" (articulated | rigid | static), "object", ...}
    SEQ/rgb/*.png     8-bit colour
    SEQ/depth/*.png   16-bit depth, matched to rgb/ by sorted file name
    SEQ/mask/*.png    optional, non-zero = object
    SEQ/truth.json    optional per-frame ground truth, for per-pair truth (docs/data-formats.md):
                      "object_poses" (4x4 camera_from_object, per frame); with "parts", "part_poses",
                      "part_valid_px", "part_points_m" and "sensor", the observable articulation truth;
                      otherwise the joint-state truth from "joint_positions" and "part_visibility"
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
# Observable articulation: each side of a joint needs depth on at least this many pixels, and this share
# of the object's pixels, in both frames.
MIN_SIDE_PIXELS = 30
MIN_SIDE_SHARE = 0.02
# A side's median visible point must move by more than this many axial noise sigmas, plus one pixel at
# its depth, for AM; a motion between AMBIGUOUS_SIGMAS sigmas and that gives no truth.
OBSERVABLE_SIGMAS = 3.0
AMBIGUOUS_SIGMAS = 1.0


def _images(folder: Path) -> list[Path]:
    return (
        sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES) if folder.is_dir() else []
    )


Threshold = float | tuple[float, float]


def _exceeds(value: float, eps: Threshold) -> bool | None:
    """True above the band, False at or below it, None (ambiguous) inside it."""
    low, high = eps if isinstance(eps, tuple) else (eps, eps)
    return True if value > high else False if value <= low else None


def pair_truth_from_states(
    joint_a, joint_b, pose_a, pose_b, *, joint_eps: Threshold, move_eps_m: Threshold, turn_eps_rad: Threshold
) -> str | None:
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


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    order = np.argsort(values)
    cum = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cum, 0.5 * cum[-1])])


def _side_motion(truth: dict, side: list[int], frame: int, T_ref: dict, motion: np.ndarray):
    """Median displacement (m) and median camera depth (m) of the points of the parts ``side`` visible
    in ``frame`` when ``motion`` (4x4, in the reference frame) moves them; None when no point is seen.

    ``T_ref[f]`` is camera_from_reference in frame f. Each part's sample counts for its pixels."""
    disp, depth, weight = [], [], []
    for m in side:
        pts = np.asarray(truth["part_points_m"][frame][m], dtype=float).reshape(-1, 3)
        if not len(pts):
            continue
        P = np.asarray(truth["part_poses"][frame][m], dtype=float)
        cam = pts @ P[:3, :3].T + P[:3, 3]
        T = np.linalg.inv(T_ref[frame]) @ P
        ref = pts @ T[:3, :3].T + T[:3, 3]
        moved = ref @ motion[:3, :3].T + motion[:3, 3]
        disp.append(np.linalg.norm(moved - ref, axis=1))
        depth.append(cam[:, 2])
        weight.append(np.full(len(pts), truth["part_valid_px"][frame][m] / len(pts)))
    if not disp:
        return None
    w = np.concatenate(weight)
    return _weighted_median(np.concatenate(disp), w), _weighted_median(np.concatenate(depth), w)


def observable_joint_motions(truth: dict, i: int, j: int) -> list[dict]:
    """For every joint, how far its motion between frames i and j moves what the sensor sees of it.

    The *moving side* of a joint is its child part with every part that hangs on it, the *rest* is
    every other part. Each side is judged in the other's frame: the joint's motion from i to j (the
    change of parent_from_child) moves the moving side's visible points, as seen from the rest, and
    its inverse moves the rest's points, as seen from the moving side. Each side's median point
    displacement is taken over its points seen in frame i (moved forward) and in frame j (moved back),
    the smaller of the two; its depth is the larger of its median depths in i and j.

    Returns
    -------
    list of dict
        Per joint: ``valid`` (both sides have depth on at least ``MIN_SIDE_PIXELS`` pixels and
        ``MIN_SIDE_SHARE`` of the object's pixels, in both frames), and for each side
        (``moving``, ``rest``) its ``displacement_m``, ``depth_m`` and ``sigma_m`` (the sensor's axial
        noise there, with the depth quantisation's step / sqrt(12) as a floor).
    """
    parents = [p["parent"] for p in truth["parts"]]
    sensor = truth["sensor"]
    step_sigma = sensor.get("depth_step_m", 0.0) / np.sqrt(12.0)
    out = []
    for child, part in enumerate(truth["parts"]):
        parent = part["parent"]
        if parent < 0:
            continue
        moving = [child]
        for k, p in enumerate(parents):
            if p in moving and k not in moving:
                moving.append(k)
        rest = [k for k in range(len(parents)) if k not in moving]
        valid = True
        for f in (i, j):
            px = truth["part_valid_px"][f]
            need = max(MIN_SIDE_PIXELS, MIN_SIDE_SHARE * sum(px))
            valid &= all(sum(px[k] for k in s) >= need for s in (moving, rest))
        cam = {
            side: {f: np.asarray(truth["part_poses"][f][k], dtype=float) for f in (i, j)}
            for side, k in (("parent", parent), ("child", child))
        }
        T_pc = {f: np.linalg.inv(cam["parent"][f]) @ cam["child"][f] for f in (i, j)}
        forward = T_pc[j] @ np.linalg.inv(T_pc[i])  # in the parent's frame
        forward_c = np.linalg.inv(T_pc[j]) @ T_pc[i]  # the rest's motion, child's frame
        sides = {}
        for name, members, ref, M in (
            ("moving", moving, cam["parent"], forward),
            ("rest", rest, cam["child"], forward_c),
        ):
            a = _side_motion(truth, members, i, ref, M)
            b = _side_motion(truth, members, j, ref, np.linalg.inv(M))
            seen = [x for x in (a, b) if x is not None]
            if not seen:
                sides[name] = None
                continue
            z = max(x[1] for x in seen)
            sigma = sensor["axial_a_m"] + sensor["axial_b_per_m"] * (z - sensor["axial_reference_m"]) ** 2
            sides[name] = dict(
                displacement_m=min(x[0] for x in seen), depth_m=z, sigma_m=max(sigma, step_sigma)
            )
        out.append(dict(joint=part["joint"], valid=bool(valid and all(sides.values())), **sides))
    return out


def observable_pair_truth(truth: dict, i: int, j: int) -> str | None:
    """Pair truth by what the sensor can see: ``AM``, ``RM``, ``NM`` or None (ambiguous).

    ``AM`` when, for some joint whose two sides both have enough valid depth in both frames
    (``observable_joint_motions``), the joint's motion moves the median visible point of each side by
    more than ``OBSERVABLE_SIGMAS`` times the axial depth noise sigma(z) plus one pixel (z / fx) at that
    side's depth. None when no joint does but one moves each side by more than ``AMBIGUOUS_SIGMAS``
    sigma. Otherwise the object's own motion decides ``RM`` or ``NM`` (``pair_truth_from_states``); or,
    when its base is not seen in both frames, the motion of the parts that are.
    """
    fx = truth["sensor"]["fx_px"]
    ambiguous = False
    for motion in observable_joint_motions(truth, i, j):
        if not motion["valid"]:
            continue
        sides = (motion["moving"], motion["rest"])
        if all(s["displacement_m"] > OBSERVABLE_SIGMAS * s["sigma_m"] + s["depth_m"] / fx for s in sides):
            return "AM"
        ambiguous |= all(s["displacement_m"] > AMBIGUOUS_SIGMAS * s["sigma_m"] for s in sides)
    if ambiguous:
        return None
    # No articulation is seen. The object's (its base's) motion is, unless the base is hidden and other
    # parts are not: a drawer pulled out of a carcass that an arm hides is seen to move.
    poses = truth.get("object_poses") or [None] * len(truth["part_poses"])
    seen = _parts_seen(truth, i, j)
    if not seen or any(truth["parts"][m]["parent"] < 0 for m in seen):
        moves = [(poses[i], poses[j])]
    else:
        moves = [(truth["part_poses"][i][m], truth["part_poses"][j][m]) for m in seen]
    verdicts = [
        pair_truth_from_states(
            None, None, a, b, joint_eps=PRISMATIC_BAND_M, move_eps_m=MOVE_BAND_M, turn_eps_rad=TURN_BAND_RAD
        )
        for a, b in moves
    ]
    return "RM" if "RM" in verdicts else None if None in verdicts else "NM"


def _parts_seen(truth: dict, i: int, j: int) -> list[int]:
    """The parts with depth on at least ``MIN_SIDE_PIXELS`` pixels and ``MIN_SIDE_SHARE`` of the
    object's pixels in both frames i and j."""
    counts = [truth["part_valid_px"][f] for f in (i, j)]
    return [
        m
        for m in range(len(counts[0]))
        if all(px[m] >= max(MIN_SIDE_PIXELS, MIN_SIDE_SHARE * sum(px)) for px in counts)
    ]


#: truth.json keys the observable articulation truth needs.
OBSERVABLE_TRUTH_KEYS = ("parts", "part_poses", "part_valid_px", "part_points_m", "sensor")


class FolderSequence(Sequence):
    def __init__(
        self,
        path: Path,
        meta: dict,
        rgb: list[Path],
        depth: list[Path],
        masks: list[Path],
        truth: dict | None,
        width: int,
        height: int,
    ):
        meta_path = path / "meta.json"
        intr = Intrinsics(
            *(require_number(meta, k, path=meta_path) for k in ("fx", "fy", "cx", "cy")),
            width=width,
            height=height,
        )
        self.depth_scale = require_number(meta, "depth_scale", path=meta_path)
        label = meta.get("label")
        if label is not None and label not in LABELS:
            raise InputError(f"label {label!r} is not one of {', '.join(LABELS)}", path=meta_path)
        super().__init__(
            name=path.name,
            path=path,
            intrinsics=intr,
            n_frames=len(rgb),
            label=label,
            object_name=meta.get("object"),
            has_masks=bool(masks),
            meta=meta,
        )
        self.rgb_files, self.depth_files, self.mask_files, self.truth = rgb, depth, masks, truth

    def load(self, i: int) -> Frame:
        rgb = read_rgb(self.rgb_files[i])
        depth = read_depth(self.depth_files[i], units_per_metre=self.depth_scale)
        mask = read_mask(self.mask_files[i]) if self.mask_files else None
        for what, image, path in (
            ("colour", rgb, self.rgb_files[i]),
            ("mask", mask, self.mask_files[i] if self.mask_files else None),
        ):
            if image is not None and image.shape[:2] != depth.shape:
                raise InputError(
                    f"{what} image is {image.shape[1]}x{image.shape[0]} but its depth image "
                    f"{self.depth_files[i].name} is {depth.shape[1]}x{depth.shape[0]}",
                    path=path,
                )
        return Frame(i, self.rgb_files[i].stem, rgb, depth, mask)

    def pair_truth(self, i: int, j: int) -> str | None:
        """Observable articulation truth (``observable_pair_truth``) when truth.json has what it needs,
        else the joint-state truth of ``pair_truth_legacy``."""
        if self.truth and all(k in self.truth for k in OBSERVABLE_TRUTH_KEYS):
            return observable_pair_truth(self.truth, i, j)
        return self.pair_truth_legacy(i, j)

    def pair_truth_legacy(self, i: int, j: int) -> str | None:
        """Joint-state truth: AM when the first joint moved by more than its band, judged by how far the
        visible part went when truth.json has ``part_visibility``; else RM or NM by the object's motion."""
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
        return pair_truth_from_states(
            a, b, poses[i], poses[j], joint_eps=joint_eps, move_eps_m=MOVE_BAND_M, turn_eps_rad=TURN_BAND_RAD
        )


class FolderReader(Reader):
    """Reads the native folder format (see module docstring)."""

    name = "folder"
    description = "native format: meta.json + rgb/, depth/ (16-bit), optional mask/ and truth.json"

    def sequences(self, path: Path) -> list[Sequence]:
        path = Path(path)
        if not (path.is_dir() and (path / "meta.json").is_file() and (path / "depth").is_dir()):
            return []
        if (path / "rgb.txt").is_file() and (path / "depth.txt").is_file():
            return []  # a TUM RGB-D folder whose meta.json only gives intrinsics: the tum reader's
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
        return [
            FolderSequence(path, meta, rgb, depth, masks, truth, width=first.shape[1], height=first.shape[0])
        ]
