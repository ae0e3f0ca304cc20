"""The compiled (Numba) per-point loops of :mod:`.projective`: projection, look-up and the normal
equations of projective ICP, one pass over the points where numpy makes a dozen temporary arrays;
and the image preprocessor's passes over the depth image (finite depths, the median of the valid
neighbours, normals). All release the GIL, so that worker threads run them at the same time."""

from __future__ import annotations

import numpy as np
from numba import njit

from artclass_core.types import FREE_SPACE, OCCLUDED, OFF_OBJECT, SURFACE, UNSEEN


@njit(cache=True, nogil=True)
def _pixel(q0, q1, q2, camera, h, w):
    """Nearest pixel (column, row) of a point, or (-1, -1) outside the image or behind the camera."""
    if not q2 > 0:
        return -1, -1
    u = np.rint(camera[0] * q0 / q2 + camera[2])
    v = np.rint(camera[1] * q1 / q2 + camera[3])
    if u >= 0 and u < w and v >= 0 and v < h:
        return int(u), int(v)
    return -1, -1


@njit(cache=True, nogil=True)
def _plane_residual(q0, q1, q2, u, v, depth, normals, camera):
    """Signed point-to-plane distance of a point to the object surface at pixel (u, v); NaN where the
    pixel has no surface (depth and normal)."""
    z = np.float64(depth[v, u])
    n0, n1, n2 = np.float64(normals[v, u, 0]), np.float64(normals[v, u, 1]), np.float64(normals[v, u, 2])
    if not (z > 0 and (n0 != 0 or n1 != 0 or n2 != 0)):
        return np.nan
    y0 = (u - camera[2]) / camera[0] * z
    y1 = (v - camera[3]) / camera[1] * z
    return (q0 - y0) * n0 + (q1 - y1) * n1 + (q2 - z) * n2


@njit(cache=True, nogil=True)
def _moved(T, p0, p1, p2):
    """A point moved by the rigid motion T (4, 4)."""
    return (
        T[0, 0] * p0 + T[0, 1] * p1 + T[0, 2] * p2 + T[0, 3],
        T[1, 0] * p0 + T[1, 1] * p1 + T[1, 2] * p2 + T[1, 3],
        T[2, 0] * p0 + T[2, 1] * p1 + T[2, 2] * p2 + T[2, 3],
    )


@njit(cache=True, nogil=True)
def _outside_at(outside, v0, u0, v, u):
    """The distance to the mask at pixel (u, v), from its values in a box whose top-left pixel is
    (u0, v0): inf beyond the box."""
    i, j = v - v0, u - u0
    if i >= 0 and i < outside.shape[0] and j >= 0 and j < outside.shape[1]:
        return outside[i, j]
    return np.inf


@njit(cache=True, nogil=True)
def look_kernel(
    motions, points, scene, depth, normals, outside, v0, u0, covered, camera, reach, off_px, status, residual
):
    h, w = scene.shape
    for k in range(motions.shape[0]):
        for i in range(points.shape[0]):
            q0, q1, q2 = _moved(motions[k], points[i, 0], points[i, 1], points[i, 2])
            status[k, i] = UNSEEN
            residual[k, i] = np.nan
            u, v = _pixel(q0, q1, q2, camera, h, w)
            if u < 0 or not scene[v, u] > 0:
                continue
            gap = np.float64(scene[v, u]) - q2
            if gap < -reach[i]:
                status[k, i] = OCCLUDED
            elif gap > reach[i]:
                status[k, i] = FREE_SPACE
            elif _outside_at(outside, v0, u0, v, u) > off_px:
                # a surface beside the object, unless a hand there may cover the object: hidden
                status[k, i] = OCCLUDED if covered.shape[0] and covered[v, u] else OFF_OBJECT
            else:
                status[k, i] = SURFACE
                plane = _plane_residual(q0, q1, q2, u, v, depth, normals, camera)
                residual[k, i] = -gap if np.isnan(plane) else plane


