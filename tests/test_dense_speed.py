"""The dense registrar's fast paths against the plain numpy math they replace, and its registration
on a synthetic surface moved by a known motion.

The scene: an egg-crate surface (12 x 12 cm, 1 cm bumps) 0.7 m in front of a 320 x 240 camera,
textured by its own coordinates (so optical flow can follow it), in front of a wall.
"""

from __future__ import annotations

import dataclasses
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
import pytest

from artclass_core import Frame, Intrinsics
from artclass_core.geometry import transform
from artclass_core.scheduler import worker_pool
from artclass_core.types import FREE_SPACE, OCCLUDED, OFF_OBJECT, SURFACE, UNSEEN
from artclass_plugins.dense.flow import flow_targets, structure
from artclass_plugins.dense.image import (
    ImagePreprocessor,
    bounding_box,
    filter_depth,
    finite_depth,
    measured_noise,
    median_5x5,
    normal_map,
    vertex_map,
)
from artclass_plugins.dense.projective import (
    NEAR_MASK_PX,
    Target,
    _outside,
    flow_misfit,
    hypothesis_costs,
    icp,
    kabsch,
    kernels,
    look_all,
    robust_kabsch,
    warm_up,
)
from artclass_plugins.dense.registrar import DenseRegistrar, _distinct

INTR = Intrinsics(fx=300.0, fy=300.0, cx=159.5, cy=119.5, width=320, height=240)
DEPTH_M = 0.7


def _rotation(axis, angle_rad: float) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis, float) / np.linalg.norm(axis) * angle_rad)[0]


def _motion(axis=(0.3, 1.0, 0.2), angle_deg: float = 3.0, shift_m=(0.008, -0.004, 0.006)) -> np.ndarray:
    """A rigid motion about the surface's centre, ``T_target_from_source``."""
    T = np.eye(4)
    R = _rotation(axis, np.radians(angle_deg))
    centre = np.array([0.0, 0.0, DEPTH_M])
    T[:3, :3], T[:3, 3] = R, centre - R @ centre + np.asarray(shift_m)
    return T


def _frame(T: np.ndarray, index: int = 0) -> Frame:
    """The scene with the surface moved by ``T``: z-buffered points, their texture and the mask."""
    s = np.arange(-0.06, 0.06, 0.0004)
    gx, gy = np.meshgrid(s, s)
    bumps = 0.01 * np.sin(gx / 0.012) * np.cos(gy / 0.015)
    surface = transform(np.column_stack([gx.ravel(), gy.ravel(), DEPTH_M + bumps.ravel()]), T)
    wy, wx = np.meshgrid(np.arange(-0.4, 0.4, 0.003), np.arange(-0.5, 0.5, 0.003))
    wall = np.column_stack([wx.ravel(), wy.ravel(), np.full(wx.size, 1.0)])
    shade = (
        128
        + 60 * np.sin(gx.ravel() / 0.004) * np.sin(gy.ravel() / 0.006)
        + 50 * np.cos((gx.ravel() + gy.ravel()) / 0.01)
    )
    points = np.vstack([surface, wall])
    grey = np.concatenate([shade, np.full(len(wall), 90.0)])
    on_object = np.arange(len(points)) < len(surface)
    u = np.rint(INTR.fx * points[:, 0] / points[:, 2] + INTR.cx).astype(int)
    v = np.rint(INTR.fy * points[:, 1] / points[:, 2] + INTR.cy).astype(int)
    ok = (u >= 0) & (u < INTR.width) & (v >= 0) & (v < INTR.height)
    pix = (v * INTR.width + u)[ok]
    order = np.lexsort((points[ok, 2], pix))
    first = order[np.unique(pix[order], return_index=True)[1]]
    depth = np.zeros(INTR.width * INTR.height, np.float32)
    shade_img = np.zeros(INTR.width * INTR.height)
    mask = np.zeros(INTR.width * INTR.height, bool)
    depth[pix[first]] = points[ok][first, 2]
    shade_img[pix[first]] = grey[ok][first]
    mask[pix[first]] = on_object[ok][first]
    shape = (INTR.height, INTR.width)
    rgb = np.repeat(np.clip(shade_img, 0, 255).astype(np.uint8).reshape(shape)[..., None], 3, axis=2)
    return Frame(index, f"{index:06d}", rgb, depth.reshape(shape), mask.reshape(shape))


