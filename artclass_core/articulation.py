"""Parts and joints: what a part finder returns (an :class:`Articulation`) and what a joint
estimator returns (a :class:`JointEstimate`).

A part finder (:class:`~artclass_core.interfaces.PartFinder`, registered through
``register_part_finders``) takes a finished run and returns the object's parts, the joints between
them and each frame's part image; a joint estimator fits one joint to a part's poses.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.spatial.transform import Rotation

from .types import RunResult

#: Joint types a :class:`JointEstimate` can carry, simplest first.
JOINT_TYPES = ("fixed", "prismatic", "revolute", "screw", "free")


@dataclass
class JointEstimate:
    """The joint between a moving part and its parent, as a joint estimator finds it.

    Everything is in the parent's frame, in metres and radians. ``states[i]`` is the joint state in
    frame ``i`` relative to the first frame whose pose the model explains: an angle in radians for ``revolute``
    and ``screw``, a travel in metres for ``prismatic``; NaN where the pose is unknown or an outlier.

    Attributes
    ----------
    type : one of :data:`JOINT_TYPES`
    axis_direction : ndarray, shape (3,), unit vector, or None (``fixed``, ``free``)
    axis_point_m : ndarray, shape (3,), metres, or None: a point on a revolute or screw axis (the one
        nearest the part), or the part's point a prismatic axis runs through
    states : ndarray, shape (N,), radians or metres
    inliers : ndarray, shape (N,), bool: the poses the chosen model explains
    axis_direction_std_rad : float, one standard deviation of the axis direction (NaN if unknown)
    axis_point_std_m : float, one standard deviation of the axis position across the axis
    states_std : ndarray, shape (N,), one standard deviation of each state
    scores : dict, the BIC of every model tried (lower is better); empty if the estimator has none
    info : dict, JSON-ready extra evidence (noise levels found, outlier count, screw pitch ...)
    """

    type: str
    axis_direction: np.ndarray | None
    axis_point_m: np.ndarray | None
    states: np.ndarray
    inliers: np.ndarray
    axis_direction_std_rad: float = float("nan")
    axis_point_std_m: float = float("nan")
    states_std: np.ndarray | None = None
    scores: dict[str, float] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def state_unit(self) -> str:
        """``"m"`` for a prismatic joint, ``"rad"`` otherwise."""
        return "m" if self.type == "prismatic" else "rad"

    def motion(self, state) -> np.ndarray:
        """The motion of the child, in the parent's coordinates, from state 0 to ``state``: (4, 4) for
        one state, (N, 4, 4) for states (N,) (the identity where a state is not finite, and for a
        joint without an axis)."""
        states = np.asarray(state, float)
        q = np.where(np.isfinite(states), states, 0.0).reshape(-1)
        T = np.tile(np.eye(4), (len(q), 1, 1))
        if self.axis_direction is not None:
            d = np.asarray(self.axis_direction, float)
            if self.type == "prismatic":
                T[:, :3, 3] = q[:, None] * d
            else:
                R = Rotation.from_rotvec(q[:, None] * d).as_matrix()
                c = np.asarray(self.axis_point_m, float)
                pitch = self.info.get("pitch_m_per_rad", 0.0)
                T[:, :3, :3], T[:, :3, 3] = R, c - R @ c + q[:, None] * d * pitch
        return T.reshape(states.shape + (4, 4))

    def summary(self, *, up: np.ndarray) -> str:
        """One readable line, e.g. ``"revolute joint, axis 2 deg from vertical, 0-74 deg over the video"``.

        Parameters
        ----------
        up : ndarray, shape (3,): the vertical in the parent's frame (the camera's up, or -gravity)
        """
        if self.type == "fixed":
            return "fixed joint: the part does not move relative to its parent"
        if self.type == "free" or self.axis_direction is None:
            return (
                f"free motion: no single joint explains the part's motion ({int(self.inliers.sum())} of "
                f"{len(self.inliers)} poses fit the best one)"
            )
        up = np.asarray(up, float) / np.linalg.norm(up)
        tilt = np.degrees(np.arccos(np.clip(abs(float(self.axis_direction @ up)), 0.0, 1.0)))
        word = "direction" if self.type == "prismatic" else "axis"
        scale, unit = (1000.0, "mm") if self.type == "prismatic" else (np.degrees(1.0), "deg")
        known = self.states[np.isfinite(self.states)] * scale
        low, high = (float(known.min()), float(known.max())) if len(known) else (0.0, 0.0)
        span = f"{max(low, 0.0) + 0.0:.0f}-{high:.0f}" if round(low) >= 0 else f"{low:.0f} to {high:.0f}"
        return f"{self.type} joint, {word} {tilt:.0f} deg from vertical, {span} {unit} over the video"


@dataclass
class Part:
    """A part of the object over the video.

    Attributes
    ----------
    index : int, 0 for the base
    name : str
    parent : int, the parent part's index (-1 for the base)
    points_m : ndarray, shape (N, 3), metres: the part's points with every joint at state 0, in the
        base's coordinates of the first frame (the URDF moves a child's into its joint frame)
    frames : list of int: the frames in which the part was labelled
    n_labelled : int: its labelled points over all frames
    """

    index: int
    name: str
    parent: int
    points_m: np.ndarray
    frames: list[int]
    n_labelled: int

    def to_dict(self) -> dict[str, Any]:
        return dict(
            index=self.index,
            name=self.name,
            parent=self.parent,
            n_frames=len(self.frames),
            n_labelled=self.n_labelled,
            n_points=len(self.points_m),
        )


@dataclass
class PartJoint:
    """The joint of ``child`` on ``parent`` (part indices): the estimate in the base's coordinates of
    the first frame with every joint at state 0, and a state per frame of the video."""

    parent: int
    child: int
    estimate: JointEstimate
    n_pairs: int

    def to_dict(self, *, up: np.ndarray) -> dict[str, Any]:
        e = self.estimate

        def vec(v):
            return None if v is None else [round(float(x), 6) for x in v]

        def num(x):
            return None if x is None or not np.isfinite(x) else round(float(x), 6)

        return dict(
            parent=self.parent,
            child=self.child,
            type=e.type,
            summary=e.summary(up=up),
            axis_direction=vec(e.axis_direction),
            axis_point_m=vec(e.axis_point_m),
            axis_direction_std_rad=num(e.axis_direction_std_rad),
            axis_point_std_m=num(e.axis_point_std_m),
            state_unit=e.state_unit,
            states=[num(q) for q in e.states],
            states_std=[num(q) for q in (e.states_std if e.states_std is not None else e.states * np.nan)],
            n_pairs=self.n_pairs,
            scores={k: round(v, 3) for k, v in e.scores.items()},
            info={k: (round(v, 6) if isinstance(v, float) else v) for k, v in e.info.items()},
        )


@dataclass
class Articulation:
    """The parts and joints found in a run: what a part finder returns.

    Attributes
    ----------
    parts : list of Part, the base first, every parent before its children
    joints : list of PartJoint, one per moving part
    base_poses : ndarray, shape (n_frames, 4, 4): ``base_poses[f]`` maps the base's coordinates of the
        first frame to camera coordinates of frame f, metres (NaN where unknown)
    views : dict, frame -> ``(pixels, part, mask, stride)``: the frame's labelled pixels (N, 2) int
        (column, row), the part index of each (N,) int, the segmenter's mask (H, W) bool (all False:
        none) and the pixel stride the points were sampled at; :meth:`label_image` fills the image from
        them
    """

    parts: list[Part]
    joints: list[PartJoint]
    base_poses: np.ndarray
    views: dict[int, tuple] = field(default_factory=dict, repr=False)

    #: The camera's vertical (y points down), the reference of "from vertical" in the summaries.
    UP = np.array([0.0, -1.0, 0.0])

    def summary(self) -> str:
        """One line per joint (naming its two parts when there are several), or why there is none."""
        if not self.joints:
            return "no joint: no part moves relative to the rest"
        if len(self.joints) == 1:
            return self.joints[0].estimate.summary(up=self.UP)
        name = {p.index: p.name for p in self.parts}
        return "; ".join(
            f"{name[j.child]} on {name[j.parent]}: {j.estimate.summary(up=self.UP)}" for j in self.joints
        )

    def to_dict(self) -> dict[str, Any]:
        return dict(
            parts=[p.to_dict() for p in self.parts], joints=[j.to_dict(up=self.UP) for j in self.joints]
        )

    @property
    def frames(self) -> list[int]:
        """Frames with a part segmentation."""
        return sorted(self.views)

    def label_image(self, frame: int) -> np.ndarray | None:
        """Frame ``frame``'s part segmentation, shape (H, W), uint8: 0 = not the object, 1 + part index;
        each pixel of the segmenter's mask takes the part of the nearest labelled point. None when no
        pair labelled the frame."""
        if frame not in self.views:
            return None
        pixels, part, mask, stride = self.views[frame]
        seeds = np.zeros(mask.shape, np.uint8)
        seeds[pixels[:, 1], pixels[:, 0]] = part + 1
        if not mask.any():
            mask = cv2.dilate((seeds > 0).astype(np.uint8), np.ones((stride, stride), np.uint8)) > 0
        _, (rows, cols) = distance_transform_edt(seeds == 0, return_indices=True)
        return np.where(mask, seeds[rows, cols], 0).astype(np.uint8)


def forget_clouds(result: RunResult) -> None:
    """Drop the clouds and evidence a run kept for finding its parts (they are large)."""
    for f in result.frames:
        f.cloud = None
    for p in result.pairs:
        p.release()