@njit(cache=True, nogil=True)
def cost_kernel(residual, status, flow, scale, worst, half, flow_scale, flow_worst, out):
    """``out`` (H, N) float32 := each point's cost under each hypothesis (:func:`.rule.point_costs`):
    the squared residual in units of ``scale`` and the squared flow misfit in units of
    ``flow_scale``, each at most its ``worst``; ``worst`` where the point lands in free space or off
    the object, ``half`` where it is hidden or unseen; a NaN flow misfit adds nothing. Each scale
    comes with its worst (and half) in the dtype numpy computes that term in (float32 beside a Python
    float, float64 beside a NumPy float64), so the costs are numpy's to the bit."""
    no_flow = flow_worst - flow_worst
    for h in range(residual.shape[0]):
        for i in range(residual.shape[1]):
            s = status[h, i]
            if s == SURFACE:
                c = residual[h, i] / scale
                c = c * c
                if c > worst:  # as np.minimum: NaN stays NaN
                    c = worst
            elif s == FREE_SPACE or s == OFF_OBJECT:
                c = worst
            else:
                c = half
            f = flow[h, i] / flow_scale
            f = f * f
            if f > flow_worst:
                f = flow_worst
            if f != f:
                f = no_flow
            out[h, i] = c + f


@njit(cache=True, nogil=True)
def totals_kernel(costs, out):
    """``out`` (H,) := each hypothesis's total cost over the points (:func:`.rule.select`), summed
    point by point in the costs' dtype: numpy's order for the costs of some of the points,
    ``costs[:, seen]``, which are stored point by point, so the totals are numpy's to the bit."""
    out[:] = 0
    for i in range(costs.shape[1]):
        for h in range(costs.shape[0]):
            out[h] += costs[h, i]


@njit(cache=True, nogil=True)
def savings_kernel(costs, best, out):
    """``out`` (H,) := what each hypothesis saves over the points' costs ``best`` (N,), the sum of
    ``max(best - costs[h], 0)`` (:func:`.rule.select`), in the order of :func:`totals_kernel`."""
    out[:] = 0
    for i in range(costs.shape[1]):
        for h in range(costs.shape[0]):
            saved = best[i] - costs[h, i]
            if not saved <= 0:  # as np.maximum: NaN stays NaN
                out[h] += saved


@njit(cache=True, nogil=True)
def second_differences_kernel(value, across, down, out):
    """The finite second differences ``v[p - L] - 2 v[p] + v[p + L]`` of the grid ``value`` (rows,
    columns) at lag ``across`` along the rows, then at lag ``down`` along the columns (0: none), into
    ``out`` in numpy's order (:func:`.rule.field_noise`); returns how many."""
    rows, columns = value.shape
    n = 0
    if across:
        for r in range(rows):
            for c in range(across, columns - across):
                d = value[r, c - across] - 2 * value[r, c] + value[r, c + across]
                if np.isfinite(d):
                    out[n] = d
                    n += 1
    if down:
        for r in range(down, rows - down):
            for c in range(columns):
                d = value[r - down, c] - 2 * value[r, c] + value[r + down, c]
                if np.isfinite(d):
                    out[n] = d
                    n += 1
    return n


@njit(cache=True, nogil=True, error_model="numpy")
def flow_kernel(motions, points, flow_px, across, camera, out):
    for k in range(motions.shape[0]):
        for i in range(points.shape[0]):
            out[k, i] = np.nan
            if not (np.isfinite(flow_px[i, 0]) and np.isfinite(flow_px[i, 1])):
                continue
            q0, q1, q2 = _moved(motions[k], points[i, 0], points[i, 1], points[i, 2])
            du = camera[0] * q0 / q2 + camera[2] - flow_px[i, 0]
            dv = camera[1] * q1 / q2 + camera[3] - flow_px[i, 1]
            if np.isfinite(across[i, 0]):
                out[k, i] = abs(du * across[i, 0] + dv * across[i, 1])
            else:
                out[k, i] = np.hypot(du, dv)