@pytest.fixture(scope="module")
def pair():
    """Source and target clouds of the surface moved by :func:`_motion`, and that motion."""
    pre = ImagePreprocessor(ImagePreprocessor.Params(max_points=2500))
    T = _motion()
    a, b = _frame(np.eye(4), 0), _frame(T, 1)
    return pre.process(a, a.mask, intrinsics=INTR), pre.process(b, b.mask, intrinsics=INTR), T


# -- the numpy reference: the same math, one array operation at a time ------------------------------


def _ref_project(points, shape):
    z = points[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(INTR.fx * points[:, 0] / z + INTR.cx)
        v = np.rint(INTR.fy * points[:, 1] / z + INTR.cy)
    inside = (z > 0) & (u >= 0) & (u < shape[1]) & (v >= 0) & (v < shape[0])
    return np.where(inside, u, 0).astype(np.intp), np.where(inside, v, 0).astype(np.intp), inside


def _ref_plane(moved, target, u, v):
    z = target.object_m[v, u]
    n = target.normals[v, u]
    y = np.column_stack([(u - INTR.cx) / INTR.fx * z, (v - INTR.cy) / INTR.fy * z, z])
    return np.einsum("ij,ij->i", moved - y, n), (z > 0) & n.any(axis=1)


def _whole_image(box, origin, shape):
    """A distance to the mask kept in a box (top-left pixel ``origin``) as a whole image: inf beyond."""
    full = np.full(shape, np.inf, np.float32)
    full[origin[0] : origin[0] + box.shape[0], origin[1] : origin[1] + box.shape[1]] = box
    return full


def _ref_look(moved, target, reach, off_px):
    u, v, inside = _ref_project(moved, target.scene_m.shape)
    scene = np.where(inside, target.scene_m[v, u], 0)
    seen = inside & (scene > 0)
    gap = scene - moved[:, 2]
    status = np.full(len(moved), UNSEEN, np.int8)
    status[seen & (gap < -reach)] = OCCLUDED
    status[seen & (gap > reach)] = FREE_SPACE
    near = seen & (np.abs(gap) <= reach)
    off = near & (_whole_image(target.outside_px, target.outside_origin, target.scene_m.shape)[v, u] > off_px)
    status[off] = OFF_OBJECT
    status[near & ~off] = SURFACE
    plane, has = _ref_plane(moved, target, u, v)
    return status, np.where(near & ~off, np.where(has, plane, -gap), np.nan).astype(np.float32)


def _ref_icp(points, groups, T, target, reaches, flow_px, across, metres_per_px, min_points=6, thinning=4):
    """Gauss-Newton point-to-plane ICP with a flow term, each group linearised about its centroid."""
    T = np.array(T, float)
    G = len(T)
    count = np.bincount(groups, minlength=G)
    centre = np.stack([np.bincount(groups, points[:, d], minlength=G) for d in range(3)], 1) / count[:, None]
    rank = np.zeros(len(groups), int)
    for g in range(G):
        rank[groups == g] = np.arange(count[g])
    thin = (rank % thinning == 0) | (count[groups] < 4 * thinning * min_points)
    for reach in reaches:
        use = thin if reach > 2 * reaches[-1] and not thin.all() else np.ones(len(points), bool)
        p, g_all = points[use], groups[use]
        moved = np.einsum("nij,nj->ni", T[g_all, :3, :3], p) + T[g_all, :3, 3]
        u, v, inside = _ref_project(moved, target.scene_m.shape)
        r, has = _ref_plane(moved, target, u, v)
        ok = inside & has & (np.abs(r) < reach)
        rows = [(r[ok], target.normals[v[ok], u[ok]].astype(float), moved[ok], g_all[ok])]
        f, e = flow_px[use], across[use]
        known = np.isfinite(f[:, 0]) & (moved[:, 2] > 0)
        q, f, e, gk = moved[known], f[known], e[known], g_all[known]
        z = q[:, 2]
        du = INTR.fx * q[:, 0] / z + INTR.cx - f[:, 0]
        dv = INTR.fy * q[:, 1] / z + INTR.cy - f[:, 1]
        gu = np.column_stack([INTR.fx / z, 0 * z, -INTR.fx * q[:, 0] / z**2])
        gv = np.column_stack([0 * z, INTR.fy / z, -INTR.fy * q[:, 1] / z**2])
        edge = np.isfinite(e[:, 0])
        en = np.nan_to_num(e)
        for res, grad, sel in (
            (du, gu, ~edge),
            (dv, gv, ~edge),
            (du * en[:, 0] + dv * en[:, 1], gu * en[:, :1] + gv * en[:, 1:], edge),
        ):
            near = sel & (np.abs(res * metres_per_px) < reach)
            rows.append((res[near] * metres_per_px, grad[near] * metres_per_px, q[near], gk[near]))
        r, grad, at, g = (np.concatenate(x) for x in zip(*rows))
        arm = at - np.einsum("nij,nj->ni", T[g, :3, :3], centre[g]) - T[g, :3, 3]
        J = np.concatenate([np.cross(arm, grad), grad], axis=1)
        w = np.square(1 - np.square(r / reach))
        for k in range(G):
            sel = g == k
            if sel.sum() < min_points:
                continue
            A = (J[sel] * w[sel, None]).T @ J[sel]
            A += 1e-6 * np.trace(A) * np.eye(6) + 1e-12 * np.eye(6)
            x = -np.linalg.solve(A, (J[sel] * w[sel, None]).T @ r[sel])
            R = cv2.Rodrigues(x[:3])[0]
            c = T[k, :3, :3] @ centre[k] + T[k, :3, 3]
            step = np.eye(4)
            step[:3, :3], step[:3, 3] = R, c - R @ c + x[3:]
            T[k] = step @ T[k]
    return T


def _flow(source, T, rng):
    """Flow targets of the source points under ``T``, 1 px of noise, a third unknown, a third edges."""
    moved = transform(source.points, T)
    flow = np.column_stack(
        [INTR.fx * moved[:, 0] / moved[:, 2] + INTR.cx, INTR.fy * moved[:, 1] / moved[:, 2] + INTR.cy]
    ) + rng.normal(0, 1.0, (len(moved), 2))
    kind = rng.integers(0, 3, len(moved))
    flow[kind == 0] = np.nan
    angle = rng.uniform(0, np.pi, len(moved))
    across = np.where((kind == 1)[:, None], np.column_stack([np.cos(angle), np.sin(angle)]), np.nan)
    return flow, across


def test_compiled_icp_equals_the_numpy_reference(pair):
    source, target, T_true = pair
    rng = np.random.default_rng(0)
    tgt = Target.of(target)
    flow, across = _flow(source, T_true, rng)
    n = len(source)
    # Three groups: all points from the identity, all from a perturbed truth, and the left half.
    points = np.vstack([source.points] * 2 + [source.points[source.points[:, 0] < 0]])
    groups = np.repeat([0, 1, 2], [n, n, len(points) - 2 * n])
    index = np.concatenate([np.arange(n), np.arange(n), np.flatnonzero(source.points[:, 0] < 0)])
    inits = np.stack([np.eye(4), _motion(angle_deg=2.0, shift_m=(0.005, 0.0, 0.004)), np.eye(4)])
    reaches = [0.03, 0.03, 0.015, 0.008, 0.004, 0.004]
    fast, _ = icp(
        points,
        groups,
        inits,
        tgt,
        reach_m=reaches,
        flow_px=flow[index],
        across=across[index],
        metres_per_px=0.0005,
    )
    slow = _ref_icp(points, groups, inits, tgt, reaches, flow[index], across[index], 0.0005)
    assert np.abs(fast - slow).max() < 1e-9
    assert np.abs(fast - inits).max() > 1e-3  # the motions did move


def test_icp_of_indexed_points_equals_icp_of_their_copies(pair):
    """Fitting ``points[index]`` by index gives the motions of fitting the copied points, to the bit."""
    source, target, T_true = pair
    tgt = Target.of(target)
    flow, across = _flow(source, T_true, np.random.default_rng(3))
    n = len(source)
    index = np.concatenate([np.arange(n), np.flatnonzero(source.points[:, 1] < 0), np.arange(n)])
    groups = np.repeat([0, 1, 2], [n, len(index) - 2 * n, n])
    inits = np.stack([np.eye(4), np.eye(4), _motion(angle_deg=2.0, shift_m=(0.005, 0.0, 0.004))])
    common = dict(reach_m=[0.03, 0.015, 0.004], metres_per_px=0.0005)
    by_index, n_by_index = icp(
        source.points, groups, inits, tgt, flow_px=flow, across=across, index=index, **common
    )
    copied, n_copied = icp(
        source.points[index], groups, inits, tgt, flow_px=flow[index], across=across[index], **common
    )
    np.testing.assert_array_equal(by_index, copied)
    np.testing.assert_array_equal(n_by_index, n_copied)
    assert np.abs(by_index - inits).max() > 1e-3


def test_look_all_equals_the_numpy_reference(pair):
    source, target, T_true = pair
    tgt = Target.of(target)
    reach = np.full(len(source), 0.004)
    motions = np.stack([np.eye(4), T_true, _motion(angle_deg=8.0), _motion(shift_m=(0.0, 0.0, -0.05))])
    status, residual = look_all(motions, source.points, tgt, reach_m=reach, off_object_px=2.0)
    for h, T in enumerate(motions):
        ref_status, ref_residual = _ref_look(transform(source.points, T), tgt, reach, 2.0)
        np.testing.assert_array_equal(status[h], ref_status)
        np.testing.assert_allclose(residual[h], ref_residual, atol=1e-7, equal_nan=True)
    assert {SURFACE, FREE_SPACE, OCCLUDED} <= set(np.unique(status).tolist())


def _ref_normals(vertices, *, window_px=5, min_support=0.25):
    valid = (vertices[..., 2] > 0).astype(np.float32)
    k = (window_px, window_px)
    support = cv2.blur(valid, k)
    mean = cv2.blur(vertices * valid[..., None], k) / np.maximum(support, 1e-6)[..., None]
    h = window_px // 2
    dx = mean[h:-h, 2 * h :] - mean[h:-h, : -2 * h]
    dy = mean[2 * h :, h:-h] - mean[: -2 * h, h:-h]
    n = [
        dx[..., 1] * dy[..., 2] - dx[..., 2] * dy[..., 1],
        dx[..., 2] * dy[..., 0] - dx[..., 0] * dy[..., 2],
        dx[..., 0] * dy[..., 1] - dx[..., 1] * dy[..., 0],
    ]
    length = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    ok = (valid[h:-h, h:-h] > 0) & (length > 0)
    for window in (support[h:-h, h:-h], support[h:-h, 2 * h :], support[h:-h, : -2 * h]):
        ok &= window >= min_support
    ok &= (support[2 * h :, h:-h] >= min_support) & (support[: -2 * h, h:-h] >= min_support)
    n = [np.where(ok, c / np.maximum(length, 1e-12), 0).astype(np.float32) for c in n]
    centre = vertices[h:-h, h:-h]
    facing = n[0] * centre[..., 0] + n[1] * centre[..., 1] + n[2] * centre[..., 2] > 0
    sign = np.where(facing, -1, 1).astype(np.float32)
    normals = np.zeros_like(vertices)
    for axis in range(3):
        normals[h:-h, h:-h, axis] = n[axis] * sign
    return normals


def test_compiled_normals_equal_the_numpy_reference_to_the_bit():
    """The egg-crate surface with a third of its pixels lost (as a grazing sensor loses them) and a hole:
    the normals, their zeros included, are numpy's float32 arithmetic exactly."""
    frame = _frame(_motion())
    depth = np.where(frame.mask, frame.depth_m, 0).astype(np.float32)
    depth[np.random.default_rng(0).random(depth.shape) < 0.35] = 0
    depth[100:110, 150:170] = 0
    vertices = vertex_map(depth, INTR)
    got, ref = normal_map(vertices), _ref_normals(vertices)
    np.testing.assert_array_equal(got.view(np.uint32), ref.view(np.uint32))
    has = ref.any(axis=2)
    # the sparse surface keeps normals, the hole's edge does not
    assert 0.2 < has.sum() / (depth > 0).sum() < 1


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_finite_depth_equals_the_numpy_expression_to_the_bit(dtype):
    """NaN, infinities, negative zero and values that round to float32 on the way."""
    depth = np.random.default_rng(2).uniform(0.2, 3.0, (7, 9)).astype(dtype)
    depth[0, :4] = [np.nan, np.inf, -np.inf, -0.0]
    ref = np.where(np.isfinite(depth), depth, 0).astype(np.float32)
    got = finite_depth(depth)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got.view(np.uint32), ref.view(np.uint32))
    assert np.isfinite(depth[1:]).all() and not got[0, :3].any()


