"""Poses of a part moved by a known joint, with noise and wrong poses: ground truth for tests and benchmarks."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .models import twist_exp


@dataclass(frozen=True)
class SyntheticJoint:
    """A known joint and the poses it gives the part (parent's frame, metres, radians)."""

    type: str
    direction: np.ndarray  # (3,), unit
    point_m: np.ndarray  # (3,), on the axis (revolute) or the part's origin at state 0 (prismatic)
    states: np.ndarray  # (N,), radians or metres, 0 in the first frame
    poses: np.ndarray  # (N, 4, 4), with noise and outliers
    outliers: np.ndarray  # (N,), bool


def synthetic_joint(
    kind: str,
    *,
    n_frames: int = 60,
    travel: float,
    noise_m: float,
    noise_rad: float,
    n_outliers: int = 0,
    seed: int = 0,
) -> SyntheticJoint:
    """A part 20 cm from a tilted axis about 80 cm in front of the camera, moved through ``travel``
    (radians for ``revolute``, metres for ``prismatic``, ignored for ``fixed``) at an even pace.

    Noise is Gaussian per axis on the part's origin (``noise_m``) and rotation vector (``noise_rad``).
    ``n_outliers`` frames get a wrong pose instead (10-30 degrees and 3-10 cm off).
    """
    rng = np.random.default_rng(seed)
    direction = np.array([0.1, 0.05, 1.0])
    direction /= np.linalg.norm(direction)
    hinge = np.array([0.05, -0.1, 0.8])
    origin = Rotation.from_rotvec([0.3, 0.2, 0.1])
    part = hinge + np.array([0.2, 0.05, 0.02])
    if kind == "revolute":
        xi, point = np.r_[direction, np.cross(hinge, direction)], hinge
    elif kind == "prismatic":
        xi, point = np.r_[np.zeros(3), direction], part
    else:
        xi, point, travel = np.zeros(6), part, 0.0
    states = np.linspace(0.0, travel, n_frames)
    quats, t = twist_exp(xi, states)
    R = Rotation.from_quat(quats)
    poses = np.tile(np.eye(4), (n_frames, 1, 1))
    poses[:, :3, :3] = (
        Rotation.from_rotvec(rng.normal(0, noise_rad, (n_frames, 3))) * R * origin
    ).as_matrix()
    poses[:, :3, 3] = R.apply(part) + t + rng.normal(0, noise_m, (n_frames, 3))
    outliers = np.zeros(n_frames, bool)
    outliers[rng.choice(np.arange(1, n_frames), n_outliers, replace=False)] = True
    for i in np.flatnonzero(outliers):
        turn = rng.normal(size=3)
        turn *= np.radians(rng.uniform(10, 30)) / np.linalg.norm(turn)
        shift = rng.normal(size=3)
        shift *= rng.uniform(0.03, 0.10) / np.linalg.norm(shift)
        poses[i, :3, :3] = Rotation.from_rotvec(turn).as_matrix() @ poses[i, :3, :3]
        poses[i, :3, 3] += shift
    return SyntheticJoint(kind, direction, point, states, poses, outliers)
