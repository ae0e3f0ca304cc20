"""The default decision rule: count the distinct motions that the data needs, judged in metres.

The paper's rule bins each cell's (q, t) and counts bins. On real depth noise that splits one motion
over many bins: a cell's transform is expressed about the camera origin (a 0.5 degree error becomes
several millimetres of translation), ICP slides freely on flat or cylindrical cells, and bin edges
fall anywhere. This rule asks instead how many rigid motions are needed to *explain the points*.

For a pair (i, i + k):

1. Hypotheses: the identity, a whole-object ICP, and every matched cell's own ICP transform.
2. Every hypothesis h is scored on every cell c by the share of c's points that h brings within
   tau of the target surface (point-to-plane distance to the nearest target point, or the plain
   distance where no target point is near). tau is noise-scaled: ``noise_factor`` times the robust
   residual of the cells under their own motion, never below ``noise_floor_m``.
3. h *explains* c when its score is within ``explain_margin`` of the best score any hypothesis gets
   on c. A flat or cylindrical cell is explained by every motion that keeps its surface in place,
   so such cells constrain the answer but cannot by themselves create a new motion; the comparison
   with the cell's best score makes the test relative to what occlusion leaves achievable.
   Cells that no hypothesis explains well (best score < ``min_cell_score``) carry no evidence.
4. NM when the identity explains a share ``static_share`` of the informative points.
5. Otherwise a greedy cover: take the hypothesis that explains most points, refit it by ICP on the
   points it explains, remove them, and repeat. A further motion counts only with support of at
   least ``min_part_cells`` cells and ``min_part_share`` of the informative points (a lone outlier
   cell is not a part).
6. Cross-explanation: with two or more motions, a single ICP refit on all the informative points is
   tried from each motion; if one rigid motion explains the supposed parts as well, the pair is RM.
7. Two or more supported motions: AM; one motion: RM (NM when it is the identity).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from artclass_core import CellMotion, Cloud, DecisionRule, Params, RuleDecision, param
from artclass_core.geometry import rotation_angle_rad, transform

reg = o3d.pipelines.registration


@dataclass(frozen=True)
class RobustRuleParams(Params):
    noise_floor_m: float = param(0.002, unit="m", bounds=(1e-5, 0.1),
                                 help="Smallest inlier distance tau: below this, misfit is sensor noise.")
    noise_factor: float = param(3.0, unit="sigma", bounds=(0.5, 20.0),
                                help="tau is this many robust standard deviations of the cells' residuals "
                                     "under their own motion.")
    explain_margin: float = param(0.15, unit="fraction", bounds=(0.0, 1.0),
                                  help="A motion explains a cell when its inlier share is within this of the "
                                       "best share any motion reaches on the cell.")
    min_cell_score: float = param(0.5, unit="fraction", bounds=(0.0, 1.0),
                                  help="Cells whose best inlier share is below this (occluded, out of view) "
                                       "carry no evidence.")
    static_share: float = param(0.9, unit="fraction", bounds=(0.5, 1.0),
                                help="No motion when the identity explains this share of the informative points.")
    min_part_cells: int = param(2, unit="cells", bounds=(1, 100),
                                help="A second motion needs at least this many cells of its own.")
    min_part_share: float = param(0.1, unit="fraction", bounds=(0.0, 0.5),
                                  help="A second motion needs at least this share of the informative points.")
    max_points_per_cell: int = param(48, unit="points", bounds=(4, 10000),
                                     help="Points per cell used for scoring (evenly subsampled, for speed).")


def _icp(source: np.ndarray, target: np.ndarray, target_normals: np.ndarray, init: np.ndarray,
         max_distance_m: float) -> np.ndarray:
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    tgt.normals = o3d.utility.Vector3dVector(target_normals)
    result = reg.registration_icp(src, tgt, max_distance_m, init, reg.TransformationEstimationPointToPlane(),
                                  reg.ICPConvergenceCriteria(max_iteration=30))
    return np.array(result.transformation)


class RobustRule(DecisionRule):
    __doc__ = __doc__
    name = "robust"
    description = "counts the rigid motions needed to explain the points, with noise-scaled thresholds (default)"
    Params = RobustRuleParams

    def decide(self, cells: list[CellMotion], *, source: Cloud, target: Cloud) -> RuleDecision:
        p = self.params
        matched = [n for n, c in enumerate(cells) if c.matched]
        if not matched or source.normals is None or target.normals is None:
            return RuleDecision("skipped", [None] * len(cells), reason="no matched cell with normals")
        spacing = float(source.info.get("v_m") or np.median(cKDTree(source.points).query(source.points, k=2)[0][:, 1]))
        tree = cKDTree(target.points)

        # Points used for scoring: every matched cell's source points, evenly subsampled.
        idx = [c.source_idx[np.linspace(0, len(c.source_idx) - 1, min(len(c.source_idx), p.max_points_per_cell)).astype(int)]
               for c in (cells[n] for n in matched)]
        owner = np.repeat(np.arange(len(matched)), [len(i) for i in idx])
        pts = source.points[np.concatenate(idx)]
        counts = np.bincount(owner, minlength=len(matched)).astype(float)

        def residuals(T: np.ndarray) -> np.ndarray:
            moved = transform(pts, T)
            d, j = tree.query(moved)
            normal_d = np.abs(np.einsum("ij,ij->i", moved - target.points[j], target.normals[j]))
            return np.where(d <= 2.0 * spacing, normal_d, d)

        hyps = [np.eye(4), _icp(source.points, target.points, target.normals, np.eye(4),
                                max(pair_extent(source) / 5.0, 4 * spacing))]
        hyps += [cells[n].registration.T_target_from_source for n in matched]
        res = np.stack([residuals(T) for T in hyps])                       # (H, P)

        # Noise scale from each cell's residual under its own motion.
        own = res[2 + owner, np.arange(len(owner))]
        sigma = 1.4826 * np.median(own)
        tau = max(p.noise_floor_m, p.noise_factor * sigma)

        score = _per_cell((res <= tau).astype(float), owner, counts)      # (H, C) inlier share
        best = score.max(axis=0)
        informative = best >= p.min_cell_score
        if not informative.any():
            return RuleDecision("skipped", [None] * len(cells), reason="no cell is explained by any motion",
                                info=dict(tau_m=tau))
        explains = (score >= best - p.explain_margin) & informative          # (H, C)
        weight = counts * informative
        total = weight.sum()

        clusters: list[int | None] = [None] * len(cells)
        info = dict(tau_m=round(tau, 6), sigma_m=round(float(sigma), 6), n_informative=int(informative.sum()),
                    n_hypotheses=len(hyps))
        if (explains[0] * weight).sum() >= p.static_share * total:
            for c in np.flatnonzero(informative):
                clusters[matched[c]] = 0
            return RuleDecision("NM", clusters, ["no motion"], reason="the identity explains the points", info=info)

        motions, members = self._cover(hyps, explains, weight, total, informative)
        if len(motions) >= 2:
            merged = self._single_motion(motions, members, residuals, pts, owner, counts, best, weight, target,
                                         tau, spacing)
            if merged is not None:
                motions, members = [merged[0]], [merged[1]]
                info["merged"] = True
        for m, cs in enumerate(members):
            for c in cs:
                if clusters[matched[c]] is None:
                    clusters[matched[c]] = m
        keys = [_describe(T) for T in motions]
        info.update(motions=keys, support=[float(weight[cs].sum() / total) for cs in members])
        if len(motions) >= 2:
            return RuleDecision("AM", clusters, keys, reason=f"{len(motions)} distinct motions", info=info)
        decision = "NM" if _is_identity(motions[0], pts, tau) else "RM"
        return RuleDecision(decision, clusters, keys, reason="one motion explains the points", info=info)

    def _cover(self, hyps, explains, weight, total, informative):
        """Greedy cover of the informative cells by refitted motions with enough support."""
        p = self.params
        left = informative.copy()
        motions, members = [], []
        while left.any():
            gain = (explains & left) @ weight
            h = int(np.argmax(gain))
            cs = np.flatnonzero(explains[h] & left)
            if motions and (len(cs) < p.min_part_cells or weight[cs].sum() < p.min_part_share * total):
                break
            motions.append(hyps[h])
            members.append(cs)
            left[cs] = False
        return motions, members

    def _single_motion(self, motions, members, residuals_of, pts, owner, counts, best, weight, target, tau, spacing):
        """One rigid motion that explains all the supposed parts nearly as well, if there is one."""
        p = self.params
        cells = np.concatenate(members)
        use = np.isin(owner, cells)
        total = weight[cells].sum()
        for T0 in motions:
            T = _icp(pts[use], target.points, target.normals, T0, max(4 * tau, 2 * spacing))
            share = _per_cell((residuals_of(T) <= tau)[None].astype(float), owner, counts)[0]
            explained = weight[cells][share[cells] >= best[cells] - p.explain_margin].sum()
            if explained >= (1.0 - p.min_part_share) * total:
                return T, cells
        return None


def _per_cell(values: np.ndarray, owner: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Mean of ``values`` (H, P) over each cell's points -> (H, C)."""
    out = np.zeros((values.shape[0], len(counts)))
    for h in range(values.shape[0]):
        out[h] = np.bincount(owner, weights=values[h], minlength=len(counts))
    return out / np.maximum(counts, 1)


def pair_extent(cloud: Cloud) -> float:
    return float(cloud.info.get("diameter_m") or np.linalg.norm(np.ptp(cloud.points, axis=0)))


def _is_identity(T: np.ndarray, pts: np.ndarray, tau: float) -> bool:
    return bool(np.max(np.linalg.norm(transform(pts, T) - pts, axis=1)) <= tau)


def _describe(T: np.ndarray) -> str:
    return f"{np.degrees(rotation_angle_rad(T[:3, :3])):.1f} deg, {1000 * np.linalg.norm(T[:3, 3]):.1f} mm"
