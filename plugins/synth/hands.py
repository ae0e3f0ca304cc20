"""Hands and grippers that handle the object: meshes, colours and where they hold.

A holder (a human hand with its forearm, or a two-finger robot gripper on its
arm) is built from mesh primitives in its own *holder frame*: metres, the
origin at the grasp point, +z the approach direction (into the held surface),
the forearm or arm along -z, the pinch (thumb to fingers) along y. It is
rendered as ``HAND`` pixels: it hides the object but is never part of its
mask.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from .objects import ObjectSpec, Piece, box, cylinder, part_poses, rotation_about_axis, sphere
from .render import AMBIENT

__all__ = [
    "HOLDER_KINDS",
    "Holder",
    "SKIN_TONES",
    "Limb",
    "arm_poses",
    "colour_box",
    "colour_boxes",
    "grasp_pose",
    "gripper_limb",
    "hand_limb",
    "holder_pieces",
    "mirrored",
    "top_pose",
    "wave_path",
]

#: Kinds of holder.
HOLDER_KINDS = ("hand", "gripper")

#: Linear RGB-ish skin colours in [0, 1], from light to dark, spanning the range of human skin
#: reflectance (roughly the Fitzpatrick types I to VI under white light); a hand's colour is drawn
#: between two neighbours.
SKIN_TONES = (
    (0.96, 0.84, 0.74),
    (0.92, 0.74, 0.60),
    (0.80, 0.60, 0.46),
    (0.64, 0.45, 0.32),
    (0.45, 0.30, 0.21),
    (0.28, 0.19, 0.14),
)
_SLEEVES = (
    (0.15, 0.20, 0.45),
    (0.55, 0.10, 0.12),
    (0.20, 0.40, 0.25),
    (0.30, 0.30, 0.32),
    (0.85, 0.85, 0.82),
    (0.60, 0.50, 0.35),
)
#: Length of the sleeve from the wrist end of the forearm to the shoulder, and of the robot arm behind
#: the gripper, metres: a real arm reaches out of the picture, it never ends in mid-air.
SLEEVE_M = 1.2
ROBOT_ARM_M = 1.2
_GRIPPER_COLOURS = ((0.55, 0.56, 0.58), (0.12, 0.12, 0.13))


def skin_colour(rng: np.random.Generator) -> tuple[float, float, float]:
    """A skin colour drawn uniformly along ``SKIN_TONES``."""
    t = rng.uniform(0.0, len(SKIN_TONES) - 1.0)
    k = min(int(t), len(SKIN_TONES) - 2)
    a, b = np.asarray(SKIN_TONES[k]), np.asarray(SKIN_TONES[k + 1])
    return tuple(float(c) for c in a + (t - k) * (b - a))


def holder_pieces(kind: str, rng: np.random.Generator) -> tuple[Piece, ...]:
    """The meshes of a hand (palm, four fingers, thumb, forearm, sleeve) or of a two-finger
    gripper (body, two fingers, arm), in the holder frame.

    Parameters
    ----------
    kind : {"hand", "gripper"}
    rng : numpy.random.Generator
        Draws the skin, sleeve or gripper colour and the hand's size (palm 7.5-9 cm wide).
    """
    if kind == "hand":
        skin = skin_colour(rng)
        sleeve = _SLEEVES[int(rng.integers(len(_SLEEVES)))]
        s = rng.uniform(0.9, 1.05)  # hand size
        kw = dict(pattern="blobs", cell_m=0.02, contrast=0.06)
        pieces = [box((0.085 * s, 0.03 * s, 0.09 * s), (0.0, 0.0, -0.065 * s), skin, **kw)]
        for f in range(4):  # fingers on the +y side of the held edge
            x = (-0.03 + 0.02 * f) * s
            pieces.append(
                cylinder(0.0085 * s, 0.065 * s, (x, 0.02 * s, -0.005 * s), skin, resolution=8, **kw)
            )
            pieces.append(sphere(0.0085 * s, (x, 0.02 * s, 0.0275 * s), skin, resolution=6, **kw))
        pieces.append(
            cylinder(0.0095 * s, 0.055 * s, (0.025 * s, -0.02 * s, -0.01 * s), skin, resolution=8, **kw)
        )  # thumb on the -y side
        pieces.append(
            cylinder(0.028 * s, 0.16, (0.0, 0.0, -0.11 * s - 0.08), skin, resolution=12, **kw)
        )  # forearm
        pieces.append(
            cylinder(
                0.04,
                SLEEVE_M,
                (0.0, 0.0, -0.11 * s - 0.15 - SLEEVE_M / 2),
                sleeve,
                resolution=12,
                pattern="stripes",
                cell_m=0.03,
                contrast=0.15,
            )
        )
        return tuple(pieces)
    if kind == "gripper":
        colour = _GRIPPER_COLOURS[int(rng.integers(len(_GRIPPER_COLOURS)))]
        dark = tuple(0.6 * c for c in colour)
        return (
            box((0.09, 0.05, 0.06), (0.0, 0.0, -0.06), colour, pattern="plain"),
            box((0.02, 0.012, 0.05), (0.0, 0.018, -0.01), dark, pattern="plain"),
            box((0.02, 0.012, 0.05), (0.0, -0.018, -0.01), dark, pattern="plain"),
            cylinder(
                0.035,
                ROBOT_ARM_M,
                (0.0, 0.0, -0.09 - ROBOT_ARM_M / 2),
                colour,
                resolution=16,
                pattern="stripes",
                cell_m=0.05,
                contrast=0.1,
            ),
        )
    raise ValueError(f"kind={kind!r} is not one of {HOLDER_KINDS}")


# A colour box holds the noisy colours within this many noise sigmas of the noise-free ones.
_BOX_SIGMAS = 3.0


def colour_box(pieces, *, rgb_sigma: float, ambient: float = AMBIENT) -> str:
    """The HSV box, ``"h0,s0,v0,h1,s1,v1"`` in OpenCV units (H 0-180, S and V 0-255), that holds the
    colours the camera sees on ``pieces`` (a robot's gripper: what its owner measures once and writes
    into the rig's settings).

    The box spans both colours of every piece's pattern, lit from the ambient share alone (a face
    turned from the light) to full light, widened by ``_BOX_SIGMAS`` colour-noise sigmas. Hue is
    left open (0-180) when the colours are too grey for the noise to leave it defined.

    Parameters
    ----------
    pieces : sequence of Piece
    rgb_sigma : float
        Colour noise, 8-bit levels.
    ambient : float
        Ambient share of the lighting, as rendered.
    """
    colours = np.array([c for p in pieces for c in (p.colour, p.colour2)], dtype=float)
    rgb = np.concatenate([colours * ambient, colours]) * 255.0
    hsv = cv2.cvtColor(np.clip(np.rint(rgb), 0, 255).astype(np.uint8)[None], cv2.COLOR_RGB2HSV)[0]
    pad = _BOX_SIGMAS * rgb_sigma
    top, bottom = rgb.max(1), rgb.min(1)
    # saturation (max - min) / max, the difference of two channels' independent noises being
    # sqrt(2) times as wide as one's
    spread = math.sqrt(2.0) * pad
    sat = 255.0 * np.minimum((top - bottom + spread) / np.maximum(top, 1.0), 1.0)
    grey = bool(np.any(top - bottom < spread))
    h0, h1 = (0, 180) if grey else (int(hsv[:, 0].min()), int(hsv[:, 0].max()))
    v0, v1 = max(int(np.floor(top.min() - pad)), 0), min(int(np.ceil(top.max() + pad)), 255)
    return f"{h0},0,{v0},{h1},{int(np.ceil(sat.max()))},{v1}"


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def _frame(origin, approach) -> np.ndarray:
    """A holder pose with ``approach`` as +z and x horizontal where possible."""
    z = _unit(approach)
    x = np.cross([0.0, 0.0, 1.0], z)
    x = _unit(x) if np.linalg.norm(x) > 1e-6 else np.array([1.0, 0.0, 0.0])
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = origin
    return T


def grasp_pose(
    spec: ObjectSpec, part: int, q0, rng: np.random.Generator, *, side: float | None = None
) -> np.ndarray:
    """Where a holder grasps ``part`` of ``spec``: ``T_part_from_holder``, shape (4, 4).

    The grasp point is a vertex of the part as far as possible from what it turns about or
    slides along (the free edge of a lid, the knob end of a drawer; for the base, one side),
    preferring the front (-y, the side the camera sees) and drawn at random among the candidates.
    The holder approaches it from outside the part, its forearm rising away from the object.

    Parameters
    ----------
    spec : ObjectSpec
    part : int
        Part index.
    q0 : array_like or None
        Joint positions when the grasp is chosen (the first frame).
    rng : numpy.random.Generator
    side : {1.0, -1.0}, optional
        For the base: hold it at its +x (1) or -x (-1) side rather than a side drawn at random.
    """
    T_op = part_poses(spec, q0)[part]
    local = np.concatenate([p.vertices_m for p in spec.parts[part].pieces])
    pts = local @ T_op[:3, :3].T + T_op[:3, 3]
    if part == 0:  # held at its left or right side
        centre = 0.5 * (pts.min(0) + pts.max(0))
        coin = 1.0 if rng.random() < 0.5 else -1.0
        score = (pts[:, 0] - centre[0]) * (coin if side is None else side)
    else:
        joint = spec.joints[part - 1]
        T_parent = part_poses(spec, q0)[joint.parent]
        axis = T_parent[:3, :3] @ _unit(joint.axis)
        if joint.joint_type == "prismatic":
            score = pts @ axis
        else:
            off = pts - (T_parent[:3, :3] @ np.asarray(joint.origin_m) + T_parent[:3, 3])
            score = np.linalg.norm(off - np.outer(off @ axis, axis), axis=1)
    lo, hi = score.min(), score.max()
    candidates = np.flatnonzero(score >= hi - 0.15 * (hi - lo))
    pick = candidates[np.argmin(pts[candidates, 1] + rng.uniform(0.0, 0.04, len(candidates)))]
    centroid = pts.mean(0)
    outward = pts[pick] - centroid
    outward[2] = max(outward[2], 0.0)  # an arm never reaches up from under the table
    outward = _unit(outward) if np.linalg.norm(outward) > 1e-6 else np.array([0.0, -1.0, 0.0])
    # The forearm (-z) points outward and up, the approach (+z) into the part.
    approach = -_unit(outward + rng.uniform(0.5, 0.9) * np.array([0.0, 0.0, 1.0]))
    T_obj_holder = _frame(pts[pick], approach)
    return np.linalg.inv(T_op) @ T_obj_holder


def wave_path(
    centre_world,
    eye_world,
    right_world,
    n: int,
    rng: np.random.Generator,
    *,
    clearance_m: float,
    eye_distance_m: float | None = None,
) -> np.ndarray:
    """Poses ``T_world_from_holder`` (n, 4, 4) of a hand that moves across in front of an object
    without touching it: between the object and the camera, at least ``clearance_m`` from the
    object's centre, sweeping sideways through the line of sight.

    Parameters
    ----------
    centre_world, eye_world : array_like, shape (3,), metres
        Object centre and camera position.
    right_world : array_like, shape (3,)
        The camera's +x axis in the world.
    n : int
    rng : numpy.random.Generator
    clearance_m : float
        Smallest distance between the hand's grasp point and the object centre.
    eye_distance_m : float, optional
        Pass this far from the camera instead (a hand close to the lens), still at least
        ``clearance_m`` from the object.
    """
    c, eye = np.asarray(centre_world, float), np.asarray(eye_world, float)
    d = eye - c
    dist = float(np.linalg.norm(d))
    frac = max(rng.uniform(0.25, 0.4), min(clearance_m / dist, 0.7))
    if eye_distance_m is not None:
        frac = max(1.0 - eye_distance_m / dist, min(clearance_m / dist, 0.95))
    mid = c + frac * d
    right = _unit(right_world)
    side = 1.0 if rng.random() < 0.5 else -1.0
    sweep = rng.uniform(0.10, 0.18)
    t = np.linspace(0.0, 1.0, n)
    s = t * t * (3.0 - 2.0 * t)
    bob = 0.015 * np.sin(2 * math.pi * rng.uniform(0.5, 1.5) * t + rng.uniform(0, 2 * math.pi))
    out = np.empty((n, 4, 4))
    for i in range(n):
        p = mid + right * side * sweep * (2.0 * s[i] - 1.0) + np.array([0.0, 0.0, bob[i]])
        # The hand points along its motion, the forearm trailing and rising.
        out[i] = _frame(p, _unit(side * right + np.array([0.0, 0.0, -0.4])))
    return out


# ---------------------------------------------------------------- randomised limbs


@dataclass
class Holder:
    """A hand or gripper in a sequence: its meshes and its pose in every frame.

    Attributes
    ----------
    kind : {"hand", "gripper"}
    pieces : tuple of Piece
        Meshes in the holder frame.
    T_world_from_holder : ndarray, shape (N, 4, 4)
    holds : int or None
        The part it holds (or rests on), or None for a hand moving in front of the object.
    arm_pieces : tuple of Piece
        Meshes in the arm frame (a randomised limb's forearm and sleeve, or robot arm); empty when
        ``pieces`` hold the arm.
    T_holder_from_arm : ndarray, shape (N, 4, 4), or None
        The arm frame per frame (the wrist's bend).
    role : {"grasp", "rest", "pass", "pass_close"}
        Holds a part and moves it with it; rests on a still object (touching it); passes in front
        of the object; passes close to the camera.
    style : dict
        What was drawn for a randomised limb (``Limb.style``), for ``truth.json``.
    """

    kind: str
    pieces: tuple
    T_world_from_holder: np.ndarray
    holds: int | None
    arm_pieces: tuple = ()
    T_holder_from_arm: np.ndarray | None = None
    role: str = "grasp"
    style: dict | None = None


#: Length of a limb from the wrist (or a gripper's flange) to where it leaves any picture, metres.
LIMB_M = 1.3
#: Sleeve styles: where the sleeve starts, metres from the wrist along the forearm (times the hand
#: size), or no sleeve (a bare arm); drawn with these probabilities.
SLEEVE_STYLES = {"long": (0.0, 0.03), "pushed_up": (0.06, 0.15), "short": (0.24, 0.32), "none": None}
_SLEEVE_P = (0.4, 0.2, 0.25, 0.15)
#: Share of hands in a glove.
GLOVE_P = 0.2
_PATTERNS = ("plain", "stripes", "checker", "blobs")


def any_colour(rng: np.random.Generator, *, value=(0.05, 0.95)) -> tuple[float, float, float]:
    """A colour of any hue and saturation, its value (brightness) drawn in ``value``: black, white
    and everything between."""
    return tuple(float(c) for c in colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(), rng.uniform(*value)))


def _fabric(rng: np.random.Generator) -> dict:
    """Pattern keywords of a piece of clothing."""
    return dict(
        pattern=_PATTERNS[int(rng.integers(len(_PATTERNS)))],
        cell_m=float(rng.uniform(0.01, 0.05)),
        contrast=float(rng.uniform(0.05, 0.4)),
    )


def _with_vertices(piece: Piece, vertices: np.ndarray) -> Piece:
    return replace(piece, vertices_m=vertices)


def _frustum(r0: float, r1: float, z0: float, z1: float, colour, *, resolution=14, **kw) -> Piece:
    """A closed tapered cylinder along z from ``z0`` (radius ``r0``) to ``z1`` (radius ``r1``)."""
    piece = cylinder(1.0, abs(z1 - z0), (0.0, 0.0, 0.5 * (z0 + z1)), colour, resolution=resolution, **kw)
    v = piece.vertices_m.copy()
    t = (v[:, 2] - z0) / (z1 - z0)
    v[:, :2] *= (r0 + t * (r1 - r0))[:, None]
    return _with_vertices(piece, v)


def _capsule_chain(start, direction, lengths, curls, radius, colour, *, curl_axis=(1.0, 0.0, 0.0), **kw):
    """A finger: segments of ``lengths`` from ``start``, each turned by its ``curls`` angle (radians)
    about ``curl_axis``, with a ball at every joint and at the tip."""
    out, p, d = [], np.asarray(start, float), _unit(direction)
    out.append(sphere(radius, tuple(p), colour, resolution=6, **kw))
    for length, curl in zip(lengths, curls):
        d = rotation_about_axis(curl_axis, curl) @ d
        out.append(
            cylinder(radius, length, tuple(p + 0.5 * length * d), colour, axis=tuple(d), resolution=8, **kw)
        )
        p = p + length * d
        out.append(sphere(radius, tuple(p), colour, resolution=6, **kw))
    return out


@dataclass(frozen=True)
class Limb:
    """A randomised hand with its arm, or a gripper with its robot arm.

    Attributes
    ----------
    hand : tuple of Piece
        In the holder frame (see the module docstring).
    arm : tuple of Piece
        In the arm frame: the origin at the wrist (a gripper's flange), the arm along -z.
    wrist_m : tuple of 3 floats
        The wrist in the holder frame.
    style : dict
        What was drawn (colours, sleeve, glove, size), for ``truth.json``.
    """

    hand: tuple
    arm: tuple
    wrist_m: tuple
    style: dict


def hand_limb(rng: np.random.Generator, *, curl_deg=(0.0, 60.0)) -> Limb:
    """A human hand and arm with everything drawn: size (0.85-1.15 of an adult's), skin tone, rounded
    fingers (balls and cylinders) curled by ``curl_deg`` at each joint, a glove (one in five, any
    colour) and a sleeve of any colour and pattern that starts at the wrist, part-way up the forearm,
    above the elbow or not at all (a bare arm)."""
    s = float(rng.uniform(0.85, 1.15))
    skin = skin_colour(rng)
    glove = any_colour(rng) if rng.random() < GLOVE_P else None
    sleeve_style = list(SLEEVE_STYLES)[int(rng.choice(len(SLEEVE_STYLES), p=_SLEEVE_P))]
    sleeve_colour = any_colour(rng)
    fabric = _fabric(rng)
    hand_colour = glove or skin
    kw = dict(pattern="blobs", cell_m=0.02, contrast=0.06)
    finger_r = float(rng.uniform(0.0075, 0.0095)) * s
    curls = np.radians(rng.uniform(*curl_deg, size=(5, 2)))
    pieces = [sphere(1.0, (0.0, 0.0, 0.0), hand_colour, resolution=10, **kw)]
    palm = np.array([0.044, 0.016, 0.048]) * s
    pieces[0] = _with_vertices(pieces[0], pieces[0].vertices_m * palm + [0.0, 0.0, -0.065 * s])
    for f, (length, scale) in enumerate(zip((0.045, 0.05, 0.048, 0.038), (1.0, 1.0, 0.95, 0.85))):
        x = (-0.03 + 0.02 * f) * s
        pieces += _capsule_chain(
            (x, 0.008 * s, -0.02 * s),
            (0.0, 0.0, 1.0),
            (length * s, 0.6 * length * s),
            curls[f],
            finger_r * scale,
            hand_colour,
            **kw,
        )
    pieces += _capsule_chain(
        (0.03 * s, -0.02 * s, -0.075 * s),
        (0.3, 0.0, 1.0),
        (0.04 * s, 0.03 * s),
        -curls[4],
        finger_r * 1.15,
        hand_colour,
        **kw,
    )
    wrist_r = float(rng.uniform(0.022, 0.03)) * s
    elbow_z = -0.26 * s
    arm = [
        _frustum(wrist_r, 1.35 * wrist_r, 0.0, elbow_z, skin, **kw),
        cylinder(
            1.5 * wrist_r, LIMB_M + elbow_z, (0.0, 0.0, 0.5 * (elbow_z - LIMB_M)), skin, resolution=14, **kw
        ),
    ]
    style = {"kind": "hand", "size": round(s, 4), "skin": [round(c, 4) for c in skin], "sleeve": sleeve_style}
    if glove is not None:
        cuff = float(rng.uniform(0.02, 0.08))
        arm.append(_frustum(wrist_r + 0.002, 1.1 * wrist_r + 0.002, 0.01, -cuff, glove, **kw))
        style["glove"] = [round(c, 4) for c in glove]
    if sleeve_style != "none":
        start = float(rng.uniform(*SLEEVE_STYLES[sleeve_style])) * s
        loose = float(rng.uniform(0.004, 0.012))
        r0 = wrist_r * (1.0 + 0.35 * min(start / -elbow_z, 1.0)) + loose
        arm.append(_frustum(r0, 1.6 * wrist_r + loose, -start, -LIMB_M, sleeve_colour, **fabric))
        style.update(sleeve_colour=[round(c, 4) for c in sleeve_colour], sleeve_start_m=round(start, 4))
    return Limb(tuple(pieces), tuple(arm), (0.0, 0.0, -0.11 * s), style)


def gripper_limb(rng: np.random.Generator) -> Limb:
    """A two-finger gripper on a robot arm, every colour drawn (body, fingers and arm of any hue, dark
    to light; the fingers half the time a dark grey), its size within +-20 %."""
    k = float(rng.uniform(0.8, 1.2))
    body = any_colour(rng)
    fingers = tuple(float(rng.uniform(0.08, 0.2)) * np.ones(3)) if rng.random() < 0.5 else any_colour(rng)
    arm_colour = body if rng.random() < 0.5 else any_colour(rng)
    gap = float(rng.uniform(0.012, 0.024))
    hand = (
        box((0.09 * k, 0.05 * k, 0.06 * k), (0.0, 0.0, -0.06 * k), body, pattern="plain"),
        box((0.02 * k, 0.012, 0.05 * k), (0.0, gap, -0.01 * k), fingers, pattern="plain"),
        box((0.02 * k, 0.012, 0.05 * k), (0.0, -gap, -0.01 * k), fingers, pattern="plain"),
    )
    arm = (
        cylinder(
            0.035 * k,
            LIMB_M,
            (0.0, 0.0, -LIMB_M / 2),
            arm_colour,
            resolution=16,
            pattern="stripes",
            cell_m=0.05,
            contrast=0.1,
        ),
    )
    style = {
        "kind": "gripper",
        "size": round(k, 4),
        "body": [round(c, 4) for c in body],
        "fingers": [round(float(c), 4) for c in fingers],
        "arm": [round(c, 4) for c in arm_colour],
    }
    return Limb(hand, arm, (0.0, 0.0, -0.09 * k), style)


def colour_boxes(limb: Limb, *, rgb_sigma: float, ambient: float = AMBIENT) -> list[str]:
    """One ``colour_box`` per colour of a gripper limb (its body, fingers and arm)."""
    pieces = limb.hand + limb.arm
    colours = dict.fromkeys(p.colour for p in pieces)
    return [
        colour_box([p for p in pieces if p.colour == c], rgb_sigma=rgb_sigma, ambient=ambient)
        for c in colours
    ]


def _align(a, b) -> np.ndarray:
    """The smallest rotation taking unit vector ``a`` to unit vector ``b``."""
    a, b = _unit(a), _unit(b)
    axis = np.cross(a, b)
    s, c = float(np.linalg.norm(axis)), float(np.dot(a, b))
    if s < 1e-9:
        return (
            np.eye(3)
            if c > 0
            else rotation_about_axis(
                np.cross(a, [1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.cross(a, [0.0, 1.0, 0.0]), math.pi
            )
        )
    return rotation_about_axis(axis, math.atan2(s, c))


#: A forearm (or robot arm) always rises at least this much from the wrist: an arm reaches down to
#: what it holds, it never comes up through the table.
MIN_ARM_ELEVATION_DEG = 10.0


#: An arm keeps at least this angle between itself and the line from the wrist to the camera: a person
#: does not reach through the lens.
MIN_ARM_TO_EYE_DEG = 45.0


def _turn_away(d: np.ndarray, avoid: np.ndarray, min_deg: float, towards: np.ndarray) -> np.ndarray:
    """Unit direction ``d`` turned to at least ``min_deg`` from unit direction ``avoid``, on the side
    of ``avoid`` that ``towards`` lies (the previous frame's arm, so that the arm does not jump)."""
    cos_min = math.cos(math.radians(min_deg))
    if float(d @ avoid) <= cos_min:
        return d
    side = towards - (towards @ avoid) * avoid
    side = _unit(side) if np.linalg.norm(side) > 1e-6 else _unit(np.cross(avoid, [1.0, 0.0, 0.0]))
    return cos_min * avoid + math.sqrt(1.0 - cos_min**2) * side


def arm_poses(
    limb: Limb,
    T_world_from_holder: np.ndarray,
    rng: np.random.Generator,
    *,
    bend_deg: float = 30.0,
    sway_deg: float = 20.0,
    follow: bool = True,
    eye_world=None,
) -> np.ndarray:
    """``T_holder_from_arm`` per frame, shape (N, 4, 4): the arm turned about the wrist by a bend
    (flexion about the holder's x, deviation about its y) that is drawn within +-``bend_deg`` and
    sways by up to ``sway_deg`` over the sequence.

    With ``follow=False`` the arm keeps its first frame's direction in the world while the hand turns
    (a hand sliding an object round on the table turns at the wrist). The wrist turns the arm further
    where it would otherwise come within ``MIN_ARM_TO_EYE_DEG`` of the line to the camera at
    ``eye_world``, or below ``MIN_ARM_ELEVATION_DEG``.
    """
    n = len(T_world_from_holder)
    t = np.linspace(0.0, 1.0, n)
    flex0, dev0 = rng.uniform(-bend_deg, bend_deg), rng.uniform(-0.5 * bend_deg, 0.5 * bend_deg)
    amp, freq, phase = rng.uniform(0.0, sway_deg), rng.uniform(0.3, 1.0), rng.uniform(0.0, 2 * math.pi)
    flex = np.radians(flex0 + amp * np.sin(2 * math.pi * freq * t + phase))
    dev = np.radians(dev0 + 0.5 * amp * np.cos(2 * math.pi * freq * t + phase))
    lowest = math.sin(math.radians(MIN_ARM_ELEVATION_DEG))
    wrist = np.r_[np.asarray(limb.wrist_m, float), 1.0]
    out = np.repeat(np.eye(4)[None], n, axis=0)
    previous = np.array([0.0, 0.0, 1.0])  # the first frame turns the arm upwards, if it must
    for f in range(n):
        R = rotation_about_axis((1.0, 0.0, 0.0), flex[f]) @ rotation_about_axis((0.0, 1.0, 0.0), dev[f])
        R_wh = T_world_from_holder[f][:3, :3]
        R_w = (R_wh if follow else T_world_from_holder[0][:3, :3]) @ R  # the arm's frame in the world
        d = R_w @ np.array([0.0, 0.0, -1.0])
        want = d
        if eye_world is not None:
            to_eye = np.asarray(eye_world, float) - (T_world_from_holder[f] @ wrist)[:3]
            want = _turn_away(want, _unit(to_eye), MIN_ARM_TO_EYE_DEG, previous)
        if want[2] < lowest:
            horizontal = want[:2] / max(np.linalg.norm(want[:2]), 1e-9)
            want = np.r_[math.sqrt(1 - lowest**2) * horizontal, lowest]
        out[f, :3, :3] = R_wh.T @ _align(d, want) @ R_w
        out[f, :3, 3] = limb.wrist_m
        previous = want
    return out


def top_pose(
    points_m: np.ndarray, rng: np.random.Generator, *, mode: str, side_deg: float = 80.0
) -> np.ndarray:
    """``T_object_from_holder`` of a hand on top of an object whose vertices (object frame, z up, the
    camera on the -y side) are ``points_m``.

    ``mode="flat"``: the palm rests flat on the top face (palm down, fingers straight across it), the
    forearm rising 5-20 degrees behind it. ``mode="twist"``: the hand grips the top from above, on the
    vertical through the top face's centre, the forearm rising steeply (55-80 degrees), as when
    twisting a lid. The forearm comes from the camera's half of the table (the -y side), from
    within ``side_deg`` of either side (+-x): a person reaches round the object, not through the wall
    behind it.
    """
    top_z = float(points_m[:, 2].max())
    top = points_m[points_m[:, 2] >= top_z - 0.004]
    lo, hi = top[:, :2].min(0), top[:, :2].max(0)
    az = math.radians(rng.uniform(-side_deg, 0.0) + (0.0 if rng.random() < 0.5 else -180.0 + side_deg))
    shoulder = np.array([math.cos(az), math.sin(az), 0.0])  # from the hand towards the shoulder
    up = np.array([0.0, 0.0, 1.0])
    if mode == "flat":
        spot = lo + (hi - lo) * rng.uniform(0.3, 0.7, size=2)
        z = _unit(-shoulder - math.tan(math.radians(rng.uniform(5.0, 20.0))) * up)
        x = _unit(np.cross(z, up))
        origin = np.r_[spot, top_z] - 0.06 * shoulder + 0.018 * up
    elif mode == "twist":
        spot = 0.5 * (lo + hi)
        tilt = math.radians(90.0 - rng.uniform(55.0, 80.0))
        z = _unit(-up * math.cos(tilt) - shoulder * math.sin(tilt))
        x = _unit(np.cross(up, z))
        origin = np.r_[spot, top_z + 0.004]
    else:
        raise ValueError(f"mode={mode!r} is not 'flat' or 'twist'")
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = origin
    return T


def mirrored(limb: Limb) -> Limb:
    """The same limb reflected in its y-z plane: the other hand of the same person."""

    def flip(pieces):
        return tuple(_with_vertices(p, p.vertices_m * [-1.0, 1.0, 1.0]) for p in pieces)

    return Limb(flip(limb.hand), flip(limb.arm), limb.wrist_m, dict(limb.style, side="other"))
