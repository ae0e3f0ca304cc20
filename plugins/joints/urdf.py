"""A model of parts and joints, written as a URDF with one mesh per part.

A URDF describes a tree of links joined by joints. Each link here is one part of the object, its
geometry the convex hull of its points (a PLY mesh beside the URDF); each joint carries its type,
axis and the limits of the states seen in the video.
"""

from __future__ import annotations

import dataclasses
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from artclass_core import InputError
from artclass_core.interfaces import JointEstimate

#: Joint types a URDF can express, by JointEstimate type ("free" is a floating joint).
URDF_TYPES = {"fixed": "fixed", "revolute": "revolute", "prismatic": "prismatic", "free": "floating"}


@dataclass(frozen=True)
class Link:
    """A part: ``points_m`` (N, 3), metres, in the link's own frame (for a child, its joint's frame)."""

    name: str
    points_m: np.ndarray


@dataclass(frozen=True)
class Joint:
    """A joint between two links.

    Attributes
    ----------
    name, parent, child : str (link names)
    type : ``fixed``, ``revolute``, ``prismatic`` or ``free``
    T_parent_from_joint : ndarray, shape (4, 4): the joint frame (the child's frame at state 0) in the
        parent's frame, metres
    axis : ndarray, shape (3,): unit axis in the joint frame
    limits : (lower, upper), radians or metres: the states seen
    """

    name: str
    parent: str
    child: str
    type: str
    T_parent_from_joint: np.ndarray = field(default_factory=lambda: np.eye(4))
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    limits: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class ArticulatedModel:
    """Parts and the joints between them: a tree whose root is the one link that is no joint's child."""

    name: str
    links: tuple[Link, ...]
    joints: tuple[Joint, ...]


def joint_from_estimate(estimate: JointEstimate, *, name: str, parent: str, child: str) -> Joint:
    """A URDF joint from a joint estimate in the parent's frame.

    The joint frame is placed at ``estimate.axis_point_m`` (unrotated), so the child's points in its
    own frame are its points in the parent's frame at state 0 minus that point. The limits are the
    smallest and largest state seen.
    """
    if estimate.type not in URDF_TYPES:
        raise InputError(f"joint {name!r}: a {estimate.type} joint has no URDF equivalent")
    T = np.eye(4)
    if estimate.axis_point_m is not None:
        T[:3, 3] = estimate.axis_point_m
    axis = estimate.axis_direction if estimate.axis_direction is not None else np.array([0.0, 0.0, 1.0])
    seen = estimate.states[np.isfinite(estimate.states)]
    limits = (float(seen.min()), float(seen.max())) if len(seen) else (0.0, 0.0)
    return Joint(name, parent, child, estimate.type, T, np.asarray(axis, float), limits)


def _hull_mesh(link: Link) -> o3d.geometry.TriangleMesh:
    points = np.asarray(link.points_m, float)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4:
        raise InputError(
            f"link {link.name!r}: a mesh needs at least 4 points (N, 3), got shape {points.shape}"
        )
    try:
        hull, _ = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).compute_convex_hull()
    except RuntimeError as err:
        raise InputError(f"link {link.name!r}: its points span no volume ({err})") from None
    hull.compute_vertex_normals()
    return hull


def _origin(parent: ET.Element, T: np.ndarray) -> None:
    rpy = Rotation.from_matrix(T[:3, :3]).as_euler("xyz")  # URDF: fixed axes x, y, z (roll, pitch, yaw)
    ET.SubElement(
        parent, "origin", xyz=" ".join(f"{v:.9g}" for v in T[:3, 3]), rpy=" ".join(f"{v:.9g}" for v in rpy)
    )


