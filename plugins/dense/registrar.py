"""The ``dense`` registrar: rigid-motion hypotheses for a whole pair, and every point's evidence.

1. Optical flow gives, on texture, where each source point went (3D correspondences through the
   target's depth).
2. The object's motion: projective point-to-plane ICP of all points, coarse to fine, from the
   identity, from the shift of the median point and from the flow's motion; and from the first two
   again on depth alone, in case the flow misleads everywhere (stripes).
3. Local motions, seeded from the paper's grid cells (edge x = diameter / ``cells_per_diameter``):
   each cell's flow motion (or the object's), refined by ICP on the cell's points; all cells at once.
4. Every hypothesis is scored on every point (:func:`~.projective.look_all`, and the flow), and the
   motions a default selection picks are refitted on the points they explain; a motion is also fitted
   to the points none of them explains (a part that spans several cells), and, when the selection
   picks several, the whole object from each of them, with the flow and on depth alone (flow locked
   on the next stripe pulls a fit with it back). Near-copies are dropped. Where a motion and the
   flow disagree, the texture where the motion lands each point is compared with the source's
   (:class:`~.flow.Landings`): on stripes, a motion a period off lands on the same texture.
5. The hypotheses are scored the other way round too: every target point, moved by each motion's
   inverse, against the source image. A part sliding out of a still base leaves surface where the
   base's own motion says there should be none; only this direction sees that.
6. The still scene beside the object (textured, unmoved in the optical flow) shows how much the
   sensor's depth changed there by itself (:mod:`.scene`).

The result (:class:`~artclass_core.types.MotionEvidence`) holds no decision: a rule selects from it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from artclass_core import Cloud, MotionEvidence, PairRegistrar, Params, param
from artclass_core.types import SURFACE

from .flow import Landings, crop_flow, flow_targets
from .image import ImageParams, noise_m
from .projective import Target, flow_misfit, icp, kernels, look_all, robust_kabsch
from .rule import WHOLE_OBJECT, DenseRuleParams, point_costs, regions, select
from .scene import still_scene_error

_MIN_FLOW_MATCHES = 6


@dataclass(frozen=True)
class DenseParams(Params):
    reach_sigmas: float = param(
        10.0,
        unit="sigma",
        bounds=(1.0, 100.0),
        help="A moved point within this many sensor noise sigmas (the preprocessor's "
        "depth_noise_m at its depth) plus two pixels of the observed "
        "depth is on that surface; farther in front, it is hidden; farther behind, "
        "the camera sees through where it should be.",
    )
    cells_per_diameter: float = param(
        5.0,
        unit="1",
        bounds=(1.0, 50.0),
        help="Local motions are seeded from cells of edge diameter / this (the paper's x = D/5).",
    )
    min_seed_points: int = param(
        16, unit="points", bounds=(6, 10000), help="A cell with fewer points seeds no motion."
    )
    use_flow: bool = param(True, help="Use optical flow on textured surfaces (sees motion along a surface).")
    min_texture: float = param(
        16.0,
        unit="(grey/px)^2",
        bounds=(0.0, 1e4),
        help="Flow is used where the smaller structure-tensor eigenvalue reaches this "
        "(two-dimensional texture).",
    )
    max_roundtrip_px: float = param(
        1.0,
        unit="px",
        bounds=(0.1, 20.0),
        help="Flow is used where the backward flow brings a point back within this.",
    )
    refine_rounds: int = param(
        1,
        unit="rounds",
        bounds=(0, 10),
        help="Rounds of refitting the selected motions on the points they explain.",
    )


class DenseRegistrar(PairRegistrar):
    """Motion hypotheses for the whole pair, from projective ICP and optical flow (see module docstring)."""

    name = "dense"
    description = (
        "dense motion hypotheses for a whole pair: projective ICP, flow, per-point evidence (default)"
    )
    Params = DenseParams

    def register_pair(self, source: Cloud, target: Cloud) -> MotionEvidence:
        t0 = time.perf_counter()
        p = self.params
        tgt = Target.of(target)
        points = source.points
        depth = float(np.median(points[:, 2]))
        pixel_m = depth / tgt.intrinsics.fx
        sigma0 = float(noise_m(depth, _sensor_noise(source)))
        reach = self.reach(source, tgt.intrinsics.fx)
        fine = 4 * sigma0 + 2 * pixel_m
        size = float(np.linalg.norm(np.ptp(points, axis=0)))
        coarse = [max(size / d, fine) for d in (4, 4, 8, 8, 16, 16, 32)] + [fine] * 3

        # Residuals compare two smoothed surfaces: the noise left in each, added in quadrature; and
        # never below the spread of the difference of two quantisation errors (uniform, one step wide).
        noise = max(
            np.sqrt(2) * max(c.info.get("smoothed_noise_m", 0.0) for c in (source, target)),
            max(c.info.get("depth_step_m", 0.0) for c in (source, target)) / np.sqrt(6),
            sigma0,
        )
        rule = DenseRuleParams()
        no_flow = np.full((len(points), 2), np.nan)
        flow = crop_flow(source, target) if p.use_flow else None
        flow_px, across = (
            flow_targets(
                source, target, min_texture=p.min_texture, max_roundtrip_px=p.max_roundtrip_px, flow=flow
            )
            if p.use_flow
            else (no_flow, no_flow)
        )
        landings = (
            Landings(source, target, flow_px, beyond_px=rule.noise_factor * rule.flow_sigma_px)
            if p.use_flow
            else None
        )
        matched, matches = _flow_points(flow_px, tgt)
        matched &= ~np.isfinite(across[:, 0])  # 3D matches only where the flow is known in full

        shift = np.eye(4)
        shift[:3, 3] = np.median(target.points, axis=0) - np.median(points, axis=0)
        inits = [np.eye(4), shift]
        if matched.sum() >= _MIN_FLOW_MATCHES:
            inits.append(robust_kabsch(points[matched], matches[matched], inlier_m=fine))
        fit, depth_fit = (
            _Fit(tgt, flow_px, across, noise / rule.flow_sigma_px),
            _Fit(tgt, no_flow, no_flow, 0.0),
        )
        starts = np.stack(inits)
        whole = fit.each(points, starts, coarse)
        # The object's motion from depth alone too: flow on stripes can mislead the fit as a whole (a
        # helical stripe on a turning can seems to travel along its axis).
        depth_only = depth_fit.each(points, starts[:2], coarse)
        kinds = ["", " (shift)", " (flow)"][: len(whole)] + [" (depth)", " (depth, shift)"]
        hyps = np.concatenate([np.eye(4)[None], whole, depth_only])
        names = ["identity"] + [f"{WHOLE_OBJECT}{k}" for k in kinds]

        cells = _cells(points, size / p.cells_per_diameter, p.min_seed_points)
        if cells.max() >= 0:
            # Each cell's flow motion where it has enough matches (all such cells at once), else the object's.
            n_cells = cells.max() + 1
            seeds = np.repeat(whole[-1][None], n_cells, axis=0)
            own = matched & (cells >= 0)
            flowing = np.flatnonzero(np.bincount(cells[own], minlength=n_cells) >= _MIN_FLOW_MATCHES)
            if len(flowing):
                number = np.full(n_cells, -1)
                number[flowing] = np.arange(len(flowing))
                own &= number[cells] >= 0
                seeds[flowing] = robust_kabsch(
                    points[own], matches[own], inlier_m=fine, groups=number[cells[own]]
                )
            used = cells >= 0
            local = fit(points, np.flatnonzero(used), cells[used], seeds, coarse[1:])
            hyps = np.concatenate([hyps, local])
            names += [f"cell {c}" for c in range(len(local))]

        hyps, names = _distinct(hyps, names, points, sigma0)
        status, residual = _look_all(hyps, points, tgt, reach)
        flow_err, grey = _flow_errors(hyps, points, flow_px, across, tgt, landings)

        for r in range(p.refine_rounds):
            ev = MotionEvidence(
                hyps,
                names,
                residual,
                status,
                flow_err,
                noise,
                points,
                source.pixels,
                pixel_m,
                dict(stride_px=int(source.info.get("stride_px", 1))),
            )
            new, new_names = self._refits(ev, (fit, depth_fit), rule, r, coarse)
            if not len(new):
                break
            n_before = len(hyps)
            hyps, names = _distinct(np.concatenate([hyps, new]), names + new_names, points, sigma0)
            if len(hyps) == n_before:
                break
            more_status, more_residual = _look_all(hyps[n_before:], points, tgt, reach)
            status, residual = np.vstack([status, more_status]), np.vstack([residual, more_residual])
            more_err, more_grey = _flow_errors(hyps[n_before:], points, flow_px, across, tgt, landings)
            flow_err, grey = np.vstack([flow_err, more_err]), np.vstack([grey, more_grey])
        # The other way round: each target point moved by each motion's inverse onto the source image.
        back = Target.of(source)
        inverse = np.linalg.inv(hyps)
        status_back, residual_back = _look_all(
            inverse, target.points, back, self.reach(target, back.intrinsics.fx)
        )
        info = dict(
            stride_px=int(source.info.get("stride_px", 1)),
            n_flow=int(matched.sum()),
            n_points=len(points),
            seconds=round(time.perf_counter() - t0, 4),
        )
        if landings is not None:
            info["flow_grey"] = landings.flow_grey
        return MotionEvidence(
            hyps,
            names,
            np.hstack([residual, residual_back]),
            np.hstack([status, status_back]),
            np.hstack([flow_err, np.full(status_back.shape, np.nan, np.float32)]),
            noise,
            np.vstack([points, target.points]),
            np.vstack([source.pixels, target.pixels]),
            pixel_m,
            info,
            n_source=len(points),
            landing_grey=np.hstack([grey, np.full(status_back.shape, np.nan, np.float32)]),
            scene_error_m=still_scene_error(
                source,
                target,
                flow,
                lambda z: self.reach_at(z, source, tgt.intrinsics.fx),
                still_px=rule.flow_sigma_px,
                spread_px=rule.noise_lag_rad * tgt.intrinsics.fx,
            ),
        )

    def reach(self, cloud: Cloud, fx: float) -> np.ndarray:
        """How far from the observed depth each moved point of ``cloud`` still counts as on that surface
        (metres): ``reach_sigmas`` sensor noise sigmas at its depth, plus two pixels."""
        return self.reach_at(cloud.points[:, 2], cloud, fx)

    def reach_at(self, z: np.ndarray, cloud: Cloud, fx: float) -> np.ndarray:
        """The same at depths ``z`` (metres), with ``cloud``'s sensor noise."""
        return self.params.reach_sigmas * noise_m(z, _sensor_noise(cloud)) + 2 * z / fx

    def _refits(
        self,
        ev: MotionEvidence,
        fits: tuple[_Fit, _Fit],
        rule: DenseRuleParams,
        round_: int,
        reach: list[float],
    ) -> tuple[np.ndarray, list]:
        """The motions a default selection picks, refitted on the points they explain; for each of the
        largest image regions of points that none of them explains, motions fitted to that region
        from each selected motion; and, when it picks several, the whole object's from each of them,
        with the flow and on depth alone (coarse to fine). ``fits``: the fit with the flow and the fit
        on depth alone."""
        fit, depth_fit = fits
        costs = point_costs(ev, noise_factor=rule.noise_factor, flow_sigma_px=rule.flow_sigma_px)
        seen = (ev.status == SURFACE).any(axis=0)
        if seen.sum() < self.params.min_seed_points:
            return np.empty((0, 4, 4)), []
        n = int(seen.sum())
        misfit = rule.noise_factor**2
        chosen = select(
            costs[:, seen],
            ev.pixels[seen],
            penalty=6 * np.log(n),
            misfit=misfit,
            min_points=max(rule.min_part_points, int(rule.min_part_share * n)),
            min_coherence=rule.min_coherence,
            stride=int(ev.info["stride_px"]),
            min_still_points=rule.min_part_points,
        )
        best = costs[chosen].min(axis=0)
        owner = np.asarray(chosen)[np.argmin(costs[chosen], axis=0)]
        members: list[np.ndarray] = []
        inits: list[np.ndarray] = []
        whole: list[bool] = []
        for h in chosen:
            own = np.flatnonzero(seen & (owner == h) & (best < misfit / 2))
            if len(own) >= self.params.min_seed_points:
                members.append(own)
                inits.append(ev.motions[h])
                whole.append(False)
        if len(chosen) > 1:
            # The whole object from each selected motion: one rigid motion may explain what two
            # poor fits split between them.
            everything = np.flatnonzero(seen)
            for h in chosen:
                members.append(everything)
                inits.append(ev.motions[h])
                whole.append(True)
        for region in regions(
            seen & (best >= misfit),
            ev.pixels,
            int(ev.info["stride_px"]),
            min_points=self.params.min_seed_points,
            most=3,
        ):
            for h in chosen:
                members.append(region)
                inits.append(ev.motions[h])
                whole.append(False)
        if not inits:
            return np.empty((0, 4, 4)), []
        index = np.concatenate(members)
        groups = np.repeat(np.arange(len(members)), [len(m) for m in members])
        T = fit(ev.points, index, groups, np.stack(inits), reach)
        names = [f"refit {round_}.{g}" for g in range(len(T))]
        names = [f"{WHOLE_OBJECT} ({name})" if w else name for name, w in zip(names, whole)]
        if len(chosen) > 1:
            # Flow on stripes can pull the whole object's fit back to the motion it was selected for
            # (a striped ruler or banana carried along its length: the flow locks on the next stripe).
            on_depth = depth_fit.each(ev.points, ev.motions[chosen], reach, among=np.flatnonzero(seen))
            T = np.concatenate([T, on_depth])
            names += [f"{WHOLE_OBJECT} (depth, refit {round_}.{g})" for g in range(len(on_depth))]
        return T, names


