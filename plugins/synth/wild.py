"""Randomised scenes (the ``benchmark-wild`` preset): everything a sequence's seed draws beyond its
object and motion.

From the seed, per sequence: the depth sensor (structured light with a bias field, or time of
flight) and its parameters, the camera (rendered intrinsics, the intrinsics stated for it, the
colour-depth offset), the lighting, the surface (textured or plain, and one in four objects dark),
the speeds and timings of the motion (``draw_motion_style``), and who handles the object: nobody,
one or two hands (skin, sleeve, glove, size, finger curl, wrist bend) or robot grippers of any
colour, grasping, resting on a still object, or passing in front of it or close to the camera.

Random streams: ``default_rng([seed, 10])`` draws the scene, ``[seed, 3]`` the limbs and where they
hold, ``[seed, 0]`` the trajectory and ``[seed, 1, i]`` frame i's noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .hands import (
    Holder,
    arm_poses,
    colour_boxes,
    grasp_pose,
    gripper_limb,
    hand_limb,
    mirrored,
    top_pose,
    wave_path,
)
from .motion import Trajectory, draw_motion_style, make_trajectory
from .objects import ObjectSpec, object_points_m, part_poses, stand_pieces
from .render import PROP, place_pieces
from .sensors import SENSOR_KINDS, CameraDraw, draw_camera, draw_sensor

__all__ = ["DRAWN", "SceneDraw", "WildPlan", "draw_scene", "plan_wild"]

#: The value of ``noise``, ``hand`` or ``texture`` that leaves the choice to the seed.
DRAWN = "drawn"
#: Random stream of the scene draw.
SCENE_STREAM = 10
#: Who handles the object, and how often.
HOLDER_P = {"none": 0.25, "hand": 0.5, "gripper": 0.25}
#: Share of handled sequences with a second hand, where the motion has room for one.
TWO_HANDS_P = 0.3
#: A still object's holders: passing in front, passing close to the camera, resting on it, or one
#: resting while the other passes; and how often.
STATIC_ROLES = {("pass",): 0.35, ("pass_close",): 0.25, ("rest",): 0.25, ("rest", "pass"): 0.15}
#: Shares of plain (untextured) objects and of dark ones (their colours scaled by 0.12-0.35).
PLAIN_P = 1 / 3
DARK_P = 0.25
#: A hand passing close to the camera is this far from it, metres.
CLOSE_PASS_M = (0.15, 0.3)


@dataclass(frozen=True)
class SceneDraw:
    """What a randomised sequence's seed drew besides the trajectory and the limbs.

    Attributes
    ----------
    sensor : StructuredLight or TimeOfFlight
    camera : CameraDraw
    texture : {"textured", "plain"}
    albedo_scale : float
        The object's colours times this (1, or 0.12-0.35 for a dark object).
    ambient : float
    light_dir_camera : tuple of 3 floats
    holder_kind : {"none", "hand", "gripper"}
    roles : tuple of (role, target)
        Per holder: ``grasp`` with target ``part`` (the last part), ``base``, ``base_other`` (the
        base's other side), ``twist`` or ``flat`` (from above); ``rest``, ``pass`` or ``pass_close``.
    motion_style : dict
        From ``draw_motion_style``.
    stand : dict or None
        ``colour``, ``height_m``, ``margin_m`` of the stand a ``lift`` starts on.
    """

    sensor: object
    camera: CameraDraw
    texture: str
    albedo_scale: float
    ambient: float
    light_dir_camera: tuple
    holder_kind: str
    roles: tuple
    motion_style: dict
    stand: dict | None

    def record(self) -> dict:
        """The scene's part of ``truth.json`` (``scene``)."""
        return {
            "texture": self.texture,
            "albedo_scale": round(self.albedo_scale, 4),
            "ambient": round(self.ambient, 4),
            "light_dir_camera": [round(v, 4) for v in self.light_dir_camera],
            "holder_kind": self.holder_kind,
            "roles": [list(r) for r in self.roles],
        }


def _pick(rng: np.random.Generator, options: dict):
    keys = list(options)
    return keys[int(rng.choice(len(keys), p=list(options.values())))]


def _roles(motion: str, kind: str, rng: np.random.Generator) -> tuple:
    two = kind == "hand" and rng.random() < TWO_HANDS_P
    static = _pick(rng, STATIC_ROLES)
    if kind == "none":
        return ()
    if motion == "articulate":
        return (("grasp", "part"),) + ((("grasp", "base"),) if two else ())
    if motion == "carry_articulate":
        return (("grasp", "part"), ("grasp", "base"))
    if motion in ("carry", "lift"):
        return (("grasp", "base"),) + ((("grasp", "base_other"),) if two else ())
    if motion == "spin":
        return (("grasp", "twist"),)
    if motion == "slide":
        return (("grasp", "flat" if kind == "hand" else "twist"),)
    if kind == "gripper" and len(static) > 1:
        static = ("pass",)
    return tuple((role, "top" if role == "rest" else "none") for role in static)


def draw_scene(
    *,
    spec: ObjectSpec,
    motion: str,
    n_frames: int,
    width: int,
    height: int,
    rng: np.random.Generator,
    noise: str = DRAWN,
    hand: str = DRAWN,
    texture: str = DRAWN,
) -> SceneDraw:
    """Draw a randomised sequence's scene (see the module docstring); ``noise`` (a sensor kind),
    ``hand`` (a holder kind) and ``texture`` fix what they name instead of drawing it."""
    camera = draw_camera(width, height, rng)
    kind = str(rng.choice(SENSOR_KINDS))
    sensor = draw_sensor(kind if noise == DRAWN else noise, rng, intrinsics=camera.rendered)
    plain = rng.random() < PLAIN_P
    dark = rng.random() < DARK_P
    albedo = float(rng.uniform(0.12, 0.35)) if dark else 1.0
    ambient = float(rng.uniform(0.2, 0.5))
    light = (float(rng.uniform(-0.8, 0.8)), float(rng.uniform(-0.9, 0.3)), -1.0)
    holder = _pick(rng, HOLDER_P)
    holder = holder if hand == DRAWN else hand
    roles = _roles(motion, holder, rng)
    style = draw_motion_style(motion, n_frames, rng, held=bool(roles))
    stand = None
    if motion == "lift" or spec.name == "kettle":  # a kettle always stands on its power base
        stand = {
            "colour": [round(float(c), 4) for c in rng.uniform(0.05, 0.6) * np.ones(3)],
            "height_m": round(float(rng.uniform(0.008, 0.025)), 4),
            "margin_m": round(float(rng.uniform(0.005, 0.03)), 4),
        }
    return SceneDraw(
        sensor,
        camera,
        ("plain" if plain else "textured") if texture == DRAWN else texture,
        albedo,
        ambient,
        light,
        holder,
        roles,
        style,
        stand,
    )


@dataclass
class WildPlan:
    """A randomised sequence's draw beyond its scene: the trajectory, the holders and the props."""

    trajectory: Trajectory
    holders: list
    props: list
    gripper_hsv: list


def _limb(kind: str, rng: np.random.Generator, first=None, *, flat: bool = False):
    """A holder's limb; a person's second hand mirrors the first, and a hand lying flat on the
    object barely curls its fingers."""
    if kind == "hand":
        return (
            hand_limb(rng, curl_deg=(0.0, 15.0) if flat else (0.0, 60.0))
            if first is None
            else mirrored(first)
        )
    return gripper_limb(rng)


def _tremor(n: int, rng: np.random.Generator, amplitude_m: float = 0.001) -> np.ndarray:
    """Small smooth translations of a resting hand, shape (n, 4, 4)."""
    t = np.linspace(0.0, 1.0, n)
    f, ph = rng.uniform(1.0, 3.0, size=3), rng.uniform(0.0, 2 * np.pi, size=3)
    out = np.repeat(np.eye(4)[None], n, axis=0)
    out[:, :3, 3] = amplitude_m * np.sin(2 * np.pi * f * t[:, None] + ph)
    return out


def plan_wild(spec: ObjectSpec, motion: str, n: int, seed: int, scene: SceneDraw) -> WildPlan:
    """The trajectory, holders and props of a randomised sequence whose scene is ``scene``."""
    rng = np.random.default_rng([seed, 3])
    kind = scene.holder_kind
    limbs, first = [], None
    for role, target in scene.roles:
        limbs.append(_limb(kind, rng, first, flat=role == "rest" or target == "flat"))
        first = limbs[0]  # a gripper's limb ignores it
    # Where the base is held, chosen before the trajectory: a flip turns the object about that forearm.
    side = 1.0 if rng.random() < 0.5 else -1.0
    base_points = object_points_m(spec, spec.rest_positions()) if len(spec.parts) == 1 else None
    held: dict[int, np.ndarray] = {}
    for k, (_, target) in enumerate(scene.roles):
        if target in ("base", "base_other"):
            held[k] = grasp_pose(spec, 0, None, rng, side=side if target == "base" else -side)
        elif target in ("twist", "flat"):
            held[k] = top_pose(base_points, rng, mode=target)
    pivot = next((held[k] for k, (_, t) in enumerate(scene.roles) if t in ("base", "base_other")), None)
    stand_h = scene.stand["height_m"] if scene.stand else 0.0
    traj = make_trajectory(
        spec,
        motion,
        n_frames=n,
        rng=np.random.default_rng([seed, 0]),
        style=scene.motion_style,
        pivot=pivot,
        stand_height_m=stand_h,
    )
    q = traj.joint_positions
    q0 = None if q is None else q[0]
    T_wo = traj.T_world_from_object
    T_wc = np.linalg.inv(traj.T_camera_from_world[0])
    eye = T_wc[:3, 3]
    holders = []
    for k, ((role, target), limb) in enumerate(zip(scene.roles, limbs)):
        part = 0
        if target == "part":
            part = len(spec.parts) - 1
            held[k] = grasp_pose(spec, part, q0, rng)
        if role == "grasp":
            poses = np.stack(
                [T_wo[f] @ part_poses(spec, None if q is None else q[f])[part] @ held[k] for f in range(n)]
            )
        elif role == "rest":  # on the base's top
            base = np.concatenate([p.vertices_m for p in spec.parts[0].pieces])
            T_top = top_pose(base, rng, mode="flat" if kind == "hand" else "twist")
            poses = np.stack([T_wo[f] @ T_top for f in range(n)]) @ _tremor(n, rng)
        else:
            pts = object_points_m(spec, q0)
            centre_obj = 0.5 * (pts.min(0) + pts.max(0))
            centre = T_wo[0][:3, :3] @ centre_obj + T_wo[0][:3, 3]
            radius = 0.5 * float(np.linalg.norm(pts.max(0) - pts.min(0)))
            close = rng.uniform(*CLOSE_PASS_M) if role == "pass_close" else None
            poses = wave_path(
                centre, T_wc[:3, 3], T_wc[:3, 0], n, rng, clearance_m=radius + 0.12, eye_distance_m=close
            )
            part = None
        # A robot's wrist holds still (the arm only turns away from the table and the camera); a hand
        # lying flat barely bends, and turns at the wrist as it slides the object round.
        flat = role == "rest" or target == "flat"
        bend, sway = (0.0, 0.0) if kind == "gripper" else (10.0, 5.0) if flat else (30.0, 20.0)
        T_ha = arm_poses(
            limb, poses, rng, bend_deg=bend, sway_deg=sway, follow=target != "flat", eye_world=eye
        )
        holders.append(
            Holder(kind, limb.hand, poses, part, limb.arm, T_ha, role, dict(limb.style, target=target))
        )
    props = []
    if scene.stand is not None:
        pieces = stand_pieces(
            spec,
            tuple(scene.stand["colour"]),
            height_m=scene.stand["height_m"],
            margin_m=scene.stand["margin_m"],
        )
        # On the table under the object's first pose, turned as the object is about the vertical.
        x = T_wo[0][:2, 0] / max(float(np.linalg.norm(T_wo[0][:2, 0])), 1e-9)
        T_stand = np.eye(4)
        T_stand[:2, :2] = [[x[0], -x[1]], [x[1], x[0]]]
        T_stand[:2, 3] = T_wo[0][:2, 3]
        props = place_pieces(pieces, T_stand, PROP)
    rgb_sigma = getattr(scene.sensor, "rgb_sigma", None)
    rgb_sigma = scene.sensor.level.rgb_sigma if rgb_sigma is None else rgb_sigma
    boxes = []
    if kind == "gripper":
        for limb in limbs:
            boxes += colour_boxes(limb, rgb_sigma=rgb_sigma, ambient=scene.ambient)
    return WildPlan(traj, holders, props, list(dict.fromkeys(boxes)))


def check_wild_arguments(*, noise: str, hand: str, texture: str, hands: tuple, textures: tuple) -> None:
    """Raise ValueError for a value a randomised sequence cannot take."""
    for name, value, allowed in (
        ("noise", noise, (DRAWN,) + SENSOR_KINDS),
        ("hand", hand, (DRAWN,) + hands),
        ("texture", texture, (DRAWN,) + textures),
    ):
        if value not in allowed:
            raise ValueError(f"{name}={value!r} is not one of {allowed} (a randomised sequence)")
