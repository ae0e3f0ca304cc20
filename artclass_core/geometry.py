"""Small, pure geometry helpers shared by the core and the plugins. Units: metres, radians."""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError
from scipy.spatial.transform import Rotation


def quaternion_wxyz(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix, sign fixed so that w >= 0."""
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    q = np.array([w, x, y, z])
    return -q if w < 0 else q


def rotation_angle_rad(R: np.ndarray) -> float:
    """Angle of the rotation ``R`` about its axis, in [0, pi]."""
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def transform(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid transform to points of shape (N, 3)."""
    return points @ T[:3, :3].T + T[:3, 3]


def largest_distance(points: np.ndarray) -> float:
    """Largest distance between any two points (the cloud's diameter), in the points' unit.

    Exact: the farthest pair lies on the convex hull, so only hull vertices are compared.
    """
    if len(points) < 2:
        return 0.0
    try:
        hull = points[ConvexHull(points).vertices]
    except (QhullError, ValueError):   # flat or collinear cloud: the hull within its plane, or its two ends
        hull = _flat_hull(points)
    d2 = ((hull[:, None, :] - hull[None, :, :]) ** 2).sum(-1)
    return float(np.sqrt(d2.max()))


def _flat_hull(points: np.ndarray) -> np.ndarray:
    """Hull vertices of a cloud that spans fewer than three dimensions (exact, like the 3-D hull)."""
    centred = points - points.mean(0)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    if s[0] == 0 or s[1] <= s[0] * 1e-9:            # all points on one line (or one point)
        along = centred @ vt[0]
        return points[[int(along.argmin()), int(along.argmax())]]
    try:
        return points[ConvexHull(centred @ vt[:2].T).vertices]
    except (QhullError, ValueError):
        return points if len(points) <= 2000 else points[np.linspace(0, len(points) - 1, 2000).astype(int)]


def grid_cells(source: np.ndarray, target: np.ndarray, *, cell_size_m: float):
    """Split two clouds over one common grid of cubic cells.

    Parameters
    ----------
    source, target : ndarray, shape (N, 3) and (M, 3), metres
    cell_size_m : edge of a cell (the paper's x)

    Returns
    -------
    list of (cell, centre_m, source_idx, target_idx), one per cell holding a point of either cloud,
    sorted by cell index; ``cell`` is the integer (i, j, k) of the cell, ``centre_m`` its centre.
    """
    origin = np.minimum(source.min(0), target.min(0))
    keys_s = np.floor((source - origin) / cell_size_m).astype(np.int64)
    keys_t = np.floor((target - origin) / cell_size_m).astype(np.int64)
    keys = np.concatenate([keys_s, keys_t])
    cells, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(len(cells) + 1))
    n_s = len(source)
    out = []
    for c, cell in enumerate(cells):
        members = order[bounds[c]:bounds[c + 1]]
        centre = origin + (cell + 0.5) * cell_size_m
        out.append((tuple(int(v) for v in cell), centre, members[members < n_s], members[members >= n_s] - n_s))
    return out