@pytest.mark.parametrize("use_flow", [False, True])
def test_icp_recovers_a_known_motion(pair, use_flow):
    """3 degrees and 1 cm, from the identity: within 0.5 mm at the surface."""
    source, target, T_true = pair
    flow, across = _flow(source, T_true, np.random.default_rng(1))
    reaches = [0.03, 0.03, 0.015, 0.015, 0.008, 0.004, 0.004, 0.004]
    T, inliers = icp(
        source.points,
        np.zeros(len(source), int),
        np.eye(4)[None],
        Target.of(target),
        reach_m=reaches,
        flow_px=flow if use_flow else None,
        across=across if use_flow else None,
        metres_per_px=0.0005 if use_flow else 0.0,
    )
    error = np.linalg.norm(transform(source.points, T[0]) - transform(source.points, T_true), axis=1)
    assert error.max() < 5e-4
    assert inliers[0] > 0.8 * len(source)


def test_flow_misfit_equals_the_numpy_reference(pair):
    source, _, T_true = pair
    flow, across = _flow(source, T_true, np.random.default_rng(2))
    motions = np.stack([np.eye(4), T_true, _motion(angle_deg=-4.0)])
    misfit = flow_misfit(motions, source.points, flow, across, INTR)
    edge = np.isfinite(across[:, 0])
    for h, T in enumerate(motions):
        moved = transform(source.points, T)
        d = np.column_stack(
            [
                INTR.fx * moved[:, 0] / moved[:, 2] + INTR.cx - flow[:, 0],
                INTR.fy * moved[:, 1] / moved[:, 2] + INTR.cy - flow[:, 1],
            ]
        )
        ref = np.where(edge, np.abs(np.sum(d * np.nan_to_num(across), axis=1)), np.hypot(d[:, 0], d[:, 1]))
        np.testing.assert_allclose(misfit[h], ref, rtol=1e-6, atol=1e-6)
    assert np.nanmedian(misfit[1]) < 2.0 < np.nanmedian(misfit[0])  # the true motion matches the flow


