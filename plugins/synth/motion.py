"""Motion kinds and per-sequence trajectories (object pose, joint position, camera pose)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .objects import ObjectSpec, object_extent_m, object_points_m, rotation_about_axis

__all__ = [
    "MAX_TURN_DEG_PER_FRAME",
    "MOTIONS",
    "MotionSpec",
    "Trajectory",
    "draw_motion_style",
    "ease_in_out",
    "look_at",
    "make_trajectory",
]


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
    needs_tag : str or None
        Only for objects with this tag (``ObjectSpec.tags``).
    """

    name: str
    label: str
    moves_joint: bool
    moves_object: bool
    needs_joint: bool
    description: str
    needs_tag: str | None = None


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
    "spin": MotionSpec(
        "spin",
        "rigid",
        False,
        True,
        False,
        "a body of revolution turns about its own axis, standing on the table or in the air",
        needs_tag="revolution",
    ),
    "slide": MotionSpec(
        "slide",
        "rigid",
        False,
        True,
        False,
        "a flat object slides along the table, turning about its normal",
        needs_tag="flat",
    ),
    "lift": MotionSpec(
        "lift",
        "rigid",
        False,
        True,
        False,
        "the object is lifted off a stand, which stays on the table, and carried",
    ),
}
#: The motions of the first generator versions, drawn by ``make_trajectory`` as they always were.
FIXED_MOTIONS = ("articulate", "carry_articulate", "carry", "static")


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


def make_trajectory(
    spec: ObjectSpec,
    motion: str,
    *,
    n_frames: int,
    rng: np.random.Generator,
    style: dict | None = None,
    pivot: np.ndarray | None = None,
    stand_height_m: float = 0.0,
) -> Trajectory:
    """Draw a smooth, realistic trajectory for one sequence.

    Parameters
    ----------
    spec : ObjectSpec
    motion : str
        A key of ``MOTIONS``.
    n_frames : int
        At least 2.
    rng : numpy.random.Generator
    style : dict, optional
        Speeds and timings from ``draw_motion_style``. Without it, the first four motions are drawn
        as the first generator versions drew them (10-40 degree carries over the whole sequence, one
        way joints) and the others take a style drawn from ``rng``.
    pivot : ndarray, shape (4, 4), optional
        ``T_object_from_holder`` of the hand or gripper that holds the base: a flip turns the object
        about its forearm (the approach axis through the grasp point), as a wrist turns.
    stand_height_m : float
        The object starts on a stand of this height (``lift``).

    Returns
    -------
    Trajectory
    """
    if motion not in MOTIONS:
        raise ValueError(f"motion={motion!r} is not one of {sorted(MOTIONS)}")
    m = MOTIONS[motion]
    if m.needs_joint and spec.joint is None:
        raise ValueError(f"motion={motion!r} needs an articulated object; {spec.name!r} is rigid")
    if m.needs_tag and m.needs_tag not in spec.tags:
        raise ValueError(f"motion={motion!r} needs a {m.needs_tag} object; {spec.name!r} is not one")
    if n_frames < 2:
        raise ValueError(f"n_frames={n_frames} must be >= 2")
    if style is not None or motion not in FIXED_MOTIONS:
        if style is None:
            style = draw_motion_style(motion, n_frames, rng)
        return _styled_trajectory(spec, motion, n_frames, rng, style, pivot, stand_height_m)
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
        min_z = min(_lowest_z(spec, None if q is None else q[i], T_wo[i]) for i in range(n))
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


# ---------------------------------------------------------------- randomised speeds and motions

#: The fastest mean turn of a sequence: a 180-degree flip within 12 frames (0.4 s at 30 frames/s).
MAX_TURN_DEG_PER_FRAME = 15.0
#: Shares of carries that flip the object (90-180 degrees), of joints that go out and back (open,
#: then close), of spins in the air rather than on the table.
FLIP_P = 0.35
OUT_AND_BACK_P = 0.35
SPIN_IN_AIR_P = 0.4


