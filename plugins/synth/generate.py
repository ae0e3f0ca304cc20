"""Generate one synthetic RGB-D sequence with ground truth."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from .motion import MOTIONS, Trajectory, make_trajectory
from .objects import OBJECTS, T_object_from_child
from .render import (
    NOISE_LEVELS,
    CleanFrame,
    Intrinsics,
    add_sensor_noise,
    object_meshes,
    render_clean,
    room_meshes,
)
from .write import DEPTH_SCALE, prepare_sequence_dir, write_frame, write_json

__all__ = ["GENERATOR_VERSION", "SynthFrame", "SynthSequence", "generate_sequence",
           "plan_sequence"]

GENERATOR_VERSION = "0.1.0"


@dataclass
class SynthFrame:
    """One rendered frame.

    Attributes
    ----------
    index : int
    rgb : ndarray, shape (H, W, 3), uint8, RGB order
    depth_m : ndarray, shape (H, W), float32, metres, 0 = no reading
    mask : ndarray, shape (H, W), bool
        Object pixels (all parts) from the renderer, independent of depth dropouts.
    clean : CleanFrame
        Noise-free rendering (depth, colour, part ids).
    """

    index: int
    rgb: np.ndarray
    depth_m: np.ndarray
    mask: np.ndarray
    clean: CleanFrame


@dataclass
class SynthSequence:
    """A planned sequence: metadata, ground truth and a frame renderer.

    Attributes
    ----------
    meta : dict
        Contents of ``meta.json``.
    truth : dict
        Contents of ``truth.json``.
    trajectory : Trajectory
    intrinsics : Intrinsics
    object_name, noise : str
    seed : int
    """

    meta: dict
    truth: dict
    trajectory: Trajectory
    intrinsics: Intrinsics
    object_name: str
    noise: str
    seed: int

    @property
    def n_frames(self) -> int:
        return len(self.trajectory.T_world_from_object)

    def render(self, index: int) -> SynthFrame:
        """Render frame ``index`` (noise drawn from a generator seeded by (seed, 1, index))."""
        spec = OBJECTS[self.object_name]
        traj = self.trajectory
        q = None if traj.joint_positions is None else float(traj.joint_positions[index])
        meshes = room_meshes() + object_meshes(spec, q, traj.T_world_from_object[index])
        clean = render_clean(meshes, T_camera_from_world=traj.T_camera_from_world[index],
                             intrinsics=self.intrinsics)
        rng = np.random.default_rng([self.seed, 1, index])
        depth_m, rgb = add_sensor_noise(clean, noise=NOISE_LEVELS[self.noise], rng=rng)
        return SynthFrame(index, rgb, depth_m, clean.mask, clean)

    def part_visibility(self, frame: SynthFrame) -> dict:
        """How much of the moving part the camera sees in ``frame``: its share of the object's pixels,
        and how far from the joint axis (m) its visible points reach (90th percentile; 0 when unseen).
        A revolute part turned by dq moves its visible points by up to 2 r sin(dq / 2)."""
        part = frame.clean.part_ids == 1
        seen = int(np.count_nonzero(frame.clean.mask))
        joint = OBJECTS[self.object_name].joint
        reach = 0.0
        if part.any() and joint is not None:
            v, u = np.nonzero(part)
            z = frame.clean.depth_m[v, u].astype(float)
            K = self.intrinsics
            cam = np.stack([(u - K.cx_px) * z / K.fx_px, (v - K.cy_px) * z / K.fy_px, z, np.ones_like(z)])
            obj = (np.linalg.inv(self.trajectory.T_camera_from_object[frame.index]) @ cam)[:3].T
            off = obj - np.asarray(joint.origin_m)
            axis = np.asarray(joint.axis, float)
            reach = float(np.percentile(np.linalg.norm(off - np.outer(off @ axis, axis), axis=1), 90))
        return {"share": round(int(part.sum()) / max(seen, 1), 4), "axis_distance_m": round(reach, 4)}

    def frames(self) -> Iterator[SynthFrame]:
        """Render all frames in order."""
        for i in range(self.n_frames):
            yield self.render(i)


def _nested(T: np.ndarray) -> list:
    return [[round(float(x), 10) for x in row] for row in T]


def plan_sequence(
    *,
    object_name: str,
    motion: str,
    noise: str,
    n_frames: int,
    seed: int,
    width: int = 640,
    height: int = 480,
) -> SynthSequence:
    """Draw the trajectory and ground truth of a sequence without rendering it.

    Parameters are those of ``generate_sequence``.

    Returns
    -------
    SynthSequence
        Call ``.frames()`` or ``.render(i)`` to render.
    """
    if object_name not in OBJECTS:
        raise ValueError(f"object_name={object_name!r} is not one of {sorted(OBJECTS)}")
    if motion not in MOTIONS:
        raise ValueError(f"motion={motion!r} is not one of {sorted(MOTIONS)}")
    if noise not in NOISE_LEVELS:
        raise ValueError(f"noise={noise!r} is not one of {sorted(NOISE_LEVELS)}")
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"seed={seed!r} must be a non-negative integer")
    if not isinstance(n_frames, (int, np.integer)) or n_frames < 2:
        raise ValueError(f"n_frames={n_frames!r} must be an integer >= 2")
    spec = OBJECTS[object_name]
    m = MOTIONS[motion]
    if m.needs_joint and spec.joint is None:
        raise ValueError(
            f"motion={motion!r} needs an articulated object; {object_name!r} is rigid "
            f"(articulated: {sorted(k for k, v in OBJECTS.items() if v.joint is not None)})"
        )
    intr = Intrinsics.for_resolution(int(width), int(height))
    traj = make_trajectory(spec, motion, n_frames=int(n_frames),
                           rng=np.random.default_rng([int(seed), 0]))

    T_co = traj.T_camera_from_object
    meta = {
        "fx": intr.fx_px,
        "fy": intr.fy_px,
        "cx": intr.cx_px,
        "cy": intr.cy_px,
        "depth_scale": DEPTH_SCALE,
        "label": m.label,
        "object": object_name,
        "motion": motion,
        "noise": noise,
        "seed": int(seed),
        "generator": f"artclass synth {GENERATOR_VERSION}",
        "joint_type": spec.joint_type,
    }
    q = traj.joint_positions
    truth = {
        "joint_type": spec.joint_type,
        "joint_positions": [None] * len(T_co) if q is None else [round(float(x), 10) for x in q],
        "object_poses": [_nested(T) for T in T_co],
        # Extras beyond the native format: enough to score axis estimates and part motion.
        "joint_axis_object": None if spec.joint is None else {
            "origin_m": [float(x) for x in spec.joint.origin_m],
            "direction": [float(x) for x in spec.joint.axis],
        },
        "moving_part_poses": None if q is None else [
            _nested(T_co[i] @ T_object_from_child(spec.joint, float(q[i])))
            for i in range(len(T_co))
        ],
        "part_names": [p.name for p in spec.parts],
    }
    return SynthSequence(meta, truth, traj, intr, object_name, noise, int(seed))


def generate_sequence(
    out_dir: str | Path,
    *,
    object_name: str,
    motion: str,
    noise: str,
    n_frames: int,
    seed: int,
    width: int = 640,
    height: int = 480,
    overwrite: bool = False,
) -> Path:
    """Render a synthetic RGB-D sequence and write it in the native folder format.

    Parameters
    ----------
    out_dir : str or Path
        Sequence folder to create; a non-empty folder is refused unless ``overwrite``.
    object_name : str
        A key of ``OBJECTS``.
    motion : {"articulate", "carry_articulate", "carry", "static"}
        The first two need an articulated object.
    noise : {"none", "low", "high"}
        Sensor noise level (see ``NOISE_LEVELS``).
    n_frames : int
        Number of frames, >= 2.
    seed : int
        Non-negative; the same seed gives byte-identical files.
    width, height : int
        Image size in pixels; intrinsics scale with it (640x480: fx = fy = 570).
    overwrite : bool
        Replace the sequence files in an existing non-empty ``out_dir``.

    Returns
    -------
    Path
        The sequence folder.

    Raises
    ------
    FileExistsError
        ``out_dir`` is not empty and ``overwrite`` is False.
    ValueError
        Unknown object, motion or noise level, or a motion that needs a joint on a rigid object.
    """
    seq = plan_sequence(object_name=object_name, motion=motion, noise=noise,
                        n_frames=n_frames, seed=seed, width=width, height=height)
    out = prepare_sequence_dir(out_dir, overwrite=overwrite)
    visibility = []
    for frame in seq.frames():
        write_frame(out, frame.index, rgb=frame.rgb, depth_m=frame.depth_m, mask=frame.mask)
        visibility.append(seq.part_visibility(frame))
    truth = dict(seq.truth)
    if seq.truth["joint_positions"][0] is not None:
        truth["part_visibility"] = visibility
    write_json(out / "truth.json", truth)
    write_json(out / "meta.json", seq.meta)
    return out