def _ref_costs(residual, status, flow, *, noise_m, flow_sigma_px, worst):
    """The plain numpy expression of the costs."""
    with np.errstate(invalid="ignore"):
        fit = np.minimum(np.square(residual / noise_m), worst)
        flow = np.minimum(np.square(flow / flow_sigma_px), worst)
    cost = np.where(status == SURFACE, fit, worst / 2)
    cost = np.where((status == FREE_SPACE) | (status == OFF_OBJECT), worst, cost)
    return (cost + np.nan_to_num(flow, nan=0.0)).astype(np.float32)


@pytest.mark.parametrize("noise_m", [0.0013, np.float64(0.0013), np.float32(0.0013)])
def test_compiled_costs_equal_the_numpy_expression_to_the_bit(noise_m):
    """Each scale as a Python float (float32 arithmetic) or a NumPy float (its own dtype's)."""
    rng = np.random.default_rng(5)
    shape = (7, 3000)
    residual = (rng.normal(0, 0.004, shape)).astype(np.float32)
    flow = np.abs(rng.normal(0, 3.0, shape)).astype(np.float32)
    status = rng.choice(np.array([SURFACE, OCCLUDED, FREE_SPACE, OFF_OBJECT, UNSEEN], np.int8), shape)
    residual[status != SURFACE] = np.nan
    residual[0, :10] = np.nan  # a surface point without a residual stays NaN
    flow[rng.random(shape) < 0.4] = np.nan
    flow[1, :5] = np.inf
    for flow_sigma in (0.7, np.float64(0.7)):
        kw = dict(noise_m=noise_m, flow_sigma_px=flow_sigma, worst=9.0)
        got, want = hypothesis_costs(residual, status, flow, **kw), _ref_costs(residual, status, flow, **kw)
        assert got.dtype == want.dtype == np.float32
        np.testing.assert_array_equal(got, want)
        assert np.isnan(got[0, :10][status[0, :10] == SURFACE]).all()


