"""Object catalogue: articulated and rigid objects built from mesh primitives.

Every object is described in its own *object frame*: metres, z up, the origin
on the table at the centre of the object's footprint, the front of the object
facing -y (the camera looks at the front). An object is a kinematic tree of
parts. Part 0 is the *base*; its frame is the object frame. Part ``k >= 1`` is
attached to its parent part (``joints[k - 1].parent``, a lower index) through a
revolute or prismatic joint, so a desk lamp (base, lower arm, upper arm) or a
folding ruler (a chain of segments) is built like a laptop (base and lid).
Every part's geometry and every joint's axis are given in the object frame
with all joints at position 0; a part's pose is its parent's pose composed with
its own joint's motion ``T_object_from_child(joint, q)`` (see ``part_poses``).

Each part is a list of pieces (a primitive mesh, two colours and a texture
pattern in the piece's part frame), so that the RGB images have features that
move with the part they belong to.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

__all__ = [
    "Joint",
    "ObjectSpec",
    "OBJECTS",
    "Part",
    "Piece",
    "T_object_from_child",
    "object_extent_m",
    "part_poses",
    "rotation_about_axis",
    "stand_pieces",
]

#: Texture patterns a piece may carry (evaluated in its part frame).
PATTERNS = ("plain", "checker", "stripes", "blobs")


@dataclass(frozen=True)
class Piece:
    """One primitive mesh of a part.

    Attributes
    ----------
    vertices_m : ndarray, shape (V, 3), metres
        Vertex positions in the object frame (at joint position 0).
    triangles : ndarray, shape (F, 3), uint32
        Triangle vertex indices.
    colour : tuple of 3 floats in [0, 1]
        Base RGB colour.
    colour2 : tuple of 3 floats in [0, 1]
        Second colour of the texture pattern.
    pattern : str
        One of ``PATTERNS``.
    cell_m : float
        Size of one pattern cell, metres.
    """

    vertices_m: np.ndarray = field(repr=False, compare=False)
    triangles: np.ndarray = field(repr=False, compare=False)
    colour: tuple[float, float, float]
    colour2: tuple[float, float, float]
    pattern: str = "checker"
    cell_m: float = 0.03


@dataclass(frozen=True)
class Part:
    """A rigid part: a name and its pieces."""

    name: str
    pieces: tuple[Piece, ...]


@dataclass(frozen=True)
class Joint:
    """A joint that moves a child part relative to its parent part.

    Attributes
    ----------
    joint_type : {"revolute", "prismatic"}
    origin_m : tuple of 3 floats, metres
        A point on the joint axis, object frame.
    axis : tuple of 3 floats
        Unit direction of the axis, object frame. Positive ``q`` turns the
        moving part right-handedly about it (revolute) or slides it along it
        (prismatic).
    limits : tuple (low, high), radians or metres
        Physically possible joint positions.
    rest : tuple (low, high), radians or metres
        Range from which the starting position of a sequence is drawn.
    travel : tuple (low, high), radians or metres
        Range of the absolute joint displacement over an articulating sequence.
    parent : int
        Index of the parent part (0, the base, for single-joint objects).
    """

    joint_type: str
    origin_m: tuple[float, float, float]
    axis: tuple[float, float, float]
    limits: tuple[float, float]
    rest: tuple[float, float]
    travel: tuple[float, float]
    parent: int = 0

    def __post_init__(self):
        if self.joint_type not in ("revolute", "prismatic"):
            raise ValueError(f"joint_type={self.joint_type!r} is not 'revolute' or 'prismatic'")
        lo, hi = self.limits
        if not (lo <= self.rest[0] <= self.rest[1] <= hi):
            raise ValueError(f"rest={self.rest} is not inside limits={self.limits}")
        if not (0 < self.travel[0] <= self.travel[1] <= hi - lo):
            raise ValueError(f"travel={self.travel} does not fit limits={self.limits}")


@dataclass(frozen=True)
class ObjectSpec:
    """A catalogue entry.

    Attributes
    ----------
    name : str
        Unique lowercase name.
    kind : {"articulated", "rigid"}
    description : str
        One line for people.
    parts : tuple of Part
        Part 0 is the base; part ``k >= 1`` (articulated objects only) hangs on ``joints[k - 1]``.
    joints : tuple of Joint
        One per part after the base; empty for rigid objects.
    tags : tuple of str
        Shapes that motions need: ``"revolution"`` (a body of revolution about the object's z axis,
        which can be spun about it) and ``"flat"`` (lies flat on the table and can slide on it).
    """

    name: str
    kind: str
    description: str
    parts: tuple[Part, ...] = field(repr=False)
    joints: tuple[Joint, ...] = ()
    tags: tuple[str, ...] = ()

    def __post_init__(self):
        if len(self.joints) != len(self.parts) - 1:
            raise ValueError(
                f"object {self.name!r}: {len(self.parts)} parts need "
                f"{len(self.parts) - 1} joints, got {len(self.joints)}"
            )
        for k, j in enumerate(self.joints):
            if not 0 <= j.parent <= k:
                raise ValueError(
                    f"object {self.name!r}: joint {k} (part {k + 1}) has parent "
                    f"{j.parent}, which must be a part before it (0..{k})"
                )

    @property
    def joint(self) -> Joint | None:
        """The first joint (the only one of a single-joint object), or ``None`` for rigid objects."""
        return self.joints[0] if self.joints else None

    @property
    def joint_type(self) -> str | None:
        """Type of the first joint: ``"revolute"``, ``"prismatic"`` or ``None`` for rigid objects."""
        return None if self.joint is None else self.joint.joint_type

    def subtree(self, part: int) -> list[int]:
        """``part`` and every part that hangs on it, directly or through other joints."""
        out = [part]
        for k, j in enumerate(self.joints):
            if j.parent in out:
                out.append(k + 1)
        return out

    def rest_positions(self) -> np.ndarray:
        """Midpoint of every joint's ``rest`` range, shape (J,)."""
        return np.array([0.5 * (j.rest[0] + j.rest[1]) for j in self.joints])