@njit(cache=True, nogil=True)
def _add_row(A, b, g, a0, a1, a2, n0, n1, n2, r, reach):
    """Add one residual row (point-to-plane or flow), Tukey-weighted at ``reach``, to group g's normal
    equations: its gradient per metre of motion is n, its Jacobian [arm x n, n]."""
    j = (a1 * n2 - a2 * n1, a2 * n0 - a0 * n2, a0 * n1 - a1 * n0, n0, n1, n2)
    s = r / reach
    weight = (1 - s * s) ** 2
    for x in range(6):
        wx = weight * j[x]
        b[g, x] += wx * r
        for y in range(x, 6):
            A[g, x, y] += wx * j[y]


@njit(cache=True, nogil=True)
def _rotation(x0, x1, x2):
    """Rotation matrix (3, 3) of a rotation vector (Rodrigues)."""
    R = np.eye(3)
    theta = np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    if theta < 2.220446049250313e-16:
        return R
    k0, k1, k2 = x0 / theta, x1 / theta, x2 / theta
    c, s = np.cos(theta), np.sin(theta)
    C = 1 - c
    R[0, 0], R[0, 1], R[0, 2] = c + C * k0 * k0, C * k0 * k1 - s * k2, C * k0 * k2 + s * k1
    R[1, 0], R[1, 1], R[1, 2] = C * k1 * k0 + s * k2, c + C * k1 * k1, C * k1 * k2 - s * k0
    R[2, 0], R[2, 1], R[2, 2] = C * k2 * k0 - s * k1, C * k2 * k1 + s * k0, c + C * k2 * k2
    return R


@njit(cache=True, nogil=True)
def _normal_equations(
    points,
    index,
    groups,
    T,
    centre,
    use,
    reach,
    depth,
    normals,
    camera,
    flow_px,
    across,
    metres_per_px,
    A,
    b,
    rows,
    inliers,
):
    """One pass over the points ``points[index]`` (``groups``, ``use`` per entry of ``index``): each
    group's Gauss-Newton normal equations (the upper triangle of the sum of w J^T J in A, the sum of
    w J^T r in b), its number of rows and of depth matches."""
    h, w = depth.shape
    fx, fy, cx, cy = camera[0], camera[1], camera[2], camera[3]
    A[:] = 0
    b[:] = 0
    rows[:] = 0
    inliers[:] = 0
    moved_centre = np.empty((T.shape[0], 3))
    for g in range(T.shape[0]):
        moved_centre[g, 0], moved_centre[g, 1], moved_centre[g, 2] = _moved(
            T[g], centre[g, 0], centre[g, 1], centre[g, 2]
        )
    for k in range(index.shape[0]):
        if not use[k]:
            continue
        g, i = groups[k], index[k]
        q0, q1, q2 = _moved(T[g], points[i, 0], points[i, 1], points[i, 2])
        # lever arm about the moved centroid
        a0, a1, a2 = q0 - moved_centre[g, 0], q1 - moved_centre[g, 1], q2 - moved_centre[g, 2]
        u, v = _pixel(q0, q1, q2, camera, h, w)
        if u >= 0:
            r = _plane_residual(q0, q1, q2, u, v, depth, normals, camera)
            if abs(r) < reach:
                _add_row(
                    A,
                    b,
                    g,
                    a0,
                    a1,
                    a2,
                    np.float64(normals[v, u, 0]),
                    np.float64(normals[v, u, 1]),
                    np.float64(normals[v, u, 2]),
                    r,
                    reach,
                )
                rows[g] += 1
                inliers[g] += 1
        if metres_per_px > 0 and q2 > 0 and np.isfinite(flow_px[i, 0]):
            # Where the point projects against where the flow took it (metres-equivalent), and the
            # gradients of the projected column (gu) and row (gv) per metre of motion.
            du = (fx * q0 / q2 + cx - flow_px[i, 0]) * metres_per_px
            dv = (fy * q1 / q2 + cy - flow_px[i, 1]) * metres_per_px
            gu0, gu2 = fx / q2 * metres_per_px, -fx * q0 / q2**2 * metres_per_px
            gv1, gv2 = fy / q2 * metres_per_px, -fy * q1 / q2**2 * metres_per_px
            e0, e1 = across[i, 0], across[i, 1]
            if np.isfinite(e0):  # an edge point: across the edge only
                r = du * e0 + dv * e1
                if abs(r) < reach:
                    _add_row(A, b, g, a0, a1, a2, gu0 * e0, gv1 * e1, gu2 * e0 + gv2 * e1, r, reach)
                    rows[g] += 1
            else:
                if abs(du) < reach:
                    _add_row(A, b, g, a0, a1, a2, gu0, 0.0, gu2, du, reach)
                    rows[g] += 1
                if abs(dv) < reach:
                    _add_row(A, b, g, a0, a1, a2, 0.0, gv1, gv2, dv, reach)
                    rows[g] += 1


