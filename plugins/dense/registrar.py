"""The ``dense`` registrar: rigid-motion hypotheses for a whole pair, and every point's evidence.

1. Optical flow gives, on texture, where each source point went (3D correspondences through the
   target's depth).
2. The object's motion: projective point-to-plane ICP of all points, coarse to fine, from the
   identity, from the shift of the median point and from the flow's motion.
3. Local motions, seeded from the paper's grid cells (edge x = diameter / ``cells_per_diameter``):
   each cell's flow motion (or the object's), refined by ICP on the cell's points; all cells at once.
4. Every hypothesis is scored on every point (:func:`~.projective.look`, and the flow), and the
   motions a default selection picks are refitted on the points they explain; a motion is also fitted
   to the points none of them explains (a part that spans several cells). Near-copies are dropped.
5. The hypotheses are scored the other way round too: every target point, moved by each motion's
   inverse, against the source image. A part sliding out of a still base leaves surface where the
   base's own motion says there should be none; only this direction sees that.

The result (:class:`~artclass_core.types.MotionEvidence`) holds no decision: a rule selects from it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from artclass_core import Cloud, MotionEvidence, PairRegistrar, Params, param
from artclass_core.geometry import transform
from artclass_core.types import SURFACE

from .flow import flow_targets
from .image import noise_m
from .projective import Target, icp, look, robust_kabsch
from .rule import DenseRuleParams, point_costs, regions, select

_MIN_FLOW_MATCHES = 6


@dataclass(frozen=True)
class DenseParams(Params):
    depth_noise_m: float = param(0.0015, unit="m", bounds=(1e-5, 0.05),
                                 help="Depth noise (one sigma) of the sensor at 1 m, growing with the depth squared: "
                                      "the floor of the noise measured on each pair, and the scale of ICP's reach.")
    reach_sigmas: float = param(10.0, unit="sigma", bounds=(1.0, 100.0),
                                help="A moved point within this many noise sigmas (plus two pixels) of the observed "
                                     "depth is on that surface; farther in front, it is hidden; farther behind, "
                                     "the camera sees through where it should be.")
    cells_per_diameter: float = param(5.0, unit="1", bounds=(1.0, 50.0),
                                      help="Local motions are seeded from cells of edge diameter / this (the paper's "
                                           "x = D/5).")
    min_seed_points: int = param(16, unit="points", bounds=(6, 10000),
                                 help="A cell with fewer points seeds no motion.")
    use_flow: bool = param(True, help="Use optical flow on textured surfaces (sees motion along a surface).")
    min_texture: float = param(16.0, unit="(grey/px)^2", bounds=(0.0, 1e4),
                               help="Flow is used where the smaller structure-tensor eigenvalue reaches this "
                                    "(two-dimensional texture).")
    max_roundtrip_px: float = param(1.0, unit="px", bounds=(0.1, 20.0),
                                    help="Flow is used where the backward flow brings a point back within this.")
    refine_rounds: int = param(1, unit="rounds", bounds=(0, 10),
                               help="Rounds of refitting the selected motions on the points they explain.")


class DenseRegistrar(PairRegistrar):
    """Motion hypotheses for the whole pair, from projective ICP and optical flow (see module docstring)."""

    name = "dense"
    description = "dense motion hypotheses for a whole pair: projective ICP, flow, per-point evidence (default)"
    Params = DenseParams

    def register_pair(self, source: Cloud, target: Cloud) -> MotionEvidence:
        t0 = time.perf_counter()
        p = self.params
        tgt = Target.of(target)
        points = source.points
        depth = float(np.median(points[:, 2]))
        pixel_m = depth / tgt.intrinsics.fx
        sigma0 = float(noise_m(depth, p.depth_noise_m))
        reach = self._reach(points, tgt.intrinsics.fx)
        fine = 4 * sigma0 + 2 * pixel_m
        size = float(np.linalg.norm(np.ptp(points, axis=0)))
        coarse = [max(size / d, fine) for d in (4, 4, 8, 8, 16, 16, 32)] + [fine] * 3

        # Residuals compare two smoothed surfaces: the noise left in each, added in quadrature.
        noise = max(np.sqrt(2) * max(c.info.get("smoothed_noise_m", 0.0) for c in (source, target)), sigma0)
        rule = DenseRuleParams()
        no_flow = np.full((len(points), 2), np.nan)
        flow_px, across = (flow_targets(source, target, min_texture=p.min_texture, max_roundtrip_px=p.max_roundtrip_px)
                           if p.use_flow else (no_flow, no_flow))
        matched, matches = _flow_points(flow_px, tgt)
        matched &= ~np.isfinite(across[:, 0])          # 3D matches only where the flow is known in full

        shift = np.eye(4)
        shift[:3, 3] = np.median(target.points, axis=0) - np.median(points, axis=0)
        inits = [np.eye(4), shift]
        if matched.sum() >= _MIN_FLOW_MATCHES:
            inits.append(robust_kabsch(points[matched], matches[matched], inlier_m=fine))
        fit = _Fit(tgt, flow_px, across, noise / rule.flow_sigma_px)
        whole = fit.each(points, np.stack(inits), coarse)
        hyps, names = [np.eye(4), *whole], ["identity", "object", "object (shift)", "object (flow)"][:1 + len(whole)]

        cells = _cells(points, size / p.cells_per_diameter, p.min_seed_points)
        if cells.max() >= 0:
            seeds = []
            best_whole = whole[-1]
            for c in range(cells.max() + 1):
                own = (cells == c) & matched
                seeds.append(robust_kabsch(points[own], matches[own], inlier_m=fine)
                             if own.sum() >= _MIN_FLOW_MATCHES else best_whole)
            used = cells >= 0
            local = fit(points, np.flatnonzero(used), cells[used], np.stack(seeds), coarse[1:])
            hyps += list(local)
            names += [f"cell {c}" for c in range(len(local))]

        hyps, names = _distinct(hyps, names, points, sigma0)
        status, residual = _look_all(hyps, points, tgt, reach)
        flow_err = _flow_errors(hyps, points, flow_px, across, tgt)

        for r in range(p.refine_rounds):
            ev = MotionEvidence(np.stack(hyps), names, residual, status, flow_err, noise, points, source.pixels,
                                pixel_m, dict(stride_px=int(source.info.get("stride_px", 1))))
            new, new_names = self._refits(ev, fit, rule, r, coarse)
            if not new:
                break
            n_before = len(hyps)
            hyps, names = _distinct(hyps + new, names + new_names, points, sigma0)
            if len(hyps) == n_before:
                break
            more_status, more_residual = _look_all(hyps[n_before:], points, tgt, reach)
            status, residual = np.vstack([status, more_status]), np.vstack([residual, more_residual])
            flow_err = np.vstack([flow_err, _flow_errors(hyps[n_before:], points, flow_px, across, tgt)])
        # The other way round: each target point moved by each motion's inverse onto the source image.
        back = Target.of(source)
        inverse = [np.linalg.inv(T) for T in hyps]
        status_back, residual_back = _look_all(inverse, target.points, back, self._reach(target.points, back.intrinsics.fx))
        info = dict(stride_px=int(source.info.get("stride_px", 1)), n_flow=int(matched.sum()),
                    n_points=len(points), seconds=round(time.perf_counter() - t0, 4))
        return MotionEvidence(np.stack(hyps), names, np.hstack([residual, residual_back]),
                              np.hstack([status, status_back]),
                              np.hstack([flow_err, np.full(status_back.shape, np.nan, np.float32)]), noise,
                              np.vstack([points, target.points]), np.vstack([source.pixels, target.pixels]),
                              pixel_m, info, n_source=len(points))

    def _reach(self, points: np.ndarray, fx: float) -> np.ndarray:
        """How far from the observed depth each moved point still counts as on that surface (metres):
        ``reach_sigmas`` noise sigmas at its depth, plus two pixels."""
        return self.params.reach_sigmas * noise_m(points[:, 2], self.params.depth_noise_m) + 2 * points[:, 2] / fx

    def _refits(self, ev: MotionEvidence, fit: _Fit, rule: DenseRuleParams, round_: int,
                reach: list[float]) -> tuple[list, list]:
        """The motions a default selection picks, refitted on the points they explain; and, for each
        of the largest image regions of points that none of them explains, motions fitted to that
        region from each selected motion (coarse to fine)."""
        costs = point_costs(ev, noise_factor=rule.noise_factor, flow_sigma_px=rule.flow_sigma_px)
        seen = (ev.status == SURFACE).any(axis=0)
        if seen.sum() < self.params.min_seed_points:
            return [], []
        n = int(seen.sum())
        misfit = rule.noise_factor ** 2
        chosen = select(costs[:, seen], ev.pixels[seen], penalty=6 * np.log(n), misfit=misfit,
                        min_points=max(rule.min_part_points, int(rule.min_part_share * n)),
                        min_coherence=rule.min_coherence, stride=int(ev.info["stride_px"]))
        best = costs[chosen].min(axis=0)
        owner = np.asarray(chosen)[np.argmin(costs[chosen], axis=0)]
        members: list[np.ndarray] = []
        inits: list[np.ndarray] = []
        for h in chosen:
            own = np.flatnonzero(seen & (owner == h) & (best < misfit / 2))
            if len(own) >= self.params.min_seed_points:
                members.append(own)
                inits.append(ev.motions[h])
        for region in regions(seen & (best >= misfit), ev.pixels, int(ev.info["stride_px"]),
                               min_points=self.params.min_seed_points, most=3):
            for h in chosen:
                members.append(region)
                inits.append(ev.motions[h])
        if not inits:
            return [], []
        index = np.concatenate(members)
        groups = np.repeat(np.arange(len(members)), [len(m) for m in members])
        T = fit(ev.points, index, groups, np.stack(inits), reach)
        return list(T), [f"refit {round_}.{g}" for g in range(len(T))]


def _flow_points(flow_px: np.ndarray, tgt: Target) -> tuple[np.ndarray, np.ndarray]:
    """Which points have a flow target on the target object, and the 3D point there."""
    h, w = tgt.object_m.shape
    ok = np.isfinite(flow_px).all(axis=1)
    u = np.clip(np.rint(np.nan_to_num(flow_px[:, 0])).astype(int), 0, w - 1)
    v = np.clip(np.rint(np.nan_to_num(flow_px[:, 1])).astype(int), 0, h - 1)
    z = tgt.object_m[v, u]
    ok &= (z > 0) & (flow_px[:, 0] >= 0) & (flow_px[:, 0] < w) & (flow_px[:, 1] >= 0) & (flow_px[:, 1] < h)
    K = tgt.intrinsics
    return ok, np.column_stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z])


class _Fit:
    """Projective ICP of groups of a pair's source points, with the pair's optical flow."""

    def __init__(self, target: Target, flow_px: np.ndarray, across: np.ndarray, metres_per_px: float):
        self.target, self.flow_px, self.across, self.metres_per_px = target, flow_px, across, metres_per_px

    def __call__(self, points: np.ndarray, index: np.ndarray, groups: np.ndarray, inits: np.ndarray,
                 reach: list[float]) -> list[np.ndarray]:
        """The motions of the groups of points ``points[index]``, from ``inits``."""
        T, _ = icp(points[index], groups, inits, self.target, reach_m=reach, flow_px=self.flow_px[index],
                   across=self.across[index], metres_per_px=self.metres_per_px)
        return list(T)

    def each(self, points: np.ndarray, inits: np.ndarray, reach: list[float]) -> list[np.ndarray]:
        """All the points, from each of the initial motions."""
        index = np.tile(np.arange(len(points)), len(inits))
        return self(points, index, np.repeat(np.arange(len(inits)), len(points)), inits, reach)


def _cells(points: np.ndarray, size_m: float, min_points: int) -> np.ndarray:
    """Cell number (0..C-1) of each point on a grid of ``size_m``, -1 in cells with too few points."""
    keys = np.floor((points - points.min(axis=0)) / max(size_m, 1e-6)).astype(np.int64)
    _, cell, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    cell = cell.ravel()
    big = counts >= min_points
    number = np.full(len(counts), -1)
    number[big] = np.arange(big.sum())
    return number[cell]


def _distinct(hyps: list, names: list, points: np.ndarray, tolerance_m: float) -> tuple[list, list]:
    """The hypotheses without near-copies: a motion that puts every point within ``tolerance_m`` (RMS)
    of where an earlier one does is dropped."""
    sample = points[:: max(1, len(points) // 200)]
    T = np.stack(hyps)
    moved = np.einsum("hij,nj->hni", T[:, :3, :3], sample) + T[:, None, :3, 3]           # (H, S, 3)
    rms = np.sqrt(np.mean(np.sum(np.square(moved[:, None] - moved[None]), axis=-1), axis=-1))   # (H, H)
    keep: list[int] = []
    for i in range(len(hyps)):
        if not keep or rms[i, keep].min() > tolerance_m:
            keep.append(i)
    return [hyps[i] for i in keep], [names[i] for i in keep]


def _look_all(hyps: list, points: np.ndarray, tgt: Target, reach: np.ndarray):
    out = [look(transform(points, T), tgt, reach_m=reach, off_object_px=2.0) for T in hyps]
    return np.stack([s for s, _ in out]), np.stack([r for _, r in out])


def _flow_errors(hyps: list, points: np.ndarray, flow_px: np.ndarray, across: np.ndarray, tgt: Target) -> np.ndarray:
    """Distance (H, N) in pixels between where each motion and where the flow put each point (across
    the edge only, at an edge point)."""
    K = tgt.intrinsics
    out = np.full((len(hyps), len(points)), np.nan, np.float32)
    known = np.isfinite(flow_px).all(axis=1)
    if not known.any():
        return out
    edge = np.isfinite(across[known, 0])
    for h, T in enumerate(hyps):
        u, v = K.pixels(transform(points[known], T))
        d = np.column_stack([u - flow_px[known, 0], v - flow_px[known, 1]])
        out[h, known] = np.where(edge, np.abs(np.sum(d * np.nan_to_num(across[known]), axis=1)), np.hypot(d[:, 0], d[:, 1]))
    return out