# --------------------------------------------------------------------------
# Small geometry helpers
# --------------------------------------------------------------------------


def rotation_about_axis(axis, angle_rad: float) -> np.ndarray:
    """Rotation matrix, shape (3, 3), turning by ``angle_rad`` about ``axis``."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle_rad) * k + (1 - math.cos(angle_rad)) * (k @ k)


def T_object_from_child(joint: Joint | None, q: float | None) -> np.ndarray:
    """Pose of the moving part in the object frame at joint position ``q``.

    Parameters
    ----------
    joint : Joint or None
    q : float or None
        Joint position, radians (revolute) or metres (prismatic).

    Returns
    -------
    ndarray, shape (4, 4)
        Identity for rigid objects.
    """
    T = np.eye(4)
    if joint is None or q is None:
        return T
    axis = np.asarray(joint.axis, dtype=float)
    if joint.joint_type == "prismatic":
        T[:3, 3] = axis * q
        return T
    R = rotation_about_axis(axis, q)
    p = np.asarray(joint.origin_m, dtype=float)
    T[:3, :3] = R
    T[:3, 3] = p - R @ p
    return T


def part_poses(spec: ObjectSpec, q) -> list[np.ndarray]:
    """Pose of every part in the object frame, ``T_object_from_part``, at joint positions ``q``.

    Parameters
    ----------
    spec : ObjectSpec
    q : array_like, shape (J,), or float, or None
        Joint positions (radians or metres) in the order of ``spec.joints``; a float for a
        single-joint object; ``None`` puts every joint at 0.

    Returns
    -------
    list of ndarray, shape (4, 4)
        One per part; the base's is the identity.
    """
    qs = np.zeros(len(spec.joints)) if q is None else np.atleast_1d(np.asarray(q, dtype=float))
    if len(qs) != len(spec.joints):
        raise ValueError(f"object {spec.name!r} has {len(spec.joints)} joints, got {len(qs)} joint positions")
    poses = [np.eye(4)]
    for joint, qk in zip(spec.joints, qs):
        poses.append(poses[joint.parent] @ T_object_from_child(joint, float(qk)))
    return poses


def _legacy_arrays(mesh: o3d.geometry.TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    return (
        np.asarray(mesh.vertices, dtype=np.float64).copy(),
        np.asarray(mesh.triangles, dtype=np.uint32).copy(),
    )


def _place(vertices: np.ndarray, *, R: np.ndarray | None = None, t=(0.0, 0.0, 0.0)):
    v = vertices if R is None else vertices @ np.asarray(R).T
    return v + np.asarray(t, dtype=float)


def _piece(v, f, colour, *, colour2=None, pattern="checker", cell_m=0.03, contrast=0.18):
    colour = tuple(float(c) for c in colour)
    if colour2 is None:
        colour2 = tuple(max(0.0, c * (1.0 - contrast)) for c in colour)
    if pattern not in PATTERNS:
        raise ValueError(f"pattern={pattern!r} is not one of {PATTERNS}")
    return Piece(v, f, colour, tuple(float(c) for c in colour2), pattern, float(cell_m))


def box(size_m, centre_m, colour, *, R=None, **kw) -> Piece:
    """A box of extents ``size_m`` (x, y, z) centred at ``centre_m``."""
    sx, sy, sz = size_m
    v, f = _legacy_arrays(o3d.geometry.TriangleMesh.create_box(sx, sy, sz))
    v -= np.array([sx, sy, sz]) / 2.0
    return _piece(_place(v, R=R, t=centre_m), f, colour, **kw)


def _z_to(axis) -> np.ndarray:
    """Rotation taking +z to ``axis``."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    z = np.array([0.0, 0.0, 1.0])
    c = float(np.dot(z, a))
    if c > 1 - 1e-12:
        return np.eye(3)
    if c < -1 + 1e-12:
        return rotation_about_axis((1, 0, 0), math.pi)
    ax = np.cross(z, a)
    return rotation_about_axis(ax, math.atan2(np.linalg.norm(ax), c))


def cylinder(radius_m, length_m, centre_m, colour, *, axis=(0, 0, 1), resolution=20, **kw) -> Piece:
    """A closed cylinder along ``axis``, centred at ``centre_m``."""
    mesh = o3d.geometry.TriangleMesh.create_cylinder(radius_m, length_m, resolution, 1)
    v, f = _legacy_arrays(mesh)
    return _piece(_place(v, R=_z_to(axis), t=centre_m), f, colour, **kw)


def cone(radius_m, height_m, base_centre_m, colour, *, axis=(0, 0, 1), resolution=20, **kw) -> Piece:
    """A cone whose base disc is at ``base_centre_m``, pointing along ``axis``."""
    v, f = _legacy_arrays(o3d.geometry.TriangleMesh.create_cone(radius_m, height_m, resolution, 1))
    return _piece(_place(v, R=_z_to(axis), t=base_centre_m), f, colour, **kw)


def sphere(radius_m, centre_m, colour, *, resolution=12, **kw) -> Piece:
    """A sphere."""
    v, f = _legacy_arrays(o3d.geometry.TriangleMesh.create_sphere(radius_m, resolution))
    return _piece(_place(v, t=centre_m), f, colour, **kw)