@njit(cache=True, nogil=True)
def group_centres(points, index, groups, every, min_thinned, centre, thin):
    """``centre`` (G, 3) := the centroid of each group's points (0 for an empty group), the points
    being ``points[index]`` and ``groups`` (M,) the group of each; ``thin`` (M,) := the entries the
    coarse ICP iterations use: every ``every``-th of its group, in order, or every entry of a group of
    fewer than ``min_thinned``. Sums in the order of ``index``, as np.bincount's."""
    G = centre.shape[0]
    count = np.zeros(G, np.int64)
    rank = np.empty(index.shape[0], np.int64)
    centre[:] = 0.0
    for k in range(index.shape[0]):
        g = groups[k]
        rank[k] = count[g]
        count[g] += 1
        for d in range(3):
            centre[g, d] += points[index[k], d]
    for g in range(G):
        for d in range(3):
            centre[g, d] /= max(count[g], 1)
    for k in range(index.shape[0]):
        thin[k] = rank[k] % every == 0 or count[groups[k]] < min_thinned


@njit(cache=True, nogil=True)
def icp_kernel(
    points,
    index,
    groups,
    T,
    centre,
    thin,
    reaches,
    depth,
    normals,
    camera,
    flow_px,
    across,
    metres_per_px,
    damping,
    min_points,
    inliers,
):
    """The iterations of :func:`.projective.icp`; T (G, 4, 4) and inliers (G,) are updated in place."""
    G = T.shape[0]
    A = np.zeros((G, 6, 6))
    b = np.zeros((G, 6))
    rows = np.zeros(G, np.int64)
    everything = np.ones(index.shape[0], np.bool_)
    can_thin = not thin.all()
    for reach in reaches:
        use = thin if (reach > 2 * reaches[-1] and can_thin) else everything
        _normal_equations(
            points,
            index,
            groups,
            T,
            centre,
            use,
            reach,
            depth,
            normals,
            camera,
            flow_px,
            across,
            metres_per_px,
            A,
            b,
            rows,
            inliers,
        )
        if (rows < min_points).all():
            break
        for g in range(G):
            if rows[g] < min_points:
                continue
            M = A[g].copy()
            trace = 0.0
            for x in range(6):
                trace += M[x, x]
                for y in range(x):
                    M[x, y] = M[y, x]
            for x in range(6):
                M[x, x] += damping * trace + 1e-12
            step = -np.linalg.solve(M, b[g].copy())
            R = _rotation(step[0], step[1], step[2])
            # A turn about the group's moved centroid c' followed by a shift: x -> R (x - c') + c' + t.
            c0, c1, c2 = _moved(T[g], centre[g, 0], centre[g, 1], centre[g, 2])
            S = np.eye(4)
            S[:3, :3] = R
            S[0, 3] = c0 - (R[0, 0] * c0 + R[0, 1] * c1 + R[0, 2] * c2) + step[3]
            S[1, 3] = c1 - (R[1, 0] * c0 + R[1, 1] * c1 + R[1, 2] * c2) + step[4]
            S[2, 3] = c2 - (R[2, 0] * c0 + R[2, 1] * c1 + R[2, 2] * c2) + step[5]
            T[g] = S @ T[g]