def _sensor_noise(cloud: Cloud) -> float:
    """The sensor's depth noise at 1 m (metres) that the preprocessor assumed for ``cloud``."""
    return float(cloud.info.get("depth_noise_m", ImageParams.depth_noise_m))


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

    def __call__(
        self, points: np.ndarray, index: np.ndarray, groups: np.ndarray, inits: np.ndarray, reach: list[float]
    ) -> np.ndarray:
        """The motions (G, 4, 4) of the groups of points ``points[index]``, from ``inits``."""
        T, _ = icp(
            points,
            groups,
            inits,
            self.target,
            reach_m=reach,
            flow_px=self.flow_px,
            across=self.across,
            metres_per_px=self.metres_per_px,
            index=index,
        )
        return T

    def each(
        self, points: np.ndarray, inits: np.ndarray, reach: list[float], *, among: np.ndarray | None = None
    ) -> np.ndarray:
        """All the points (or those indexed by ``among``), from each of the initial motions."""
        among = np.arange(len(points)) if among is None else among
        index = np.tile(among, len(inits))
        return self(points, index, np.repeat(np.arange(len(inits)), len(among)), inits, reach)


def _cells(points: np.ndarray, size_m: float, min_points: int) -> np.ndarray:
    """Cell number (0..C-1) of each point on a grid of ``size_m``, -1 in cells with too few points."""
    keys = np.floor((points - points.min(axis=0)) / max(size_m, 1e-6)).astype(np.int64)
    span = keys.max(axis=0) + 1
    # One integer per cell, in the order of its (x, y, z) keys: np.unique of rows is much slower.
    key = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
    _, cell, counts = np.unique(key, return_inverse=True, return_counts=True)
    cell = cell.ravel()
    big = counts >= min_points
    number = np.full(len(counts), -1)
    number[big] = np.arange(big.sum())
    return number[cell]