def torus(ring_radius_m, tube_radius_m, centre_m, colour, *, axis=(0, 0, 1), **kw) -> Piece:
    """A torus around ``axis`` (the hole's direction)."""
    mesh = o3d.geometry.TriangleMesh.create_torus(ring_radius_m, tube_radius_m, 20, 10)
    v, f = _legacy_arrays(mesh)
    return _piece(_place(v, R=_z_to(axis), t=centre_m), f, colour, **kw)


def _hollow_box(size_m, centre_m, wall_m, colour, *, open_side: str, **kw) -> list[Piece]:
    """Five walls of a box; ``open_side`` in {"+z", "-y", "+x", ...} is left out."""
    sx, sy, sz = size_m
    cx, cy, cz = centre_m
    w = wall_m
    walls = {
        "-x": ((w, sy, sz), (cx - sx / 2 + w / 2, cy, cz)),
        "+x": ((w, sy, sz), (cx + sx / 2 - w / 2, cy, cz)),
        "-y": ((sx, w, sz), (cx, cy - sy / 2 + w / 2, cz)),
        "+y": ((sx, w, sz), (cx, cy + sy / 2 - w / 2, cz)),
        "-z": ((sx, sy, w), (cx, cy, cz - sz / 2 + w / 2)),
        "+z": ((sx, sy, w), (cx, cy, cz + sz / 2 - w / 2)),
    }
    if open_side not in walls:
        raise ValueError(f"open_side={open_side!r} is not one of {sorted(walls)}")
    return [box(s, c, colour, **kw) for side, (s, c) in walls.items() if side != open_side]


# --------------------------------------------------------------------------
# The catalogue
# --------------------------------------------------------------------------

_DEG = math.pi / 180.0


def _laptop() -> ObjectSpec:
    grey, dark, screen = (0.55, 0.56, 0.60), (0.18, 0.18, 0.20), (0.10, 0.14, 0.30)
    base = Part(
        "base",
        (
            box((0.32, 0.22, 0.018), (0, 0, 0.009), grey, cell_m=0.04),
            box(
                (0.27, 0.09, 0.002),
                (0, 0.03, 0.019),
                dark,
                pattern="checker",
                cell_m=0.018,
                colour2=(0.45, 0.45, 0.48),
            ),  # keyboard
            box((0.08, 0.05, 0.001), (0, -0.07, 0.0185), (0.40, 0.40, 0.44), pattern="plain"),
            cylinder(
                0.005,
                0.30,
                (0, 0.108, 0.018),
                (0.30, 0.30, 0.33),
                axis=(1, 0, 0),
                resolution=10,
                pattern="plain",
            ),  # hinge barrel
        ),
    )
    # Closed lid lies on the base; the hinge is the back top edge.
    lid = Part(
        "lid",
        (
            box((0.32, 0.22, 0.008), (0, 0, 0.022), grey, cell_m=0.05, pattern="stripes"),
            box(
                (0.29, 0.19, 0.001),
                (0, 0.005, 0.0175),
                screen,
                pattern="blobs",
                cell_m=0.04,
                colour2=(0.25, 0.45, 0.65),
            ),
        ),
    )
    joint = Joint(
        "revolute",
        (0.0, 0.11, 0.018),
        (-1.0, 0.0, 0.0),
        limits=(0.0, 135 * _DEG),
        rest=(60 * _DEG, 115 * _DEG),
        travel=(20 * _DEG, 70 * _DEG),
    )
    return ObjectSpec(
        "laptop", "articulated", "laptop: base and lid on a revolute hinge", (base, lid), (joint,)
    )


def _drawer() -> ObjectSpec:
    wood, front, knob = (0.62, 0.45, 0.28), (0.80, 0.78, 0.72), (0.25, 0.25, 0.28)
    # Carcass 30 x 32 x 22 cm, open at the front (-y).
    carcass = _hollow_box(
        (0.30, 0.32, 0.22), (0, 0, 0.11), 0.012, wood, open_side="-y", pattern="stripes", cell_m=0.02
    )
    inner = (0.30 - 0.026, 0.32 - 0.02, 0.22 - 0.03)
    drawer = [
        box((0.29, 0.015, 0.205), (0, -0.1525, 0.11), front, cell_m=0.035),
        sphere(0.012, (0, -0.171, 0.13), knob, pattern="plain", resolution=8),
    ]
    drawer += _hollow_box(
        (inner[0] - 0.004, inner[1] - 0.02, 0.14),
        (0, 0.0, 0.085),
        0.008,
        (0.70, 0.55, 0.36),
        open_side="+z",
        pattern="stripes",
        cell_m=0.015,
    )
    joint = Joint(
        "prismatic",
        (0.0, -0.16, 0.11),
        (0.0, -1.0, 0.0),
        limits=(0.0, 0.26),
        rest=(0.0, 0.06),
        travel=(0.05, 0.20),
    )
    return ObjectSpec(
        "drawer",
        "articulated",
        "cabinet with a sliding drawer (prismatic)",
        (Part("carcass", tuple(carcass)), Part("drawer", tuple(drawer))),
        (joint,),
    )


def _box_lid() -> ObjectSpec:
    card, lid_col = (0.78, 0.62, 0.40), (0.74, 0.58, 0.36)
    body = _hollow_box(
        (0.20, 0.20, 0.12),
        (0, 0, 0.06),
        0.006,
        card,
        open_side="+z",
        pattern="checker",
        cell_m=0.05,
        contrast=0.12,
    )
    lid = [box((0.206, 0.206, 0.008), (0, 0, 0.124), lid_col, pattern="checker", cell_m=0.05, contrast=0.12)]
    joint = Joint(
        "revolute",
        (0.0, 0.103, 0.12),
        (-1.0, 0.0, 0.0),
        limits=(0.0, 120 * _DEG),
        rest=(0.0, 40 * _DEG),
        travel=(20 * _DEG, 70 * _DEG),
    )
    return ObjectSpec(
        "box_lid",
        "articulated",
        "square box with a hinged lid (revolute, near-symmetric)",
        (Part("box", tuple(body)), Part("lid", tuple(lid))),
        (joint,),
    )