def _window(rng: np.random.Generator, n: int, frac: tuple[float, float], min_frames: float) -> dict:
    """A motion's start frame and length in frame intervals: ``frac`` of the sequence, at least
    ``min_frames``, within it."""
    frames = int(np.clip(round(rng.uniform(*frac) * (n - 1)), max(1, math.ceil(min_frames)), n - 1))
    return {"start": int(rng.integers(0, n - frames)), "frames": frames}


def _turn(angle_deg: float, n: int) -> float:
    """``angle_deg`` within what ``MAX_TURN_DEG_PER_FRAME`` allows over ``n`` frames (sign kept)."""
    top = MAX_TURN_DEG_PER_FRAME * (n - 1)
    return float(np.clip(angle_deg, -top, top))


def draw_motion_style(motion: str, n_frames: int, rng: np.random.Generator, *, held: bool = False) -> dict:
    """Speeds and timings of a motion, drawn (``truth.json`` keeps them as ``motion_style``).

    Every rotation is at most ``MAX_TURN_DEG_PER_FRAME`` on average over its window, so the fastest
    is a 180-degree flip within 12 frames. ``carry`` (and ``carry_articulate``) turns the object by
    10-60 degrees over most of the sequence, or (``FLIP_P``) flips it by 90-180 degrees within 12-20
    frames; joints move one way or (``OUT_AND_BACK_P``) out and back, over half the sequence or more;
    ``spin`` turns a body of revolution by 45-360 degrees about its axis (at most 180 when a hand
    turns it: a wrist's reach), on the table or in the air tilted by up to 30 degrees; ``slide`` moves
    a flat object 5-25 cm and turns it by up to 90 degrees; ``lift`` raises the object 3-10 cm off
    its stand within 4-8 frames, then carries it 5-20 cm, turning it by up to 45 degrees.

    Parameters
    ----------
    motion : str
        A key of ``MOTIONS``.
    n_frames : int
    rng : numpy.random.Generator
    held : bool
        A hand or gripper holds the object.
    """
    n = n_frames
    style: dict = {}
    if MOTIONS[motion].moves_joint:
        style["joint"] = dict(
            schedule="out_and_back" if rng.random() < OUT_AND_BACK_P else "one_way",
            **_window(rng, n, (0.5, 1.0), 2),
        )
    if motion in ("carry", "carry_articulate"):
        flip = bool(rng.random() < FLIP_P)
        angle = _turn(rng.uniform(90.0, 180.0) if flip else rng.uniform(10.0, 60.0), n)
        frac = (12 / max(n - 1, 1), 20 / max(n - 1, 1)) if flip else (0.6, 1.0)
        window = _window(rng, n, frac, abs(angle) / MAX_TURN_DEG_PER_FRAME)
        style.update(
            flip=flip, angle_deg=angle, distance_m=rng.uniform(0.0, 0.1) if flip else rng.uniform(0.03, 0.2)
        )
        style.update(window)
    elif motion == "spin":
        angle = _turn(rng.uniform(45.0, 180.0 if held else 360.0), n)
        in_air = bool(rng.random() < SPIN_IN_AIR_P)
        style.update(angle_deg=angle, in_air=in_air, tilt_deg=rng.uniform(0.0, 30.0) if in_air else 0.0)
        style.update(_window(rng, n, (0.5, 1.0), angle / MAX_TURN_DEG_PER_FRAME))
    elif motion == "slide":
        angle = _turn(rng.uniform(-90.0, 90.0), n)
        style.update(angle_deg=angle, distance_m=rng.uniform(0.05, 0.25))
        style.update(_window(rng, n, (0.5, 1.0), abs(angle) / MAX_TURN_DEG_PER_FRAME))
    elif motion == "lift":
        start = int(rng.integers(0, max(1, round(0.35 * (n - 1))) + 1))
        lift = int(np.clip(rng.integers(4, 9), 1, max(1, n - 1 - start)))
        angle = _turn(rng.uniform(0.0, 45.0), n)
        style.update(
            start=start,
            lift_frames=lift,
            height_m=rng.uniform(0.03, 0.10),
            angle_deg=angle,
            distance_m=rng.uniform(0.05, 0.2),
        )
    return {k: (round(float(v), 6) if isinstance(v, float | np.floating) else v) for k, v in style.items()}