def write_urdf(model: ArticulatedModel, folder: Path) -> Path:
    """Write ``folder/<name>.urdf`` and one ``folder/meshes/<link>.ply`` (the link's convex hull) per link.

    Returns
    -------
    Path of the URDF. Joints carry ``effort="0" velocity="0"`` in their limits: a video does not tell
    forces or speeds, and URDF requires the attributes.
    """
    folder = Path(folder)
    (folder / "meshes").mkdir(parents=True, exist_ok=True)
    _check_tree(model)
    robot = ET.Element("robot", name=model.name)
    for link in model.links:
        mesh_path = folder / "meshes" / f"{link.name}.ply"
        o3d.io.write_triangle_mesh(str(mesh_path), _hull_mesh(link))
        element = ET.SubElement(robot, "link", name=link.name)
        for tag in ("visual", "collision"):
            shape = ET.SubElement(ET.SubElement(element, tag), "geometry")
            ET.SubElement(shape, "mesh", filename=f"meshes/{link.name}.ply")
    for joint in model.joints:
        element = ET.SubElement(robot, "joint", name=joint.name, type=URDF_TYPES[joint.type])
        _origin(element, joint.T_parent_from_joint)
        ET.SubElement(element, "parent", link=joint.parent)
        ET.SubElement(element, "child", link=joint.child)
        if joint.type in ("revolute", "prismatic"):
            axis = np.asarray(joint.axis, float) / np.linalg.norm(joint.axis)
            ET.SubElement(element, "axis", xyz=" ".join(f"{v:.9g}" for v in axis))
            ET.SubElement(
                element,
                "limit",
                lower=f"{joint.limits[0]:.9g}",
                upper=f"{joint.limits[1]:.9g}",
                effort="0",
                velocity="0",
            )
    ET.indent(robot)
    path = folder / f"{model.name}.urdf"
    ET.ElementTree(robot).write(path, encoding="utf-8", xml_declaration=True)
    return path


def _check_tree(model: ArticulatedModel) -> None:
    """One root, every joint between known links, every link the child of at most one joint."""
    names = [link.name for link in model.links]
    if len(set(names)) != len(names):
        raise InputError(f"model {model.name!r}: link names repeat: {names}")
    children = [joint.child for joint in model.joints]
    for joint in model.joints:
        if joint.type not in URDF_TYPES:
            raise InputError(f"joint {joint.name!r}: a {joint.type} joint has no URDF equivalent")
        for end in (joint.parent, joint.child):
            if end not in names:
                raise InputError(f"joint {joint.name!r}: no link named {end!r}")
    roots = [n for n in names if n not in children]
    reached, frontier = set(roots[:1]), roots[:1]
    while frontier:
        frontier = [j.child for j in model.joints if j.parent in frontier and j.child not in reached]
        reached.update(frontier)
    if len(roots) != 1 or len(set(children)) != len(children) or reached != set(names):
        raise InputError(f"model {model.name!r}: the joints do not make one tree (roots: {roots})")


def model_from_articulation(articulation, *, name: str) -> ArticulatedModel:
    """The URDF model of the parts and joints found in a video
    (:class:`artclass_core.articulation.Articulation`).

    The base is the root link, in the base's coordinates of the first frame; each moving part is a
    link on its joint, its points at state 0 moved into the joint frame. Every estimate and every
    part's points are in the base's first-frame coordinates with all joints at state 0, so a joint
    frame sits in its parent's link frame at the difference of the two joints' points. URDF has no
    screw joint: a screw is written as the revolute joint of its turn.
    """
    links, joints = [], []
    names = {part.index: part.name for part in articulation.parts}
    at = {0: np.zeros(3)}  # each link frame's origin in the base's coordinates
    for part in articulation.parts:  # parents come before their children
        joint = next((j for j in articulation.joints if j.child == part.index), None)
        points = np.asarray(part.points_m, float)
        if joint is not None and joint.parent in at:
            estimate = joint.estimate
            if estimate.type == "screw":
                estimate = dataclasses.replace(estimate, type="revolute")
            urdf_joint = joint_from_estimate(
                estimate,
                name=f"{names[joint.parent]}_to_{part.name}",
                parent=names[joint.parent],
                child=part.name,
            )
            at[part.index] = urdf_joint.T_parent_from_joint[:3, 3]
            T = urdf_joint.T_parent_from_joint.copy()
            T[:3, 3] -= at[joint.parent]
            points = points - at[part.index]
            joints.append(dataclasses.replace(urdf_joint, T_parent_from_joint=T))
        elif part.index != 0:
            continue  # a part without a joint is not in the tree
        links.append(Link(part.name, points))
    return ArticulatedModel(name, tuple(links), tuple(joints))