def _lever(sign: float, z_m: float, metal, grip) -> list[Piece]:
    """One lever of a pair of pliers lying flat: jaw towards -x, handle towards +x."""
    t = 0.009
    handle_angle = sign * 8 * _DEG
    R = rotation_about_axis((0, 0, 1), handle_angle)
    d = R @ np.array([1.0, 0.0, 0.0])
    return [
        box(
            (0.055, 0.014, t),
            (-0.0275, sign * 0.002, z_m),
            metal,
            pattern="stripes",
            cell_m=0.008,
            contrast=0.3,
        ),
        box((0.05, 0.012, t), tuple(d * 0.025 + [0, 0, z_m]), metal, R=R, pattern="plain"),
        box(
            (0.075, 0.018, 0.014),
            tuple(d * 0.09 + [0, 0, z_m]),
            grip,
            R=R,
            pattern="checker",
            cell_m=0.012,
            contrast=0.25,
        ),
    ]


def _pliers() -> ObjectSpec:
    metal, red, blue = (0.62, 0.63, 0.66), (0.80, 0.12, 0.10), (0.10, 0.25, 0.75)
    a = _lever(+1.0, 0.007, metal, red)
    a.append(cylinder(0.008, 0.02, (0, 0, 0.011), (0.35, 0.35, 0.38), pattern="plain", resolution=12))
    b = _lever(-1.0, 0.016, metal, blue)
    joint = Joint(
        "revolute",
        (0.0, 0.0, 0.0),
        (0.0, 0.0, -1.0),
        limits=(0.0, 45 * _DEG),
        rest=(0.0, 10 * _DEG),
        travel=(12 * _DEG, 30 * _DEG),
    )
    return ObjectSpec(
        "pliers",
        "articulated",
        "pliers lying flat: two thin levers on a pin (revolute, thin parts)",
        (Part("lever_a", tuple(a)), Part("lever_b", tuple(b))),
        (joint,),
    )


def _globe() -> ObjectSpec:
    wood, brass = (0.40, 0.25, 0.12), (0.72, 0.60, 0.25)
    tilt = 23.5 * _DEG
    axis = np.array([math.sin(tilt), 0.0, math.cos(tilt)])
    centre = np.array([0.0, 0.0, 0.25])
    stand = [
        cylinder(0.075, 0.018, (0, 0, 0.009), wood, resolution=24, pattern="stripes", cell_m=0.01),
        cylinder(0.009, 0.10, (0, 0, 0.068), brass, resolution=10, pattern="plain"),
        cylinder(0.004, 0.29, tuple(centre), brass, axis=tuple(axis), resolution=8, pattern="plain"),
    ]
    # A half-ring meridian holding the axis, drawn as a torus tube around it.
    stand.append(torus(0.125, 0.004, tuple(centre), brass, axis=(0, 1, 0), pattern="plain"))
    ball = [
        sphere(
            0.11,
            tuple(centre),
            (0.15, 0.35, 0.72),
            colour2=(0.30, 0.62, 0.25),
            pattern="blobs",
            cell_m=0.045,
            resolution=20,
        )
    ]
    joint = Joint(
        "revolute",
        tuple(centre),
        tuple(axis),
        limits=(-2 * math.pi, 2 * math.pi),
        rest=(-math.pi, math.pi),
        travel=(40 * _DEG, 150 * _DEG),
    )
    return ObjectSpec(
        "globe",
        "articulated",
        "globe spinning on a stand (revolute, rotationally symmetric part)",
        (Part("stand", tuple(stand)), Part("ball", tuple(ball))),
        (joint,),
    )


def _microwave() -> ObjectSpec:
    white, dark, glass = (0.86, 0.86, 0.84), (0.20, 0.20, 0.22), (0.12, 0.12, 0.14)
    w, d, h = 0.40, 0.30, 0.24
    walls = _hollow_box(
        (w, d, h), (0, 0, h / 2), 0.012, white, open_side="-y", pattern="checker", cell_m=0.06, contrast=0.08
    )
    panel = box(
        (0.10, 0.02, h - 0.024),
        (w / 2 - 0.05 - 0.012, -d / 2 + 0.01, h / 2),
        dark,
        pattern="checker",
        cell_m=0.015,
        colour2=(0.45, 0.55, 0.45),
    )
    inner = box((0.012, d - 0.03, h - 0.024), (w / 2 - 0.10 - 0.018, 0, h / 2), white, pattern="plain")
    door_w = w - 0.10 - 0.012
    x0 = -w / 2
    door = [
        box(
            (door_w, 0.02, h - 0.01),
            (x0 + door_w / 2, -d / 2 - 0.01, h / 2),
            white,
            pattern="checker",
            cell_m=0.05,
            contrast=0.08,
        ),
        box(
            (door_w - 0.07, 0.002, h - 0.08),
            (x0 + door_w / 2 - 0.01, -d / 2 - 0.021, h / 2),
            glass,
            pattern="blobs",
            cell_m=0.05,
            colour2=(0.25, 0.25, 0.28),
        ),
        box((0.015, 0.02, h - 0.07), (x0 + door_w - 0.02, -d / 2 - 0.03, h / 2), dark, pattern="plain"),
    ]
    # Vertical hinge at the left front edge; positive q swings the door towards the camera.
    joint = Joint(
        "revolute",
        (x0, -d / 2 - 0.02, 0.0),
        (0.0, 0.0, -1.0),
        limits=(0.0, 110 * _DEG),
        rest=(0.0, 30 * _DEG),
        travel=(20 * _DEG, 70 * _DEG),
    )
    return ObjectSpec(
        "microwave",
        "articulated",
        "microwave oven with a hinged door (revolute, large part)",
        (Part("body", tuple(walls + [panel, inner])), Part("door", tuple(door))),
        (joint,),
    )