def _distinct(
    hyps: np.ndarray, names: list, points: np.ndarray, tolerance_m: float
) -> tuple[np.ndarray, list]:
    """The hypotheses (H, 4, 4) without near-copies: a motion that puts every point within
    ``tolerance_m`` (RMS) of where an earlier one does is dropped."""
    sample = points[:: max(1, len(points) // 200)]
    x = np.column_stack([sample, np.ones(len(sample))])
    moment = x.T @ x / len(x)  # (4, 4) second moment: the mean of |(T_i - T_j) x|^2 follows from it
    keep = np.empty(len(hyps), np.bool_)
    kernels().distinct_kernel(np.ascontiguousarray(hyps[:, :3]), moment, float(tolerance_m), keep)
    return hyps[keep], [n for n, k in zip(names, keep) if k]


def _look_all(hyps: np.ndarray, points: np.ndarray, tgt: Target, reach: np.ndarray):
    return look_all(hyps, points, tgt, reach_m=reach, off_object_px=2.0)


def _flow_errors(
    hyps: np.ndarray,
    points: np.ndarray,
    flow_px: np.ndarray,
    across: np.ndarray,
    tgt: Target,
    landings: Landings | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Distance (H, N) in pixels between where each motion and where the flow put each point (across
    the edge only, at an edge point; NaN where the flow is unknown); and, where they disagree, how
    unlike the source's texture the texture is where the motion lands the point (:class:`~.flow.Landings`)."""
    misfit = flow_misfit(hyps, points, flow_px, across, tgt.intrinsics)
    if landings is None:
        return misfit, np.full(misfit.shape, np.nan, np.float32)

    def landing(h: np.ndarray, i: np.ndarray) -> np.ndarray:
        q = np.einsum("mij,mj->mi", hyps[h, :3, :3], points[i]) + hyps[h, :3, 3]
        return np.column_stack(tgt.intrinsics.pixels(q))

    return misfit, landings(misfit, landing)