@njit(cache=True, nogil=True)
def finite_or_zero(depth, out):
    """``out`` (H, W) float32 := ``depth`` (H, W) where it is finite, else 0: numpy's
    ``np.where(np.isfinite(depth), depth, 0).astype(np.float32)`` in one pass."""
    for v in range(depth.shape[0]):
        for u in range(depth.shape[1]):
            x = depth[v, u]
            out[v, u] = x if np.isfinite(x) else 0


@njit(cache=True, nogil=True)
def valid_median_kernel(
    depth: np.ndarray, valid: np.ndarray, todo: np.ndarray, out: np.ndarray, radius: int, min_count: int
) -> None:
    """``out`` at the ``todo`` pixels: the median of their valid neighbours (0 if fewer than
    ``min_count``)."""
    h, w = depth.shape
    window = np.empty((2 * radius + 1) ** 2, np.float32)
    for v in range(h):
        for u in range(w):
            if not todo[v, u]:
                continue
            n = 0
            for dv in range(max(v - radius, 0), min(v + radius + 1, h)):
                for du in range(max(u - radius, 0), min(u + radius + 1, w)):
                    if valid[dv, du]:
                        x = depth[dv, du]
                        i = n  # insertion sort: at most 25 values
                        while i > 0 and window[i - 1] > x:
                            window[i] = window[i - 1]
                            i -= 1
                        window[i] = x
                        n += 1
            if n < min_count:
                out[v, u] = 0
            elif n % 2:
                out[v, u] = window[n // 2]
            else:
                out[v, u] = 0.5 * (window[n // 2 - 1] + window[n // 2])


@njit(cache=True, nogil=True)
def _mean(total, support, v, u, c):
    """The window mean of a vertex coordinate: its window's blur over its window's support, as numpy
    divides by ``np.maximum(support, 1e-6)`` in float32."""
    return total[v, u, c] / max(support[v, u], np.float32(1e-6))


@njit(cache=True, nogil=True)
def normals_kernel(
    vertices: np.ndarray,
    total: np.ndarray,
    support: np.ndarray,
    h: int,
    min_support: np.float32,
    out: np.ndarray,
) -> None:
    """``out`` (H, W, 3) of :func:`.image.normal_map` at the pixels ``h`` or more inside the border:
    the cross product of the central differences across 2 h pixels of the window means (``total``,
    the windows' blur of the vertices, over ``support``, the windows' share of valid pixels), made
    unit and turned to face the camera; left as it is (0) where the vertex is missing, the product is
    0 or one of the five windows has less than ``min_support`` valid. All in float32, in numpy's order
    of operations, so the normals are numpy's to the bit."""
    rows, cols = support.shape
    tiny = np.float32(1e-12)
    for v in range(h, rows - h):
        for u in range(h, cols - h):
            if not (
                vertices[v, u, 2] > 0
                and support[v, u] >= min_support
                and support[v, u + h] >= min_support
                and support[v, u - h] >= min_support
                and support[v + h, u] >= min_support
                and support[v - h, u] >= min_support
            ):
                continue
            dx0 = _mean(total, support, v, u + h, 0) - _mean(total, support, v, u - h, 0)
            dx1 = _mean(total, support, v, u + h, 1) - _mean(total, support, v, u - h, 1)
            dx2 = _mean(total, support, v, u + h, 2) - _mean(total, support, v, u - h, 2)
            dy0 = _mean(total, support, v + h, u, 0) - _mean(total, support, v - h, u, 0)
            dy1 = _mean(total, support, v + h, u, 1) - _mean(total, support, v - h, u, 1)
            dy2 = _mean(total, support, v + h, u, 2) - _mean(total, support, v - h, u, 2)
            n0 = dx1 * dy2 - dx2 * dy1
            n1 = dx2 * dy0 - dx0 * dy2
            n2 = dx0 * dy1 - dx1 * dy0
            length = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            if not length > 0:
                continue
            length = max(length, tiny)
            n0, n1, n2 = n0 / length, n1 / length, n2 / length
            if n0 * vertices[v, u, 0] + n1 * vertices[v, u, 1] + n2 * vertices[v, u, 2] > 0:
                n0, n1, n2 = -n0, -n1, -n2
            out[v, u, 0], out[v, u, 1], out[v, u, 2] = n0, n1, n2


@njit(cache=True, nogil=True)
def _kabsch_into(source, target, keep, lo, hi, T):
    """``T`` (4, 4) := the rigid motion that best maps the kept ``source[lo:hi]`` onto
    ``target[lo:hi]`` (least squares); the identity when none is kept."""
    cs, ct = np.zeros(3), np.zeros(3)
    count = 0
    for i in range(lo, hi):
        if keep[i]:
            count += 1
            for d in range(3):
                cs[d] += source[i, d]
                ct[d] += target[i, d]
    T[:] = 0.0
    for d in range(4):
        T[d, d] = 1.0
    if count == 0:
        return
    cs /= count
    ct /= count
    H = np.zeros((3, 3))
    for i in range(lo, hi):
        if keep[i]:
            for a in range(3):
                s = source[i, a] - cs[a]
                for b in range(3):
                    H[a, b] += s * (target[i, b] - ct[b])
    U, _, Vt = np.linalg.svd(H)
    V = Vt.T.copy()
    V[:, 2] *= np.sign(np.linalg.det(V @ U.T))
    R = V @ U.T
    T[:3, :3] = R
    T[:3, 3] = ct - R @ cs


@njit(cache=True, nogil=True)
def distinct_kernel(T, moment, tolerance, keep):
    """``keep`` (H,) := the motions ``T`` (H, 3, 4) that no earlier kept one is within ``tolerance``
    of: the RMS of (T_i - T_j) x over points x of second moment ``moment`` (4, 4), homogeneous."""
    keep[:] = False
    for i in range(T.shape[0]):
        far = True
        for j in range(i):
            if not keep[j]:
                continue
            total = 0.0
            for a in range(3):
                for k in range(4):
                    dk = T[i, a, k] - T[j, a, k]
                    for m in range(4):
                        total += dk * moment[k, m] * (T[i, a, m] - T[j, a, m])
            if not np.sqrt(max(total, 0.0)) > tolerance:
                far = False
                break
        keep[i] = far


@njit(cache=True, nogil=True)
def quantile(values, q):
    """``np.quantile(values, q)`` (linear interpolation, numpy's own formula)."""
    ranked = np.sort(values)
    virtual = (len(ranked) - 1) * q
    low = int(np.floor(virtual))
    gamma = virtual - low
    a, b = ranked[low], ranked[min(low + 1, len(ranked) - 1)]
    diff = b - a
    return b - diff * (1 - gamma) if gamma >= 0.5 else a + diff * gamma


@njit(cache=True, nogil=True)
def robust_kabsch_kernel(source, target, start, inlier_m, rounds, first_share, T):
    """The fits of :func:`.projective.robust_kabsch`, one group at a time: ``T`` (G, 4, 4) is filled.
    The pairs are sorted by group, and group g's start at ``start[g]``."""
    G, N = len(start), len(source)
    keep = np.ones(N, np.bool_)
    err = np.empty(N)
    for g in range(G):
        lo, hi = start[g], start[g + 1] if g + 1 < G else N
        _kabsch_into(source, target, keep, lo, hi, T[g])
        for r in range(rounds):
            for i in range(lo, hi):
                q0, q1, q2 = _moved(T[g], source[i, 0], source[i, 1], source[i, 2])
                e0, e1, e2 = q0 - target[i, 0], q1 - target[i, 1], q2 - target[i, 2]
                err[i] = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
            # Only the first fit is on every pair: afterwards the inliers of the last fit.
            limit = max(inlier_m, quantile(err[lo:hi], first_share)) if r == 0 else inlier_m
            n_new, changed = 0, False
            for i in range(lo, hi):
                new = err[i] <= limit
                n_new += new
                changed |= new != keep[i]
            if n_new < 3 or not changed:
                break
            for i in range(lo, hi):
                keep[i] = err[i] <= limit
            _kabsch_into(source, target, keep, lo, hi, T[g])