def _matchbox() -> ObjectSpec:
    sleeve_col, tray_col = (0.85, 0.20, 0.15), (0.90, 0.85, 0.70)
    sx, sy, sz = 0.14, 0.09, 0.035
    wall = 0.003
    sleeve = [
        box((sx, sy, wall), (0, 0, wall / 2), sleeve_col, pattern="stripes", cell_m=0.012),
        box(
            (sx, sy, wall),
            (0, 0, sz - wall / 2),
            sleeve_col,
            pattern="blobs",
            cell_m=0.02,
            colour2=(0.95, 0.85, 0.20),
        ),
        box((sx, wall, sz), (0, -sy / 2 + wall / 2, sz / 2), sleeve_col, pattern="stripes", cell_m=0.012),
        box((sx, wall, sz), (0, sy / 2 - wall / 2, sz / 2), sleeve_col, pattern="stripes", cell_m=0.012),
    ]
    tray = _hollow_box(
        (sx - 0.004, sy - 2 * wall - 0.002, sz - 2 * wall - 0.002),
        (0, 0, sz / 2),
        0.002,
        tray_col,
        open_side="+z",
        pattern="checker",
        cell_m=0.012,
        contrast=0.2,
    )
    joint = Joint(
        "prismatic",
        (sx / 2, 0.0, sz / 2),
        (1.0, 0.0, 0.0),
        limits=(0.0, 0.11),
        rest=(0.0, 0.02),
        travel=(0.04, 0.09),
    )
    return ObjectSpec(
        "matchbox",
        "articulated",
        "kitchen matchbox: sleeve and sliding tray (prismatic, small part)",
        (Part("sleeve", tuple(sleeve)), Part("tray", tuple(tray))),
        (joint,),
    )


def _mug() -> ObjectSpec:
    col = (0.85, 0.82, 0.20)
    body = cylinder(0.04, 0.095, (0, 0, 0.0475), col, resolution=24, pattern="stripes", cell_m=0.015)
    coffee = cylinder(0.036, 0.002, (0, 0, 0.088), (0.25, 0.15, 0.08), pattern="plain", resolution=24)
    handle = torus(0.028, 0.007, (0.045, 0, 0.05), col, axis=(0, 1, 0), pattern="plain")
    return ObjectSpec(
        "mug",
        "rigid",
        "mug: cylinder and a ring handle",
        (Part("mug", (body, coffee, handle)),),
        tags=("revolution",),
    )


def _cereal_box() -> ObjectSpec:
    b = box(
        (0.19, 0.07, 0.28),
        (0, 0, 0.14),
        (0.90, 0.55, 0.10),
        colour2=(0.20, 0.35, 0.80),
        pattern="blobs",
        cell_m=0.05,
    )
    return ObjectSpec("cereal_box", "rigid", "cereal box (rigid box)", (Part("box", (b,)),))


def _can() -> ObjectSpec:
    body = cylinder(
        0.033,
        0.115,
        (0, 0, 0.0575),
        (0.78, 0.10, 0.12),
        colour2=(0.9, 0.9, 0.9),
        pattern="stripes",
        cell_m=0.02,
        resolution=24,
    )
    top = cylinder(0.030, 0.004, (0, 0, 0.117), (0.75, 0.76, 0.78), pattern="plain", resolution=24)
    return ObjectSpec(
        "can", "rigid", "drinks can (rigid cylinder)", (Part("can", (body, top)),), tags=("revolution",)
    )


def _bottle() -> ObjectSpec:
    green = (0.20, 0.55, 0.30)
    pieces = (
        cylinder(
            0.035,
            0.17,
            (0, 0, 0.085),
            green,
            colour2=(0.92, 0.92, 0.88),
            pattern="stripes",
            cell_m=0.04,
            resolution=24,
        ),
        cone(0.035, 0.05, (0, 0, 0.17), green, pattern="plain", resolution=24),
        cylinder(0.013, 0.05, (0, 0, 0.215), green, pattern="plain", resolution=16),
        cylinder(0.015, 0.018, (0, 0, 0.245), (0.85, 0.15, 0.15), pattern="plain", resolution=16),
    )
    return ObjectSpec(
        "bottle",
        "rigid",
        "bottle (rigid, rotationally symmetric)",
        (Part("bottle", pieces),),
        tags=("revolution",),
    )


def _drill() -> ObjectSpec:
    yellow, black, metal = (0.92, 0.70, 0.10), (0.12, 0.12, 0.13), (0.60, 0.60, 0.62)
    grip_R = rotation_about_axis((0, 1, 0), -15 * _DEG)
    pieces = (
        box((0.11, 0.075, 0.06), (0, 0, 0.03), black, pattern="checker", cell_m=0.02),
        box(
            (0.04, 0.035, 0.13),
            (0.005, 0, 0.12),
            black,
            R=grip_R,
            pattern="checker",
            cell_m=0.015,
            colour2=(0.3, 0.3, 0.32),
        ),
        cylinder(
            0.035,
            0.17,
            (-0.03, 0, 0.205),
            yellow,
            axis=(1, 0, 0),
            resolution=20,
            pattern="stripes",
            cell_m=0.02,
        ),
        cylinder(0.02, 0.035, (-0.13, 0, 0.205), black, axis=(1, 0, 0), resolution=16, pattern="plain"),
        cylinder(0.003, 0.07, (-0.18, 0, 0.205), metal, axis=(1, 0, 0), resolution=8, pattern="plain"),
    )
    return ObjectSpec("drill", "rigid", "cordless drill (rigid composite)", (Part("drill", pieces),))


