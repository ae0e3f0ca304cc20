"""Hands and grippers that handle the object: meshes, colours and where they hold.

A holder (a human hand with its forearm, or a two-finger robot gripper on its
arm) is built from mesh primitives in its own *holder frame*: metres, the
origin at the grasp point, +z the approach direction (into the held surface),
the forearm or arm along -z, the pinch (thumb to fingers) along y. It is
rendered as ``HAND`` pixels: it hides the object but is never part of its
mask.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from .objects import ObjectSpec, Piece, box, cylinder, part_poses, sphere
from .render import AMBIENT

__all__ = ["HOLDER_KINDS", "SKIN_TONES", "colour_box", "grasp_pose", "holder_pieces", "wave_path"]

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


def grasp_pose(spec: ObjectSpec, part: int, q0, rng: np.random.Generator) -> np.ndarray:
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
    """
    T_op = part_poses(spec, q0)[part]
    local = np.concatenate([p.vertices_m for p in spec.parts[part].pieces])
    pts = local @ T_op[:3, :3].T + T_op[:3, 3]
    if part == 0:  # held at its left or right side
        centre = 0.5 * (pts.min(0) + pts.max(0))
        score = (pts[:, 0] - centre[0]) * (1.0 if rng.random() < 0.5 else -1.0)
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
    centre_world, eye_world, right_world, n: int, rng: np.random.Generator, *, clearance_m: float
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
    """
    c, eye = np.asarray(centre_world, float), np.asarray(eye_world, float)
    d = eye - c
    dist = float(np.linalg.norm(d))
    frac = max(rng.uniform(0.25, 0.4), min(clearance_m / dist, 0.7))
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