def test_distance_to_the_mask_is_exact_near_it():
    rng = np.random.default_rng(3)
    mask = np.zeros((120, 160), bool)
    mask[30:70, 50:90] = rng.random((40, 40)) < 0.7
    mask[0:5, 150:160] = True  # touching the image border
    full = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 3)
    near = full <= NEAR_MASK_PX

    def kept(mask):
        return _whole_image(*_outside(mask), mask.shape)

    np.testing.assert_allclose(kept(mask)[near], full[near], atol=1e-5)
    assert (kept(mask)[~near] > NEAR_MASK_PX).all()
    assert np.isinf(kept(np.zeros((10, 10), bool))).all()


def test_near_copies_are_dropped_as_by_their_point_distances():
    rng = np.random.default_rng(4)
    points = rng.normal([0, 0, 0.7], 0.05, (500, 3))
    hyps = [np.eye(4)] + [
        _motion(angle_deg=a, shift_m=(s, 0, 0))
        for a, s in [(0.05, 0.0), (1.0, 0.0), (0.0, 0.0005), (0.0, 0.003), (2.0, 0.01), (2.01, 0.01)]
    ]
    sample = points[:: max(1, len(points) // 200)]
    moved = [transform(sample, T) for T in hyps]
    keep: list[int] = []
    for i in range(len(hyps)):
        if (
            not keep
            or min(np.sqrt(np.mean(np.sum((moved[i] - moved[j]) ** 2, axis=1))) for j in keep) > 0.001
        ):
            keep.append(i)
    kept, names = _distinct(np.stack(hyps), [str(i) for i in range(len(hyps))], points, 0.001)
    assert names == [str(i) for i in keep]
    np.testing.assert_array_equal(kept, np.stack(hyps)[keep])
    assert 2 < len(keep) < len(hyps)


def test_the_sensor_noise_is_one_parameter_of_the_preprocessor():
    """The registrar judges reach by the noise the preprocessor was given, not a second setting."""
    assert "depth_noise_m" not in {f.name for f in dataclasses.fields(DenseRegistrar.Params)}
    frames = [_frame(np.eye(4), 0), _frame(_motion(), 1)]
    evidence = []
    for at_1m in (0.0015, 0.015):
        pre = ImagePreprocessor(ImagePreprocessor.Params(depth_noise_m=at_1m, max_points=1500))
        a, b = (pre.process(f, f.mask, intrinsics=INTR) for f in frames)
        assert a.info["depth_noise_m"] == at_1m
        evidence.append(DenseRegistrar(DenseRegistrar.Params()).register_pair(a, b))
    surface = [np.mean(ev.status[0] == SURFACE) for ev in evidence]  # the identity hypothesis
    assert surface[1] > surface[0] + 0.05  # a wider reach finds more surface


def _ref_robust_kabsch(source, target, *, inlier_m, rounds=3):
    """Robust Kabsch of one group of matches, written out plainly."""
    keep = np.ones(len(source), bool)
    T = kabsch(source, target)
    for _ in range(rounds):
        err = np.linalg.norm(source @ T[:3, :3].T + T[:3, 3] - target, axis=1)
        new = err <= max(inlier_m, np.quantile(err, 0.66) if keep.all() else inlier_m)
        if new.sum() < 3 or (new == keep).all():
            break
        keep = new
        T = kabsch(source[keep], target[keep])
    return T


def test_grouped_robust_kabsch_equals_one_fit_per_group():
    """Seven groups of matches (5 to 60 each, a fifth of them wrong), shuffled together."""
    rng = np.random.default_rng(3)
    sizes = [5, 8, 12, 20, 33, 47, 60]
    sources, targets = [], []
    for n in sizes:
        p = rng.normal(0, 0.03, (n, 3)) + [0, 0, DEPTH_M]
        T = _motion(axis=rng.normal(size=3), angle_deg=rng.uniform(0, 6), shift_m=rng.normal(0, 0.01, 3))
        q = transform(p, T) + rng.normal(0, 0.0005, (n, 3))
        wrong = rng.random(n) < 0.2
        q[wrong] += rng.normal(0, 0.02, (wrong.sum(), 3))
        sources.append(p)
        targets.append(q)
    groups = np.repeat(np.arange(len(sizes)), sizes)
    order = rng.permutation(len(groups))
    source, target, groups = np.vstack(sources)[order], np.vstack(targets)[order], groups[order]
    fits = robust_kabsch(source, target, inlier_m=0.002, groups=groups)
    for g in range(len(sizes)):
        want = _ref_robust_kabsch(sources[g], targets[g], inlier_m=0.002)
        assert np.abs(fits[g] - want).max() < 1e-9
        assert np.abs(robust_kabsch(sources[g], targets[g], inlier_m=0.002) - want).max() < 1e-9


def test_compiled_quantiles_are_numpys():
    rng = np.random.default_rng(4)
    for n in (1, 2, 3, 7, 10, 31):
        values = rng.integers(0, 4, n).astype(float) if n % 2 else rng.random(n)
        for q in (0.0, 0.25, 0.5, 0.66, 1.0):
            assert kernels().quantile(values, q) == np.quantile(values, q)


def test_structure_tensor_at_pixels_is_the_eigen_decomposition_of_the_averaged_gradients():
    """Smaller and larger eigenvalue, and the larger one's direction, of the 2 x 2 tensor of the
    gradients' products averaged over the window about each pixel, against numpy's ``eigh``."""
    rng = np.random.default_rng(5)
    gray = cv2.GaussianBlur(rng.integers(0, 256, (60, 80)).astype(np.uint8), (5, 5), 1.0)
    gray[20:40, 30:] = 200  # a flat patch and a straight edge along it
    pixels = np.column_stack([rng.integers(0, 80, 300), rng.integers(0, 60, 300)])
    small, large, angle = structure(gray, pixels, window_px=5)
    gx = cv2.Sobel(gray.astype(float), cv2.CV_64F, 1, 0, ksize=3) / 8
    gy = cv2.Sobel(gray.astype(float), cv2.CV_64F, 0, 1, ksize=3) / 8
    xx, yy, xy = (cv2.blur(m, (5, 5))[pixels[:, 1], pixels[:, 0]] for m in (gx * gx, gy * gy, gx * gy))
    values, vectors = np.linalg.eigh(np.stack([np.stack([xx, xy], -1), np.stack([xy, yy], -1)], -2))
    scale = np.maximum(values[:, 1], 1.0)
    assert np.abs(small - values[:, 0]).max() < 1e-4 * scale.max()
    assert np.abs(large - values[:, 1]).max() < 1e-4 * scale.max()
    distinct = values[:, 1] - values[:, 0] > 1e-3 * scale
    assert distinct.sum() > 200
    # The same direction up to its sign: |cos| of the angle between them is 1.
    along = np.abs(np.cos(angle) * vectors[:, 0, 1] + np.sin(angle) * vectors[:, 1, 1])
    assert np.abs(along[distinct] - 1).max() < 1e-3


def test_opencv_runs_on_one_thread_while_several_workers_do_and_gives_the_same_flow(pair):
    source, target, _ = pair
    before = cv2.getNumThreads()
    cv2.setNumThreads(4)
    try:
        many = flow_targets(source, target, min_texture=16.0, max_roundtrip_px=1.0)
        with worker_pool(1):
            assert cv2.getNumThreads() == 4
        with worker_pool(2) as pool:
            assert cv2.getNumThreads() == 1
            one = pool.submit(flow_targets, source, target, min_texture=16.0, max_roundtrip_px=1.0).result()
        assert cv2.getNumThreads() == 4
    finally:
        cv2.setNumThreads(before)
    assert np.isfinite(many[0]).any()
    for a, b in zip(many, one):
        np.testing.assert_array_equal(a, b)


def test_a_pairs_flow_does_not_depend_on_the_pairs_before_it_in_its_thread(pair):
    """Each thread reuses one DIS object; a pair's flow is the same as on a fresh thread, after the
    flow of a pair with a crop of another size."""
    source, target, _ = pair
    pre = ImagePreprocessor(ImagePreprocessor.Params(max_points=2500))
    a, b = _frame(np.eye(4), 0), _frame(_motion(angle_deg=10.0, shift_m=(0.04, 0.03, 0.1)), 1)
    other = pre.process(a, a.mask, intrinsics=INTR), pre.process(b, b.mask, intrinsics=INTR)
    assert bounding_box(b.mask) != bounding_box(target.view.mask)

    def flows(*pairs):
        return [flow_targets(s, t, min_texture=16.0, max_roundtrip_px=1.0) for s, t in pairs]

    with ThreadPoolExecutor(1) as fresh:
        (first,) = fresh.submit(flows, (source, target)).result()
    with ThreadPoolExecutor(1) as used:
        _, again = used.submit(flows, other, (source, target)).result()
    assert np.isfinite(first[0]).any()
    for x, y in zip(first, again):
        np.testing.assert_array_equal(x, y)


def test_warm_up_loads_the_compiled_loops_a_registration_runs(pair):
    """After warm_up, preprocessing a frame and registering a pair compile or load nothing more: each
    loop was loaded for the argument types the preprocessor and the registrar pass."""
    source, target, _ = pair
    warm_up()
    names = (
        "look_kernel",
        "flow_kernel",
        "icp_kernel",
        "group_centres",
        "robust_kabsch_kernel",
        "valid_median_kernel",
        "normals_kernel",
        "cost_kernel",
        "distinct_kernel",
    )
    loaded = {name: list(getattr(kernels(), name).signatures) for name in names}
    assert all(len(s) >= 1 for s in loaded.values())
    frame = _frame(np.eye(4))
    ImagePreprocessor(ImagePreprocessor.Params()).process(frame, frame.mask, intrinsics=INTR)
    DenseRegistrar(DenseRegistrar.Params()).register_pair(source, target)
    assert {name: list(getattr(kernels(), name).signatures) for name in names} == loaded


def test_noise_and_outlier_filter_from_one_median_equal_their_own():
    """The preprocessor blurs once for both the noise and the outlier filter: the same numbers as
    each computing its own median, and the shared median is left as it was."""
    rng = np.random.default_rng(5)
    depth = (0.8 + 0.003 * np.mgrid[0:50, 0:70][0] + rng.normal(0, 0.002, (50, 70))).astype(np.float32)
    valid = rng.random(depth.shape) < 0.8
    valid[:, :3] = True  # a surface that reaches the image's edge
    _, median = median_5x5(depth, valid)
    before = median.copy()
    assert measured_noise(depth, valid, median=median) == measured_noise(depth, valid) > 0
    common = dict(tolerance_m=np.full(depth.shape, 0.005, np.float32), smoothing_px=2)
    shared, own = filter_depth(depth, valid, median=median, **common), filter_depth(depth, valid, **common)
    np.testing.assert_array_equal(shared.view(np.uint32), own.view(np.uint32))
    assert 0 < (shared > 0).sum() < valid.sum()
    np.testing.assert_array_equal(median, before)