def _banana() -> ObjectSpec:
    yellow = (0.93, 0.82, 0.20)
    pieces = []
    n = 17
    arc_r = 0.13
    for i in range(n):
        a = (-50 + 100 * i / (n - 1)) * _DEG
        s = math.sin(math.pi * (i + 0.5) / n)
        r = 0.008 + 0.012 * s
        x, y = arc_r * math.sin(a), arc_r * (1 - math.cos(a)) - 0.04
        pieces.append(
            sphere(
                r,
                (x, y, 0.02),
                yellow,
                resolution=10,
                colour2=(0.7, 0.6, 0.1),
                pattern="stripes",
                cell_m=0.01,
            )
        )
    stem = 55 * _DEG
    pieces.append(
        cylinder(
            0.004,
            0.02,
            (arc_r * math.sin(stem), arc_r * (1 - math.cos(stem)) - 0.04, 0.02),
            (0.35, 0.28, 0.10),
            axis=(math.cos(stem), math.sin(stem), 0),
            resolution=6,
            pattern="plain",
        )
    )
    return ObjectSpec("banana", "rigid", "banana-like curved shape (rigid)", (Part("banana", tuple(pieces)),))


def _book() -> ObjectSpec:
    cover, pages = (0.55, 0.12, 0.10), (0.93, 0.91, 0.85)
    return ObjectSpec(
        "book",
        "rigid",
        "hardback book lying flat (flat, 3 cm thick)",
        (
            Part(
                "book",
                (
                    box((0.24, 0.17, 0.003), (0, 0, 0.0015), cover, pattern="plain"),
                    box(
                        (0.235, 0.165, 0.024),
                        (0.002, 0, 0.015),
                        pages,
                        pattern="stripes",
                        cell_m=0.002,
                        contrast=0.08,
                    ),
                    box(
                        (0.24, 0.17, 0.003),
                        (0, 0, 0.0285),
                        cover,
                        colour2=(0.85, 0.75, 0.30),
                        pattern="blobs",
                        cell_m=0.05,
                    ),
                    box((0.004, 0.17, 0.03), (-0.122, 0, 0.015), cover, pattern="plain"),  # spine
                ),
            ),
        ),
        tags=("flat",),
    )


def _plate() -> ObjectSpec:
    white = (0.92, 0.92, 0.90)
    return ObjectSpec(
        "plate",
        "rigid",
        "dinner plate (flat and thin, 26 cm, 1.5 cm high)",
        (
            Part(
                "plate",
                (
                    cylinder(0.09, 0.008, (0, 0, 0.004), white, resolution=32, pattern="plain"),
                    torus(
                        0.11,
                        0.016,
                        (0, 0, 0.012),
                        white,
                        colour2=(0.20, 0.35, 0.60),
                        pattern="stripes",
                        cell_m=0.012,
                        contrast=0.5,
                    ),
                ),
            ),
        ),
        tags=("flat", "revolution"),
    )


def _ruler() -> ObjectSpec:
    return ObjectSpec(
        "ruler",
        "rigid",
        "30 cm steel ruler (thin: 3 mm)",
        (
            Part(
                "ruler",
                (
                    box(
                        (0.31, 0.03, 0.003),
                        (0, 0, 0.0015),
                        (0.70, 0.71, 0.73),
                        colour2=(0.15, 0.15, 0.15),
                        pattern="stripes",
                        cell_m=0.005,
                        contrast=0.6,
                    ),
                ),
            ),
        ),
        tags=("flat",),
    )


def _scissors() -> ObjectSpec:
    steel, handle = (0.72, 0.73, 0.76), (0.10, 0.30, 0.70)

    def blade(z_m: float, sign: float) -> list[Piece]:
        # A blade towards -x and a handle ring towards +x, 2.5 mm thick, lying flat.
        return [
            box(
                (0.10, 0.012, 0.0025),
                (-0.05, sign * 0.003, z_m),
                steel,
                pattern="stripes",
                cell_m=0.01,
                contrast=0.15,
            ),
            box((0.04, 0.008, 0.0025), (0.02, sign * 0.006, z_m), steel, pattern="plain"),
            torus(0.016, 0.004, (0.058, sign * 0.016, z_m), handle, pattern="plain"),
        ]

    joint = Joint(
        "revolute",
        (0.0, 0.0, 0.0),
        (0.0, 0.0, 1.0),
        limits=(0.0, 50 * _DEG),
        rest=(0.0, 8 * _DEG),
        travel=(15 * _DEG, 40 * _DEG),
    )
    return ObjectSpec(
        "scissors",
        "articulated",
        "scissors lying flat: two thin levers turning in their own plane (revolute)",
        (
            Part(
                "blade_a",
                tuple(
                    blade(0.002, -1.0)
                    + [
                        cylinder(
                            0.004, 0.006, (0, 0, 0.003), (0.3, 0.3, 0.32), resolution=10, pattern="plain"
                        )
                    ]
                ),
            ),
            Part("blade_b", tuple(blade(0.0045, 1.0))),
        ),
        (joint,),
    )


