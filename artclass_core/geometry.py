"""Small, pure geometry helpers shared by the core and the plugins. Units: metres, radians."""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError, cKDTree
from scipy.spatial.distance import pdist
from scipy.spatial.transform import Rotation


def quaternion_wxyz(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix, sign fixed so that w >= 0.

    The same arithmetic as ``scipy.spatial.transform.Rotation.from_matrix`` (a matrix that is not
    orthonormal to 1e-12 is first replaced by the nearest rotation; the largest of w, x, y, z is
    solved for first), without its per-call overhead: the decision rules call this once per cell.
    """
    m = np.asarray(R, dtype=np.float64)
    if m.shape != (3, 3) or not np.isfinite(m).all() or _det3(m) <= 0:
        x, y, z, w = Rotation.from_matrix(m).as_quat()  # scipy's own checks and error messages
    else:
        if not (np.abs(m @ m.T - _EYE3) <= _GRAM_TOLERANCE).all():  # np.isclose(atol=1e-12, rtol=1e-5)
            u, _, vt = np.linalg.svd(m, full_matrices=False)
            m = u @ vt
        trace = m[0, 0] + m[1, 1] + m[2, 2]
        decision = (m[0, 0], m[1, 1], m[2, 2], trace)
        choice = max(range(4), key=decision.__getitem__)  # first maximum, as numpy's argmax
        q = np.empty(4)  # x, y, z, w
        if choice != 3:
            i, j, k = choice, (choice + 1) % 3, (choice + 2) % 3
            q[i] = 1 - trace + 2 * m[i, i]
            q[j] = m[j, i] + m[i, j]
            q[k] = m[k, i] + m[i, k]
            q[3] = m[k, j] - m[j, k]
        else:
            q[0] = m[2, 1] - m[1, 2]
            q[1] = m[0, 2] - m[2, 0]
            q[2] = m[1, 0] - m[0, 1]
            q[3] = 1 + trace
        x, y, z, w = q / np.linalg.norm(q)
    q = np.array([w, x, y, z])
    return -q if w < 0 else q


_EYE3 = np.eye(3)
_GRAM_TOLERANCE = 1e-12 + 1e-5 * _EYE3


def _det3(m: np.ndarray) -> float:
    return float(
        m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1])
        - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
        + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0])
    )


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
    return diameter_of_vertices(hull_vertices(points))


def hull_vertices(points: np.ndarray) -> np.ndarray:
    """The points that can be an end of the cloud's diameter: its convex hull's vertices.

    Parameters
    ----------
    points : ndarray, shape (N, 3)

    Returns
    -------
    ndarray, shape (V, 3) : a subset of ``points`` (all of them when there are fewer than 2).
    The hull vertices of a union of clouds are among the union of their hull vertices, so the
    diameter of two clouds together is :func:`diameter_of_vertices` of both clouds' vertices.
    """
    points = np.asarray(points)
    if len(points) < 2:
        return points
    try:
        return points[ConvexHull(points).vertices]
    except (QhullError, ValueError):  # flat or collinear cloud: the hull within its plane, or its two ends
        return _flat_hull(points)


def diameter_of_vertices(vertices: np.ndarray) -> float:
    """Largest distance between any two of ``vertices`` (N, 3); 0 for fewer than two."""
    if len(vertices) < 2:
        return 0.0
    return float(np.sqrt(pdist(vertices, "sqeuclidean").max()))  # no (V, V, 3) temporary


def _flat_hull(points: np.ndarray) -> np.ndarray:
    """Hull vertices of a cloud that spans fewer than three dimensions (exact, like the 3-D hull)."""
    centred = points - points.mean(0)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    if s[0] == 0 or s[1] <= s[0] * 1e-9:  # all points on one line (or one point)
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
    keys = np.floor((np.concatenate([source, target]) - origin) / cell_size_m).astype(np.int64)
    # One integer per cell, in the lexicographic order of (i, j, k) (all >= 0 from the common origin),
    # so a 1-D stable sort groups the cells in the order np.unique(axis=0) lists them.
    span = keys.max(0) + 1
    flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
    order = np.argsort(flat, kind="stable")
    sorted_flat = flat[order]
    starts = np.flatnonzero(np.r_[True, sorted_flat[1:] != sorted_flat[:-1]])
    bounds = np.r_[starts, len(flat)]
    n_s = len(source)
    out = []
    for c, first in enumerate(starts):
        members = order[first : bounds[c + 1]]
        cell = keys[members[0]]
        centre = origin + (cell + 0.5) * cell_size_m
        out.append(
            (tuple(int(v) for v in cell), centre, members[members < n_s], members[members >= n_s] - n_s)
        )
    return out


def statistical_inliers(points: np.ndarray, *, neighbours: int, std_ratio: float) -> np.ndarray:
    """Indices of the points kept by statistical outlier removal, exactly as Open3D's
    ``PointCloud.remove_statistical_outlier(nb_neighbors, std_ratio)`` keeps them.

    Each point's mean distance to its ``neighbours`` nearest points (itself included, as Open3D
    counts it) is compared with the mean ``mu`` and the sample standard deviation ``sigma`` of those
    means over the cloud; a point is kept when its mean is above 0 and below ``mu + std_ratio *
    sigma``. Computed with SciPy's KD-tree, which releases the GIL, so several frames can be
    processed in parallel threads (Open3D's version holds it); its search uses every CPU, which
    makes it faster than Open3D's on a pipeline run with one worker too.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
    neighbours : int, >= 1
    std_ratio : float

    Returns
    -------
    ndarray of int64, shape (K,) : indices into ``points``, ascending
    """
    n = len(points)
    if n == 0 or neighbours < 1:
        return np.arange(0)
    k = min(neighbours, n)
    distances, _ = cKDTree(points).query(points, k=k, workers=-1)
    distances = distances.reshape(n, k)
    mean = distances.sum(axis=1) / k
    valid = mean > 0
    n_valid = int(valid.sum())
    if n_valid == 0:
        return np.arange(0)
    mu = mean[valid].sum() / n_valid
    sigma = np.sqrt(((mean[valid] - mu) ** 2).sum() / (n_valid - 1)) if n_valid > 1 else 0.0
    return np.flatnonzero(valid & (mean < mu + std_ratio * sigma))