def _progress(n: int, start: int, frames: int) -> np.ndarray:
    """Eased progress 0 -> 1 from frame ``start`` over ``frames`` intervals, per frame."""
    return ease_in_out((np.arange(n) - start) / max(frames, 1))


def _styled_joint(j, n: int, rng: np.random.Generator, moving: bool, style: dict | None) -> np.ndarray:
    """A joint's positions: its start and travel drawn as ``_joint_schedule`` draws them, moved over
    the style's window, one way or out and back."""
    q0, travel = rng.uniform(*j.rest), rng.uniform(*j.travel)
    if not moving:
        return np.full(n, q0)
    lo, hi = j.limits
    up_ok, down_ok = q0 + travel <= hi, q0 - travel >= lo
    if up_ok and down_ok:
        sign = 1.0 if rng.random() < 0.5 else -1.0
    else:
        sign = 1.0 if up_ok or (not down_ok and hi - q0 >= q0 - lo) else -1.0
        travel = min(travel, max(hi - q0, q0 - lo))
    start, frames = style["start"], style["frames"]
    if style["schedule"] == "out_and_back":
        half = max(frames // 2, 1)
        s = _progress(n, start, half) - _progress(n, start + half, max(frames - half, 1))
    else:
        s = _progress(n, start, frames)
    return q0 + sign * travel * s


def _about(point, axis, angle_rad: float) -> np.ndarray:
    """A turn by ``angle_rad`` about the line through ``point`` along ``axis``, 4x4."""
    R = rotation_about_axis(axis, angle_rad)
    return _pose(R, np.asarray(point, float) - R @ np.asarray(point, float))


def _lowest_z(spec: ObjectSpec, q, T_world_from_object: np.ndarray) -> float:
    pts = object_points_m(spec, q)
    return float(np.min(pts @ T_world_from_object[2, :3] + T_world_from_object[2, 3]))


def _styled_trajectory(
    spec: ObjectSpec,
    motion: str,
    n: int,
    rng: np.random.Generator,
    style: dict,
    pivot: np.ndarray | None,
    stand_height_m: float,
) -> Trajectory:
    m = MOTIONS[motion]
    t = np.linspace(0.0, 1.0, n)
    q = None
    if spec.joints:
        q = np.stack(
            [_styled_joint(j, n, rng, m.moves_joint, style.get("joint")) for j in spec.joints], axis=1
        )
    qs = [None if q is None else q[i] for i in range(n)]
    T_start = _pose(
        rotation_about_axis((0, 0, 1), math.radians(rng.uniform(-50.0, 50.0))),
        (rng.uniform(-0.03, 0.03), rng.uniform(-0.05, 0.0), stand_height_m),
    )
    pts_mid = object_points_m(spec, qs[n // 2])
    centre = 0.5 * (pts_mid.min(0) + pts_mid.max(0))
    T_wo = np.repeat(T_start[None], n, axis=0)
    reach = 0.0
    # Hand tremor: a smooth wobble of ~1.5 mm and ~0.3 degrees while the object is held in the air.
    wob_f, wob_ph, wob_ax = (
        rng.uniform(1.0, 2.5, size=3),
        rng.uniform(0, 2 * math.pi, size=3),
        _unit(rng.normal(size=3)),
    )

    def wobble(i: int) -> np.ndarray:
        R = rotation_about_axis(
            wob_ax, math.radians(0.3) * math.sin(2 * math.pi * wob_f[0] * t[i] + wob_ph[1])
        )
        return _pose(R, 0.0015 * np.sin(2 * math.pi * wob_f * t[i] + wob_ph))

    if motion in ("carry", "carry_articulate"):
        s = _progress(n, style["start"], style["frames"])
        angle = math.radians(style["angle_deg"])
        if style["flip"] and pivot is not None:  # about the forearm: the wrist turns
            axis, point = pivot[:3, 2], pivot[:3, 3]
        else:
            axis, point = _unit([rng.normal(0, 0.6), rng.normal(0, 0.6), 1.0]), centre
            if style["flip"]:
                axis = _unit(rng.normal(size=3))
        direction = _unit(rng.normal(size=3) * [1.0, 0.6, 0.5])
        for i in range(n):
            T_wo[i] = (
                _pose(np.eye(3), direction * style["distance_m"] * s[i])
                @ T_start
                @ _about(point, axis, angle * s[i])
                @ wobble(i)
            )
        T_wo[:, 2, 3] += rng.uniform(0.02, 0.08) - min(_lowest_z(spec, qs[i], T_wo[i]) for i in range(n))
        reach = style["distance_m"]
    elif motion == "spin":
        s = _progress(n, style["start"], style["frames"])
        spin = [_about((0, 0, 0), (0, 0, 1), math.radians(style["angle_deg"]) * s[i]) for i in range(n)]
        if style["in_air"]:
            tilt = _about(centre, _unit([rng.normal(), rng.normal(), 0.0]), math.radians(style["tilt_deg"]))
            drift = _unit(rng.normal(size=3)) * rng.uniform(0.0, 0.05)
            for i in range(n):
                T_wo[i] = _pose(np.eye(3), drift * s[i]) @ T_start @ tilt @ spin[i] @ wobble(i)
            T_wo[:, 2, 3] += rng.uniform(0.02, 0.08) - min(_lowest_z(spec, qs[i], T_wo[i]) for i in range(n))
        else:
            T_wo = np.stack([T_start @ S for S in spin])
    elif motion == "slide":
        s = _progress(n, style["start"], style["frames"])
        direction = np.r_[_unit(rng.normal(size=2)), 0.0]
        point = np.array([centre[0], centre[1], 0.0])
        for i in range(n):
            turn = _about(point, (0, 0, 1), math.radians(style["angle_deg"]) * s[i])
            T_wo[i] = _pose(np.eye(3), direction * style["distance_m"] * s[i]) @ T_start @ turn
        reach = style["distance_m"]
    elif motion == "lift":
        up = _progress(n, style["start"], style["lift_frames"])
        end = style["start"] + style["lift_frames"]
        away = _progress(n, end, max(n - 1 - end, 1))
        axis = _unit([rng.normal(0, 0.6), rng.normal(0, 0.6), 1.0])
        direction = _unit(rng.normal(size=3) * [1.0, 0.6, 0.3] + [0.0, 0.0, 0.3])
        for i in range(n):
            turn = _about(centre, axis, math.radians(style["angle_deg"]) * away[i])
            shift = (
                np.array([0.0, 0.0, style["height_m"] * up[i]]) + direction * style["distance_m"] * away[i]
            )
            T_wo[i] = _pose(np.eye(3), shift) @ T_start @ turn @ (wobble(i) if up[i] > 0 else np.eye(4))
        # Once lifted, the object clears its stand by at least 1 cm (raise the lift where a turn would
        # dip it); before the lift it stands on it exactly.
        lifted = [i for i in range(n) if up[i] >= 1.0]
        need = max([stand_height_m + 0.01 - _lowest_z(spec, qs[i], T_wo[i]) for i in lifted] + [0.0])
        T_wo[:, 2, 3] += need * up
        reach = style["distance_m"]
    elif m.moves_object:
        raise ValueError(f"motion={motion!r} has no styled trajectory")

    centres = np.array([T_wo[i, :3, :3] @ centre + T_wo[i, :3, 3] for i in range(n)])
    target = centres.mean(0)
    distance = float(np.clip((object_extent_m(spec) + reach) / 0.36 * rng.uniform(0.85, 1.35), 0.5, 1.4))
    elev, azim = math.radians(rng.uniform(18.0, 55.0)), math.radians(rng.uniform(-45.0, 45.0))
    eye = target + distance * np.array(
        [math.cos(elev) * math.sin(azim), -math.cos(elev) * math.cos(azim), math.sin(elev)]
    )
    T_cw = np.repeat(look_at(eye, target, roll_rad=math.radians(rng.uniform(-5.0, 5.0)))[None], n, axis=0)
    if motion == "static":  # tripod jitter, at most 1 mm
        for i in range(1, n):
            d = rng.normal(0.0, 0.0003, size=3)
            T_cw[i, :3, 3] += d * min(1.0, 0.001 / max(float(np.linalg.norm(d)), 1e-12))
    return Trajectory(T_wo, q, T_cw)