def _monitor() -> ObjectSpec:
    black, grey, screen = (0.08, 0.08, 0.09), (0.30, 0.30, 0.32), (0.10, 0.16, 0.30)
    stand = (
        box((0.22, 0.18, 0.015), (0, 0.02, 0.0075), grey, pattern="plain"),
        box((0.05, 0.03, 0.20), (0, 0.06, 0.11), grey, pattern="plain"),
    )
    hinge = (0.0, 0.05, 0.20)
    panel = (
        box((0.42, 0.03, 0.26), (0, 0.03, 0.20), black, pattern="plain"),
        box(
            (0.40, 0.002, 0.235),
            (0, 0.014, 0.205),
            screen,
            colour2=(0.55, 0.65, 0.80),
            pattern="blobs",
            cell_m=0.06,
        ),
    )
    joint = Joint(
        "revolute",
        hinge,
        (1.0, 0.0, 0.0),
        limits=(-5 * _DEG, 25 * _DEG),
        rest=(-5 * _DEG, 5 * _DEG),
        travel=(8 * _DEG, 20 * _DEG),
    )
    return ObjectSpec(
        "monitor",
        "articulated",
        "computer monitor: a flat panel tilting on its stand (revolute)",
        (Part("stand", stand), Part("panel", panel)),
        (joint,),
    )


def _slide_case() -> ObjectSpec:
    wood, lid_col = (0.72, 0.52, 0.30), (0.62, 0.42, 0.24)
    sx, sy, sz = 0.22, 0.08, 0.045
    body = _hollow_box(
        (sx, sy, sz),
        (0, 0, sz / 2),
        0.005,
        wood,
        open_side="+z",
        pattern="stripes",
        cell_m=0.008,
        contrast=0.12,
    )
    lid = [
        box(
            (sx - 0.004, sy - 0.006, 0.005),
            (0, 0, sz + 0.0025),
            lid_col,
            pattern="stripes",
            cell_m=0.01,
            contrast=0.15,
        ),
        box((0.012, 0.03, 0.004), (sx / 2 - 0.02, 0, sz + 0.007), (0.35, 0.22, 0.12), pattern="plain"),
    ]  # finger grip
    joint = Joint(
        "prismatic",
        (sx / 2, 0.0, sz),
        (1.0, 0.0, 0.0),
        limits=(0.0, 0.17),
        rest=(0.0, 0.02),
        travel=(0.04, 0.12),
    )
    return ObjectSpec(
        "slide_case",
        "articulated",
        "pencil case with a sliding lid (prismatic, thin part)",
        (Part("case", tuple(body)), Part("lid", tuple(lid))),
        (joint,),
    )


def _desk_lamp() -> ObjectSpec:
    black, metal, shade = (0.10, 0.10, 0.11), (0.75, 0.75, 0.78), (0.85, 0.30, 0.15)
    base = (
        cylinder(0.075, 0.025, (0, 0.02, 0.0125), black, resolution=24, pattern="plain"),
        cylinder(0.012, 0.03, (0, 0.02, 0.035), metal, resolution=10, pattern="plain"),
    )
    shoulder, elbow = (0.0, 0.02, 0.045), (0.0, 0.02, 0.245)
    lower = (
        box((0.03, 0.014, 0.20), (0, 0.02, 0.145), metal, pattern="stripes", cell_m=0.02, contrast=0.1),
        cylinder(0.012, 0.04, elbow, black, axis=(1, 0, 0), resolution=10, pattern="plain"),
    )
    upper = (
        box((0.03, 0.18, 0.014), (0, -0.07, 0.245), metal, pattern="stripes", cell_m=0.02, contrast=0.1),
        cone(0.06, 0.09, (0, -0.18, 0.17), shade, axis=(0, 0, 1), resolution=20, pattern="plain"),
        cylinder(0.02, 0.04, (0, -0.18, 0.245), shade, resolution=12, pattern="plain"),
    )
    joints = (
        Joint(
            "revolute",
            shoulder,
            (1.0, 0.0, 0.0),
            limits=(-45 * _DEG, 30 * _DEG),
            rest=(-25 * _DEG, 5 * _DEG),
            travel=(10 * _DEG, 25 * _DEG),
            parent=0,
        ),
        Joint(
            "revolute",
            elbow,
            (1.0, 0.0, 0.0),
            limits=(-40 * _DEG, 50 * _DEG),
            rest=(-15 * _DEG, 15 * _DEG),
            travel=(12 * _DEG, 30 * _DEG),
            parent=1,
        ),
    )
    return ObjectSpec(
        "desk_lamp",
        "articulated",
        "desk lamp: base, lower arm and upper arm with its shade (two revolute joints)",
        (Part("base", base), Part("lower_arm", lower), Part("upper_arm", upper)),
        joints,
    )


def _folding_ruler() -> ObjectSpec:
    wood, ticks = (0.93, 0.82, 0.40), (0.15, 0.12, 0.08)
    n, length, width, t = 4, 0.10, 0.017, 0.004
    x0 = -n * length / 2
    parts, joints = [], []
    for k in range(n):
        z = t / 2 + (k % 2) * t  # alternate layers, as the segments of a real one overlap
        parts.append(
            Part(
                f"segment_{k}",
                (
                    box(
                        (length, width, t),
                        (x0 + (k + 0.5) * length, 0, z),
                        wood,
                        colour2=ticks,
                        pattern="stripes",
                        cell_m=0.005,
                        contrast=0.5,
                    ),
                    cylinder(
                        0.003, 0.009, (x0 + k * length, 0, t), (0.6, 0.6, 0.62), resolution=8, pattern="plain"
                    ),
                ),
            )
        )
        if k:
            joints.append(
                Joint(
                    "revolute",
                    (x0 + k * length, 0.0, 0.0),
                    (0.0, 0.0, 1.0),
                    limits=(-150 * _DEG, 150 * _DEG),
                    rest=(-40 * _DEG, 40 * _DEG),
                    travel=(20 * _DEG, 60 * _DEG),
                    parent=k - 1,
                )
            )
    return ObjectSpec(
        "folding_ruler",
        "articulated",
        "folding ruler lying flat: a chain of four segments (three revolute joints)",
        tuple(parts),
        tuple(joints),
    )


