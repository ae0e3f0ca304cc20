"""Motion kinds and per-sequence trajectories (object pose, joint position, camera pose)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .objects import ObjectSpec, object_extent_m, object_points_m, rotation_about_axis

__all__ = ["MOTIONS", "MotionSpec", "Trajectory", "ease_in_out", "look_at", "make_trajectory"]


@dataclass(frozen=True)
class MotionSpec:
    """A kind of motion.

    Attributes
    ----------
    name : str
    label : {"articulated", "rigid", "static"}
        Class label of a sequence with this motion.
    moves_joint, moves_object : bool
    needs_joint : bool
        Only for articulated objects.
    description : str
    """

    name: str
    label: str
    moves_joint: bool
    moves_object: bool
    needs_joint: bool
    description: str


#: Motion kinds by name.
MOTIONS: dict[str, MotionSpec] = {
    "articulate": MotionSpec(
        "articulate", "articulated", True, False, True, "base rests on the table, the joint moves"
    ),
    "carry_articulate": MotionSpec(
        "carry_articulate", "articulated", True, True, True, "the object is carried while the joint moves"
    ),
    "carry": MotionSpec(
        "carry", "rigid", False, True, False, "the object is carried (joint, if any, held fixed)"
    ),
    "static": MotionSpec(
        "static", "static", False, False, False, "nothing moves; the camera jitters by at most 1 mm"
    ),
}


@dataclass
class Trajectory:
    """Per-frame poses of one sequence.

    Attributes
    ----------
    T_world_from_object : ndarray, shape (N, 4, 4)
    joint_positions : ndarray, shape (N, J) or None
        Per frame, the position of each joint (radians for revolute, metres for prismatic
        joints), in the order of ``ObjectSpec.joints``; ``None`` for rigid objects.
    T_camera_from_world : ndarray, shape (N, 4, 4)
    """

    T_world_from_object: np.ndarray
    joint_positions: np.ndarray | None
    T_camera_from_world: np.ndarray

    @property
    def T_camera_from_object(self) -> np.ndarray:
        """Object base pose in the camera frame, shape (N, 4, 4)."""
        return self.T_camera_from_world @ self.T_world_from_object


def ease_in_out(u: np.ndarray) -> np.ndarray:
    """Smoothstep 3u^2 - 2u^3 of ``u`` clipped to [0, 1] (zero speed at both ends)."""
    u = np.clip(np.asarray(u, dtype=float), 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def look_at(eye_m, target_m, *, roll_rad: float = 0.0) -> np.ndarray:
    """``T_camera_from_world`` of an OpenCV camera at ``eye_m`` looking at ``target_m`` (z up)."""
    eye = np.asarray(eye_m, dtype=float)
    fwd = np.asarray(target_m, dtype=float) - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to world up")
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    R_wc = np.stack([right, down, fwd], axis=1)
    R_wc = R_wc @ rotation_about_axis((0, 0, 1), roll_rad)
    T = np.eye(4)
    T[:3, :3] = R_wc.T
    T[:3, 3] = -R_wc.T @ eye
    return T


def _pose(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _joint_schedules(spec: ObjectSpec, n: int, rng: np.random.Generator, moving: bool):
    """Positions of every joint, shape (n, J), or None for rigid objects; each joint gets its own
    start, travel and timing."""
    if not spec.joints:
        return None
    return np.stack([_joint_schedule(j, n, rng, moving) for j in spec.joints], axis=1)


def _joint_schedule(j, n: int, rng: np.random.Generator, moving: bool) -> np.ndarray:
    q0 = rng.uniform(*j.rest)
    travel = rng.uniform(*j.travel)
    lo, hi = j.limits
    up_ok, down_ok = q0 + travel <= hi, q0 - travel >= lo
    coin = rng.random()
    if not moving:
        return np.full(n, q0)
    if up_ok and down_ok:
        sign = 1.0 if coin < 0.5 else -1.0
    elif up_ok or down_ok:
        sign = 1.0 if up_ok else -1.0
    else:  # cannot happen with validated joints, but stay within limits
        sign = 1.0 if hi - q0 >= q0 - lo else -1.0
        travel = min(travel, max(hi - q0, q0 - lo))
    t0, t1 = rng.uniform(0.0, 0.15), rng.uniform(0.85, 1.0)
    t = np.linspace(0.0, 1.0, n)
    return q0 + sign * travel * ease_in_out((t - t0) / (t1 - t0))


def _unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def make_trajectory(spec: ObjectSpec, motion: str, *, n_frames: int, rng: np.random.Generator) -> Trajectory:
    """Draw a smooth, realistic trajectory for one sequence.

    Parameters
    ----------
    spec : ObjectSpec
    motion : str
        A key of ``MOTIONS``.
    n_frames : int
        At least 2.
    rng : numpy.random.Generator

    Returns
    -------
    Trajectory
    """
    if motion not in MOTIONS:
        raise ValueError(f"motion={motion!r} is not one of {sorted(MOTIONS)}")
    m = MOTIONS[motion]
    if m.needs_joint and spec.joint is None:
        raise ValueError(f"motion={motion!r} needs an articulated object; {spec.name!r} is rigid")
    if n_frames < 2:
        raise ValueError(f"n_frames={n_frames} must be >= 2")
    n = n_frames
    t = np.linspace(0.0, 1.0, n)

    q = _joint_schedules(spec, n, rng, m.moves_joint)
    yaw0 = math.radians(rng.uniform(-25.0, 25.0))
    T_start = _pose(
        rotation_about_axis((0, 0, 1), yaw0), (rng.uniform(-0.03, 0.03), rng.uniform(-0.05, 0.0), 0.0)
    )
    q_mid = None if q is None else q[n // 2]
    pts_mid = object_points_m(spec, q_mid)
    centre_obj = 0.5 * (pts_mid.min(0) + pts_mid.max(0))

    T_wo = np.repeat(T_start[None], n, axis=0)
    carry_extent = 0.0
    if m.moves_object:
        angle = math.radians(rng.uniform(10.0, 40.0))
        axis = _unit([rng.normal(0, 0.6), rng.normal(0, 0.6), 1.0])
        if rng.random() < 0.5:
            axis = -axis
        direction = _unit(rng.normal(size=3) * [1.0, 0.6, 0.5])
        dist = rng.uniform(0.05, 0.15)
        bow_dir = _unit(np.cross(direction, _unit(rng.normal(size=3))))
        bow = rng.uniform(-0.025, 0.025)
        t0, t1 = rng.uniform(0.0, 0.1), rng.uniform(0.9, 1.0)
        s = ease_in_out((t - t0) / (t1 - t0))
        # Hand tremor: a smooth wobble of ~1.5 mm and ~0.3 degrees.
        wob_f = rng.uniform(1.0, 2.5, size=3)
        wob_ph = rng.uniform(0, 2 * math.pi, size=3)
        wob_ax = _unit(rng.normal(size=3))
        for i in range(n):
            R = rotation_about_axis(axis, angle * s[i])
            wob = 0.0015 * np.sin(2 * math.pi * wob_f * t[i] + wob_ph)
            R = R @ rotation_about_axis(
                wob_ax, math.radians(0.3) * math.sin(2 * math.pi * wob_f[0] * t[i] + wob_ph[1])
            )
            # Rotate about the object's centre, then translate along a slightly bowed path.
            T_rot = _pose(R, centre_obj - R @ centre_obj)
            p = direction * dist * s[i] + bow_dir * bow * 4 * s[i] * (1 - s[i]) + wob
            T_wo[i] = _pose(np.eye(3), p) @ T_start @ T_rot
        # Lift the whole trajectory so that the object clears the table in every frame.
        clearance = rng.uniform(0.02, 0.08)
        min_z = math.inf
        for i in range(n):
            pts = object_points_m(spec, None if q is None else q[i])
            min_z = min(min_z, float(np.min(pts @ T_wo[i, 2, :3] + T_wo[i, 2, 3])))
        T_wo[:, 2, 3] += clearance - min_z
        carry_extent = dist

    # Camera: aimed at the mean object centre, 0.6-1.2 m away, looking slightly down.
    centres = np.array([T_wo[i, :3, :3] @ centre_obj + T_wo[i, :3, 3] for i in range(n)])
    target = centres.mean(0)
    extent = object_extent_m(spec) + carry_extent
    distance = float(np.clip(extent / 0.36 * rng.uniform(0.95, 1.2), 0.6, 1.2))
    elev = math.radians(rng.uniform(20.0, 42.0))
    azim = math.radians(rng.uniform(-35.0, 35.0))
    eye = target + distance * np.array(
        [math.cos(elev) * math.sin(azim), -math.cos(elev) * math.cos(azim), math.sin(elev)]
    )
    T_cw = look_at(eye, target, roll_rad=math.radians(rng.uniform(-3.0, 3.0)))
    T_cw_all = np.repeat(T_cw[None], n, axis=0)
    if motion == "static":
        # Tripod jitter: sub-millimetre camera translation, at most 1 mm.
        for i in range(1, n):
            d = rng.normal(0.0, 0.0003, size=3)
            norm = np.linalg.norm(d)
            if norm > 0.001:
                d *= 0.001 / norm
            T_cw_all[i, :3, 3] += d
    return Trajectory(T_wo, q, T_cw_all)