def _kettle() -> ObjectSpec:
    steel, black = (0.70, 0.71, 0.74), (0.10, 0.10, 0.11)
    body = cylinder(
        0.075, 0.17, (0, 0, 0.085), steel, resolution=28, pattern="stripes", cell_m=0.03, contrast=0.1
    )
    v = body.vertices_m.copy()
    v[:, :2] *= (1.0 - 0.18 * v[:, 2] / 0.17)[:, None]  # narrower towards the top
    body = Piece(v, body.triangles, body.colour, body.colour2, body.pattern, body.cell_m)
    pieces = (
        body,
        cylinder(0.048, 0.012, (0, 0, 0.176), black, resolution=24, pattern="plain"),  # lid
        sphere(0.012, (0, 0, 0.188), black, resolution=8, pattern="plain"),  # knob
        box(
            (0.022, 0.03, 0.14), (0.105, 0, 0.10), black, pattern="checker", cell_m=0.01, contrast=0.2
        ),  # grip
        box((0.05, 0.026, 0.02), (0.085, 0, 0.16), black, pattern="plain"),
        box((0.05, 0.026, 0.02), (0.085, 0, 0.04), black, pattern="plain"),
        cone(
            0.018, 0.07, (-0.06, 0, 0.12), steel, axis=(-0.8, 0, 0.6), resolution=12, pattern="plain"
        ),  # spout
    )
    return ObjectSpec(
        "kettle",
        "rigid",
        "electric kettle: a body of revolution with a handle and a spout, lifted off its power base",
        (Part("kettle", pieces),),
        tags=("revolution",),
    )


_BUILDERS = (
    _laptop,
    _drawer,
    _box_lid,
    _pliers,
    _globe,
    _microwave,
    _matchbox,
    _mug,
    _cereal_box,
    _can,
    _bottle,
    _drill,
    _banana,
    _book,
    _plate,
    _ruler,
    _scissors,
    _monitor,
    _slide_case,
    _desk_lamp,
    _folding_ruler,
    _kettle,
)


@functools.lru_cache(maxsize=1)
def _build_catalogue() -> dict[str, ObjectSpec]:
    cat = {}
    for build in _BUILDERS:
        spec = build()
        if spec.name in cat:
            raise ValueError(f"duplicate object name {spec.name!r}")
        if spec.kind == "articulated" and not spec.joints:
            raise ValueError(f"articulated object {spec.name!r} needs a joint")
        if spec.kind == "rigid" and (spec.joints or len(spec.parts) != 1):
            raise ValueError(f"rigid object {spec.name!r} needs one part and no joint")
        cat[spec.name] = spec
    return cat


#: Catalogue: object name -> ObjectSpec (``kind``, ``joint_type``, parts, joint).
OBJECTS: dict[str, ObjectSpec] = _build_catalogue()


def object_points_m(spec: ObjectSpec, q) -> np.ndarray:
    """All vertices of ``spec`` in the object frame at joint positions ``q``, shape (N, 3)."""
    out = []
    for T, part in zip(part_poses(spec, q), spec.parts):
        for piece in part.pieces:
            out.append(piece.vertices_m @ T[:3, :3].T + T[:3, 3])
    return np.concatenate(out)


def object_extent_m(spec: ObjectSpec) -> float:
    """Largest side of the axis-aligned bounding box at the joint's rest midpoint, metres."""
    pts = object_points_m(spec, spec.rest_positions())
    return float(np.max(pts.max(0) - pts.min(0)))


def stand_pieces(spec: ObjectSpec, colour, *, height_m: float, margin_m: float) -> tuple[Piece, ...]:
    """A stand that ``spec`` rests on and is lifted from (a kettle's power base, a coaster, a charging
    pad, a tray): its top at ``z = height_m``, ``margin_m`` beyond the object's footprint, a disc
    under a body of revolution and a slab under anything else. It is not part of the object.

    Parameters
    ----------
    spec : ObjectSpec
    colour : tuple of 3 floats in [0, 1]
    height_m, margin_m : float
    """
    pts = object_points_m(spec, spec.rest_positions())
    foot = pts[pts[:, 2] <= pts[:, 2].min() + 0.01]
    kw = dict(pattern="checker", cell_m=0.02, contrast=0.08)
    if "revolution" in spec.tags:
        r = float(np.max(np.linalg.norm(foot[:, :2], axis=1))) + margin_m
        disc = cylinder(r, height_m, (0.0, 0.0, height_m / 2), colour, resolution=32, **kw)
        post = cylinder(
            0.012, 0.004, (0.0, 0.0, height_m + 0.002), (0.3, 0.3, 0.32), resolution=10, pattern="plain"
        )
        return (disc, post)
    lo, hi = foot[:, :2].min(0) - margin_m, foot[:, :2].max(0) + margin_m
    size = (float(hi[0] - lo[0]), float(hi[1] - lo[1]), height_m)
    return (box(size, (float(lo[0] + hi[0]) / 2, float(lo[1] + hi[1]) / 2, height_m / 2), colour, **kw),)
