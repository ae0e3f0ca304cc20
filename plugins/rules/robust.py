"""The default decision rule: count the distinct motions that the data needs, judged in metres.

The paper's rule bins each cell's (q, t) and counts bins. On real depth noise that splits one motion
over many bins: a cell's transform is expressed about the camera origin (a 0.5 degree error becomes
several millimetres of translation), ICP slides freely on flat or cylindrical cells, and bin edges
fall anywhere. This rule asks instead how many rigid motions are needed to *explain the points*.

For a pair (i, i + k):

1. Hypotheses: the identity; a whole-object ICP started from the identity and from the centroid
   shift (coarse to fine); the rigid fit to the optical flow (below), and both ICPs refined to agree
   with the depth and the flow together (``flow_fit``); every matched cell's own ICP transform, its
   own fit to the flow and its ICP refined with the flow; and, for each cell the best
   whole-object motion leaves unexplained, a local ICP of that cell started from that motion and
   from the identity (the paper's per-cell ICP from the identity cannot capture a carried object's
   centimetres of motion). Once the first motion is known (steps 4 and 5), the cells it leaves
   unexplained, if they have the points for a part (step 5), get motions fitted to all their points
   together, from the identity, the first motion and each cell's best, and the rigid fit and the
   plain slide their optical flow shows: a part whose cells each fit poorly on their own (a tray
   sliding out along its own faces: each small cell's fit turns where the part only slid) is one
   motion.
2. Every hypothesis h is scored on every cell c by the share of c's points that h brings within
   tau of the target surface: the residual of a moved point is its distance to the tangent plane of
   the nearest target point, or its distance to that point less one sampling step v if larger (a
   point may slide within a surface by the sampling step, not onto a neighbouring surface).
   tau is noise-scaled: ``noise_factor`` times the noise measured on the data (the
   spread of the target's points about their local planes, times sqrt(2) for two samplings of one
   surface), never below ``noise_floor_m``. Comparing motions by where they
   put the cell's points removes the rotation-translation coupling of the paper's keys.
3. h *explains* c when its share is within ``explain_margin`` of the best share any hypothesis
   reaches on c, plus two standard errors of the difference of two shares measured on c's points
   (a cell of 48 points where 3 fall beyond tau is not evidence of another motion). A flat or
   cylindrical (degenerate) cell is explained by every motion that keeps its surface in place, so
   such cells constrain the answer but cannot create a motion of their own. Cells whose best share
   is below ``min_cell_score`` (occluded, out of view) carry no evidence.
   Depth cannot see a motion along a surface (a drawer's top sliding along itself, a lever turning in
   its own plane, a globe spinning): where the colour image has texture, the optical flow says where
   a point went (see ``flow.py``; followed through the frames between i and i + k where it cannot
   jump straight), and a motion must also bring the point within tau plus the flow's own tolerance
   of that place (on an edge or a stripe, where the flow is known only across it, across the edge).
   A whole-object motion is not faulted for points that it hides behind the object's own surfaces
   (a box turning away from the camera hides its far faces); a surface in front that the motion
   does not account for (a lid swung towards the camera) is no excuse, and neither is any hidden
   point when the motion is offered as a part's (step 5).
4. When the identity explains ``static_share`` of the informative points, the object as a whole
   stood still: the identity is the cover's first motion (step 5), and the answer is NM unless a
   part moved.
5. A greedy cover: the hypothesis that explains most points, then the one that explains
   most of the rest, and so on. A further motion needs at least ``min_part_cells`` cells and
   ``min_part_share`` of the informative points: a lone outlier cell is not a part. It must also be
   distinct from the first motion (step 6); one that is not is passed over and the next best tried
   (the best fit to a few cells may be a turn no joint makes where a slide also explains them). When the object
   as a whole did not move (the first motion moves no point by more than tau), ``min_still_part_share``
   (a door seen edge-on): no motion of the object's own then hides or shows its surfaces to fake a
   part, and in step 4 a part has at most the 1 - ``static_share`` that the identity leaves.
6. Separation: a further motion that puts most of its points less than tau off the surface (or,
   where flow sees them, less than tau plus the flow's tolerance along it) from where the first
   motion puts them is not a motion of its own: the data cannot tell the two apart (a bottle turned
   7 or 8 degrees about its axis). Nor is one that moves relative to the first in a way no joint
   does (see ``joint_like``: a part slides, or turns about an axis through the object).
   Cross-explanation: with two or more motions, one ICP refit on all their points is tried from the
   identity, the whole-object motions and each motion found; if a single rigid motion explains the
   supposed parts as well, there is one motion (on a cylinder or a plane the whole-object fit may
   have slid, and a region that pins the slide then looks like a part of its own).
7. Two or more motions: AM. One motion: RM, or NM when it moves no point by more than tau
   (a motion within noise is no motion). Except when that motion (in step 4, the identity) puts a
   part's worth of cells (``min_part_cells`` and the share of step 5), matched or not, where the camera
   now sees through them: the target's depth image shows a surface well behind where their points
   would be. Then some part moved off where the data cannot follow it (a lid turned edge-on, a door
   swung out of view): AM. A part hidden behind something in front is no such evidence.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from artclass_core import CellMotion, Cloud, DecisionRule, Params, RuleDecision, param
from artclass_core.geometry import rotation_angle_rad, transform

from ..preprocessors import to_o3d
from .flow import FlowEvidence, flow_targets, kabsch

MIN_FLOW_POINTS = 6
MIN_CELL_POINTS = 8  # a cell with fewer source points says nothing of its own
JOINT_MIN_TURN_RAD, JOINT_MAX_SLIDE = np.radians(3.0), 0.1

reg = o3d.pipelines.registration
# Reproducible only with Open3D on one thread of its own, which the pipeline sets before it runs
# (artclass_core.scheduler.single_threaded_open3d).


@dataclass(frozen=True)
class RobustRuleParams(Params):
    noise_floor_m: float = param(
        0.002,
        unit="m",
        bounds=(1e-5, 0.1),
        help="Smallest inlier distance tau: below this, misfit is sensor noise.",
    )
    noise_factor: float = param(
        3.0,
        unit="sigma",
        bounds=(0.5, 20.0),
        help="tau is this many times the depth noise measured on the pair (spread of "
        "points about their local planes, times sqrt 2).",
    )
    explain_margin: float = param(
        0.05,
        unit="fraction",
        bounds=(0.0, 1.0),
        help="A motion explains a cell when its inlier share is within this, plus two "
        "standard errors of the difference of two shares, of the best share any "
        "motion reaches on the cell.",
    )
    min_cell_score: float = param(
        0.5,
        unit="fraction",
        bounds=(0.0, 1.0),
        help="Cells whose best inlier share is below this (occluded, out of view) carry no evidence.",
    )
    static_share: float = param(
        0.9,
        unit="fraction",
        bounds=(0.5, 1.0),
        help="No motion when the identity explains this share of the informative points.",
    )
    min_part_cells: int = param(
        2, unit="cells", bounds=(1, 100), help="A second motion needs at least this many cells of its own."
    )
    min_part_share: float = param(
        0.15,
        unit="fraction",
        bounds=(0.0, 0.5),
        help="A second motion needs at least this share of the informative points.",
    )
    min_still_part_share: float = param(
        0.05,
        unit="fraction",
        bounds=(0.0, 0.5),
        help="The same when the object as a whole did not move (its first motion "
        "moves no point by more than tau): no motion of its own then hides "
        "or shows its surfaces to fake a part.",
    )
    use_flow: bool = param(
        True,
        help="Use optical flow between the two colour images as evidence of motions "
        "that keep a surface in place (sliding, spinning).",
    )
    max_points_per_cell: int = param(
        48,
        unit="points",
        bounds=(4, 10000),
        help="Points per cell used for scoring (evenly subsampled, for speed).",
    )


def icp_point_to_plane(
    source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, init: np.ndarray, distances_m
) -> np.ndarray:
    """Point-to-plane ICP run coarse to fine over ``distances_m``; returns T_target_from_source.

    Solved about the source's centroid: point-to-plane ICP linearises the rotation about the origin,
    and about a camera a metre away a few degrees of turn become centimetres of coupled translation
    that the linear step gets wrong (cells then lose their correspondences).
    """
    c = source.get_center()
    shift, unshift = np.eye(4), np.eye(4)
    shift[:3, 3], unshift[:3, 3] = -c, c
    src, tgt = o3d.geometry.PointCloud(source).translate(-c), o3d.geometry.PointCloud(target).translate(-c)
    T = shift @ init @ unshift
    for d in distances_m:
        T = reg.registration_icp(
            src,
            tgt,
            d,
            T,
            reg.TransformationEstimationPointToPlane(),
            reg.ICPConvergenceCriteria(max_iteration=30),
        ).transformation
    return unshift @ np.array(T) @ shift


class RobustRule(DecisionRule):
    __doc__ = __doc__
    name = "robust"
    description = (
        "counts the rigid motions needed to explain the points, with noise-scaled thresholds (default)"
    )
    Params = RobustRuleParams
    uses_frames_between = True  # optical flow is followed from frame to frame where it cannot jump
    uses_scratch = True  # the evidence below is kept in the pair's scratch dict

    def decide(
        self,
        cells: list[CellMotion],
        *,
        source: Cloud,
        target: Cloud,
        between: tuple[Cloud, ...] = (),
        scratch: dict | None = None,
    ) -> RuleDecision:
        p = self.params
        matched = [n for n, c in enumerate(cells) if c.matched]
        if not matched or source.normals is None or target.normals is None:
            return RuleDecision("skipped", [None] * len(cells), reason="no matched cell with normals")
        # What the thresholds do not change is computed once per pair and found again on re-deciding.
        memo = {} if scratch is None else scratch
        key = (
            "robust",
            p.max_points_per_cell,
            p.use_flow,
            tuple(c.frame_index for c in between),
            tuple((cells[n].cell, id(cells[n].registration)) for n in matched),
        )
        ev = memo.get(key)
        if ev is None:
            ev = memo[key] = _Evidence(
                cells,
                matched,
                source,
                target,
                max_points=p.max_points_per_cell,
                use_flow=p.use_flow,
                between=between,
                scratch=memo,
            )
        owner, counts = ev.owner, ev.counts

        tau = max(p.noise_floor_m, p.noise_factor * ev.sigma)
        hyps = list(ev.hyps)
        score = _per_cell(ev.geo <= tau, owner, counts)  # (H, C) inlier share

        # Cells the best whole-object motion leaves unexplained get local hypotheses of their own.
        g = 1 + int(np.argmax(score[1 : ev.n_global] @ counts))
        best = score.max(axis=0)
        poor = np.flatnonzero(score[g] < np.maximum(best, p.min_cell_score) - p.explain_margin)
        extra = [ev.local(c, g) for c in poor]
        if extra:
            hyps += [T for pair in extra for T, _ in pair]
            more = np.stack([r for pair in extra for _, r in pair])
            score = np.vstack([score, _per_cell(more <= tau, owner, counts)])

        plain = _per_cell(ev.plain <= tau, owner, counts)

        def weigh(score):
            """Which motions explain which cells, and the first motion (step 4)."""
            best = score.max(axis=0)
            informative = best >= p.min_cell_score
            explains = _explains(score, best, counts, p.explain_margin) & informative  # (H, C)
            weight = counts * informative
            # When the identity explains nearly everything, the object as a whole stood still; a part may not have.
            still = (explains[0] * weight).sum() >= p.static_share * weight.sum()
            # A further motion is a part's, and only the whole object's motion may hide points behind itself:
            # a part is scored on the whole-object hypotheses without that excuse.
            as_part = explains.copy()
            as_part[: ev.n_global] = _explains(plain, best, counts, p.explain_margin) & informative
            first = 0 if still else int(np.argmax(explains @ weight))
            return best, informative, explains, weight, still, as_part, first

        # A part of an object that moved must be bigger: the object's own motion hides and shows its surfaces
        # (a mug's inner wall over its rim), which can look like a small part moving.
        def share_of(first):
            return p.min_part_share if _displacement(ev.pts, hyps[first]) > tau else p.min_still_part_share

        best, informative, explains, weight, still, as_part, first = weigh(score)
        # The cells the first motion leaves unexplained (informative or not: none may fit them yet) may be
        # one part whose cells each fit poorly on their own (a tray sliding along its faces): motions
        # fitted to all of them together, when they have the points for a part.
        left = np.flatnonzero(~explains[first] & (counts >= MIN_CELL_POINTS))
        if len(left) >= p.min_part_cells and counts[left].sum() >= share_of(first) * weight.sum():
            seeds = dict.fromkeys([0, first] + [int(np.argmax(as_part[:, c] * score[:, c])) for c in left])
            joint = ev.union(tuple(left.tolist()), [hyps[h] for h in seeds])
            hyps += [T for T, _ in joint]
            score = np.vstack([score, _per_cell(np.stack([r for _, r in joint]) <= tau, owner, counts)])
            best, informative, explains, weight, still, as_part, first = weigh(score)
        info = dict(
            tau_m=round(tau, 6),
            sigma_m=round(float(ev.sigma), 6),
            n_informative=int(informative.sum()),
            n_hypotheses=len(hyps),
        )
        clusters: list[int | None] = [None] * len(cells)
        if not informative.any():
            return RuleDecision("skipped", clusters, reason="no cell is explained by any motion", info=info)
        total = weight.sum()
        part_share = share_of(first)

        def distinct(h, cells):
            """Whether motion h is a part of its own on ``cells``: None when the data cannot tell it from
            the first motion there, False when no joint moves so."""
            A, B = hyps[first], hyps[h]
            if not ev.separated(A, B, cells, tau):
                return None
            return joint_like(A, B, ev.pts.mean(0), ev.extent)

        chosen, members, passed = self._cover(
            explains, as_part, weight, total, informative, part_share, first, distinct
        )
        motions = [hyps[h] for h in chosen]
        if passed:
            info["passed_over"] = passed
        if len(motions) >= 2:
            merged = self._single_motion(
                ev, hyps, list(range(ev.n_global)) + chosen, members, best, weight, tau, part_share
            )
            if merged is not None:
                motions, members = [merged[0]], [merged[1]]
                info["merged"] = True
        for m, cs in enumerate(members):
            for c in cs:
                clusters[matched[c]] = m
        keys = [_describe(T) for T in motions]
        info.update(motions=keys, support=[round(float(weight[cs].sum() / total), 4) for cs in members])
        if len(motions) >= 2:
            return RuleDecision("AM", clusters, keys, reason=f"{len(motions)} distinct motions", info=info)
        # Only a motion that accounts for most of the object can say that the rest went elsewhere.
        gone = self._vanished(ev, motions[0], part_share) if weight[members[0]].sum() >= 0.5 * total else []
        if len(gone):
            for n in gone:
                clusters[n] = 1
            info["seen_through"] = len(gone)
            return RuleDecision(
                "AM",
                clusters,
                keys + ["moved off"],
                info=info,
                reason=f"the camera sees through {len(gone)} cells where the motion puts them: a part moved off",
            )
        if still:
            return RuleDecision(
                "NM", clusters, ["no motion"], reason="the identity explains the points", info=info
            )
        shift_m = _displacement(ev.pts, motions[0])
        info["max_displacement_m"] = round(shift_m, 6)
        if shift_m <= tau:
            return RuleDecision("NM", clusters, keys, reason="the only motion is within noise", info=info)
        return RuleDecision("RM", clusters, keys, reason="one motion explains the points", info=info)

    def _cover(self, explains, as_part, weight, total, informative, part_share, first, distinct):
        """Greedy cover of the informative cells by motions (hypothesis indices) with enough support: the
        ``first``, then further ones (parts) by ``as_part``, each with ``part_share`` of the weight and
        ``distinct(h, cells)`` from the first (a motion that is not, because the data cannot tell it from
        the first or no joint moves so, is passed over for the next best). Returns the motions, their
        cells and how many motions were passed over."""
        p = self.params
        left, candidate = informative.copy(), np.ones(len(explains), bool)
        chosen, members = [first], [np.flatnonzero(explains[first] & left)]
        passed, n_passed = np.zeros_like(left), 0
        left[members[0]] = False
        while left.any():
            h = int(np.argmax(np.where(candidate, (as_part & left) @ weight, -1.0)))
            cs = np.flatnonzero(as_part[h] & left)
            if len(cs) < p.min_part_cells or weight[cs].sum() < part_share * total:
                break
            candidate[h] = False
            verdict = distinct(h, cs)
            if verdict:
                chosen.append(h)
                members.append(cs)
                left[cs] = False
                continue
            n_passed += 1
            if verdict is None:  # these cells moved as the first motion did, as far as the data tells
                members[0] = np.concatenate([members[0], cs])
                left[cs] = False
            else:
                passed[cs] = True
        # Cells of a motion that no joint makes, which no part took, stay with the first too.
        members[0] = np.concatenate([members[0], np.flatnonzero(passed & left)])
        return chosen, members, n_passed

    def _vanished(self, ev, T, part_share) -> list[int]:
        """The cells (indices into the pair's cells) that T puts where the camera sees through them (most
        of their points, see ``_Evidence.seen_through``), if they are enough for a part
        (``min_part_cells``, ``part_share`` of the points); else none. The object did not all move
        as T says: some part went elsewhere, where the data may not follow it (turned edge-on, away)."""
        p = self.params
        gone = ev.seen_through(T) > 0.5
        w = ev.loose_counts
        if gone.sum() < p.min_part_cells or w[gone].sum() < part_share * w.sum():
            return []
        return [ev.loose[c] for c in np.flatnonzero(gone)]

    def _single_motion(self, ev, hyps, seeds, members, best, weight, tau, part_share):
        """One rigid motion that explains all the supposed parts but less than ``part_share``, if there is one."""
        p = self.params
        cells = np.concatenate(members)
        total = weight[cells].sum()
        for h in seeds:
            T, r = ev.refit(tuple(sorted(cells.tolist())), hyps[h], tau)
            share = _per_cell((r <= tau)[None], ev.owner, ev.counts)[0]
            ok = _explains(share[None, cells], best[cells], ev.counts[cells], p.explain_margin)[0]
            if weight[cells][ok].sum() >= (1.0 - part_share) * total:
                return T, cells
        return None


class _Evidence:
    """A pair's evidence that the rule's thresholds do not change: the scoring points, the motion
    hypotheses and every point's residual under each, the measured noise, and the ICP refits done so
    far (memoised, so re-deciding under other thresholds repeats none of this work)."""

    def __init__(
        self,
        cells: list[CellMotion],
        matched: list[int],
        source: Cloud,
        target: Cloud,
        *,
        max_points: int,
        use_flow: bool = True,
        between: tuple[Cloud, ...] = (),
        scratch: dict | None = None,
    ):
        # Arrays, never the clouds themselves: this lives in the pair's scratch dict, which must not keep
        # them alive (a streaming run drops each cloud as soon as its pairs are done).
        self.src_points, self.src_normals, self.src_view = source.points, source.normals, source.view
        self.tgt_points, self.tgt_normals, self.tgt_view = target.points, target.normals, target.view
        self.tree, self.source_tree = cKDTree(target.points), cKDTree(source.points)
        self.spacing = float(
            source.info.get("v_m") or np.median(self.source_tree.query(source.points, k=2)[0][:, 1])
        )
        self.extent = float(np.linalg.norm(np.ptp(np.concatenate([source.points, target.points]), axis=0)))
        self.tgt = to_o3d(target.points, target.normals)
        self.cell_idx = [cells[n].source_idx for n in matched]
        # Scoring points: every matched cell's source points, evenly subsampled.
        idx = [_evenly(i, max_points) for i in self.cell_idx]
        self.owner = np.repeat(np.arange(len(matched)), [len(i) for i in idx])
        self.pts, self.normals = source.points[np.concatenate(idx)], source.normals[np.concatenate(idx)]
        self.counts = np.bincount(self.owner, minlength=len(matched)).astype(float)
        # For the free-space test: every cell with enough source points, matched or not (a part that moved
        # far away leaves cells that no target point shares).
        self.loose = [n for n, c in enumerate(cells) if len(c.source_idx) >= MIN_CELL_POINTS]
        idx = [_evenly(cells[n].source_idx, max_points) for n in self.loose]
        self.loose_owner = np.repeat(np.arange(len(idx)), [len(i) for i in idx])
        self.loose_pts = source.points[np.concatenate(idx)] if idx else np.zeros((0, 3))
        self.loose_counts = np.bincount(self.loose_owner, minlength=len(idx)).astype(float)
        # Whole-object motions, from the identity and from the centroid shift, coarse to fine.
        src_all = to_o3d(source.points, source.normals)
        steps = [self.extent / 5, self.extent / 10, self.extent / 20, 3 * self.spacing]
        shift = np.eye(4)
        shift[:3, 3] = target.points.mean(0) - source.points.mean(0)
        self.hyps = [
            np.eye(4),
            icp_point_to_plane(src_all, self.tgt, np.eye(4), steps),
            icp_point_to_plane(src_all, self.tgt, shift, steps),
        ]
        # Where the optical flow says each scoring point went, and how far from there it may be.
        self.flow = (
            flow_targets(source, target, self.pts, between=between, scratch=scratch)
            if use_flow
            else FlowEvidence.none(len(self.pts))
        )
        self.has_flow = self.flow.full
        seen = self.has_flow | self.flow.edge
        if self.has_flow.sum() >= MIN_FLOW_POINTS:
            self.hyps.append(trimmed_kabsch(self.pts[self.has_flow], self.flow.target[self.has_flow]))
        # ICP refined with the flow: both whole-object motions on all points, each cell's on its own.
        own = [cells[n].registration.T_target_from_source for n in matched]
        whole = self.hyps[1:3] if seen.sum() >= MIN_FLOW_POINTS else []
        fits = [c for c in range(len(matched)) if (seen & (self.owner == c)).sum() >= MIN_FLOW_POINTS]
        refined = self.flow_fit(
            whole + [own[c] for c in fits],
            [np.arange(len(self.pts))] * len(whole) + [np.flatnonzero(self.owner == c) for c in fits],
        )
        self.hyps += refined[: len(whole)]
        self.n_global = len(self.hyps)
        self.hyps += own
        refined_own = dict(zip(fits, refined[len(whole) :]))
        for c in range(len(matched)):
            use = self.has_flow & (self.owner == c)
            if use.sum() >= MIN_FLOW_POINTS:
                self.hyps.append(trimmed_kabsch(self.pts[use], self.flow.target[use]))
            if c in refined_own:
                self.hyps.append(refined_own[c])
        plain = self.residuals(self.hyps)
        self.plain = plain[: self.n_global]  # whole-object motions scored as a part's
        self.geo = np.stack(
            [
                self.excuse(r, T) if h < self.n_global else r  # (H, P) metres
                for h, (T, r) in enumerate(zip(self.hyps, plain))
            ]
        )
        # Noise measured on the data, independent of any motion: the spread of the target's points about
        # their local planes; two noisy samplings of one surface differ by sqrt(2) of that.
        self.sigma = np.sqrt(2.0) * surface_noise(target.points, self.tree)
        self._local: dict = {}
        self._refits: dict = {}
        self._unions: dict = {}

    def residuals(self, Ts: list[np.ndarray]) -> np.ndarray:
        """Each scoring point's misfit (m) under each motion of ``Ts``, (H, P): distance to the nearest
        target point's tangent plane, or to the point itself less one sampling step if larger, or beyond
        the flow's tolerance from where the flow says it went, whichever is largest. All H motions
        at once: one k-d tree query."""
        Ts = np.asarray(Ts)
        moved = np.einsum("hij,pj->hpi", Ts[:, :3, :3], self.pts) + Ts[:, None, :3, 3]
        flat = moved.reshape(-1, 3)
        d, j = self.tree.query(flat)
        r = np.maximum(
            np.abs(np.einsum("ij,ij->i", flat - self.tgt_points[j], self.tgt_normals[j])), d - self.spacing
        )
        return np.maximum(r.reshape(moved.shape[:2]), self.flow.misfit(moved))

    def flow_fit(
        self, T0: list[np.ndarray], groups: list[np.ndarray], *, rounds: int = 4
    ) -> list[np.ndarray]:
        """Each motion T0[i] refined on the scoring points ``groups[i]`` (indices) to agree with the depth
        (each moved point on the tangent plane of its nearest target point) and with the optical flow
        (where it says the point went; across the edge only, on an edge): damped Gauss-Newton steps
        about the group's centroid, with Huber weights. What neither constrains (a slide along stripes)
        stays as T0 has it. All groups are solved at once (one k-d tree query a round, not one per cell)."""
        if not groups:
            return []
        n = len(groups)
        rows = np.concatenate(groups)
        group = np.repeat(np.arange(n), [len(g) for g in groups])
        size = np.bincount(group, minlength=n)[:, None]
        T = np.array(T0, dtype=float)
        for _ in range(rounds):
            moved = np.einsum("pij,pj->pi", T[group, :3, :3], self.pts[rows]) + T[group, :3, 3]
            _, j = self.tree.query(moved)
            m = self.tgt_normals[j]
            at, g, b = self.flow.constraints(moved, rows)
            at, g = np.concatenate([np.arange(len(rows)), at]), np.concatenate([m, g])
            b = np.concatenate([np.einsum("ij,ij->i", m, self.tgt_points[j] - moved), b])
            c = (
                np.stack([np.bincount(group, weights=moved[:, k], minlength=n) for k in range(3)], axis=1)
                / size
            )
            eq = group[at]
            A = np.hstack([np.cross(moved[at] - c[eq], g), g])  # g . (w x (p - c) + t) = b
            w = 1.0 / np.maximum(1.0, np.abs(b) / self.spacing)
            H = _sum_by(eq, (w[:, None, None] * A[:, :, None] * A[:, None, :]).reshape(-1, 36), n).reshape(
                n, 6, 6
            )
            H += (1e-3 * np.trace(H, axis1=1, axis2=2) / 6)[:, None, None] * np.eye(6)
            x = np.linalg.solve(H, _sum_by(eq, (w * b)[:, None] * A, n)[..., None])[..., 0]
            step = np.tile(np.eye(4), (n, 1, 1))
            step[:, :3, :3] = Rotation.from_rotvec(x[:, :3]).as_matrix()
            step[:, :3, 3] = c - np.einsum("gij,gj->gi", step[:, :3, :3], c) + x[:, 3:]
            T = step @ T
        return list(T)

    def seen_through(self, T: np.ndarray) -> np.ndarray:
        """Share of each loose cell's points that T puts where the target camera sees past them: the
        nearest surface its depth image shows within a sampling step of the point's ray lies more than
        two sampling steps behind the point. Whatever moves as T says may hide a point (behind itself,
        behind a hand), but never leave the camera a clear view through it. Zeros without the target's
        whole-frame depth."""
        view, out = self.tgt_view, np.zeros(len(self.loose_counts))
        if view is None or view.scene_depth_m is None or not len(self.loose_pts):
            return out
        K = view.intrinsics
        r = max(1, int(round(self.spacing * K.fx / np.median(self.tgt_points[:, 2]))))
        depth = np.where(view.scene_depth_m > 0, view.scene_depth_m, np.inf).astype(np.float32)
        near = cv2.erode(depth, np.ones((2 * r + 1, 2 * r + 1), np.uint8))  # not kept: 1 ms, 1 MB a pair
        gap = _in_front(np.where(np.isfinite(near), near, 0.0), K, transform(self.loose_pts, T))[0]
        through = np.isfinite(gap) & (-gap > 2 * self.spacing)
        return np.bincount(self.loose_owner, weights=through, minlength=len(out)) / np.maximum(
            self.loose_counts, 1
        )

    def excuse(self, r: np.ndarray, T: np.ndarray) -> np.ndarray:
        """Residuals ``r`` under a motion T of the whole object, which is not faulted for the points
        it hides itself (see ``hidden``)."""
        return np.where(self.hidden(transform(self.pts, T), T), 0.0, r)

    def hidden(self, moved: np.ndarray, T: np.ndarray) -> np.ndarray:
        """Moved points that the target cannot see because T's own motion hides them.

        A point is hidden when the target's depth along its ray is nearer by more than two sampling
        steps, and the surface in front is one T accounts for: T's inverse takes it back onto the
        source's surface. A box turning away from the camera hides its far faces behind its near
        ones. A surface in front that came from elsewhere (a lid swung towards the camera, a drawer
        pulled out over its old place) is not an excuse: the point stays unexplained.
        """
        view = self.tgt_view
        out = np.zeros(len(moved), bool)
        if view is None or self.src_view is None:
            return out
        gap, ui, vi, zt = _in_front(view.depth_m, view.intrinsics, moved)
        idx = np.flatnonzero(gap > 2 * self.spacing)
        if not len(idx):
            return out
        K, ui, vi, zt = view.intrinsics, ui[idx], vi[idx], zt[idx]
        q = transform(K.points(ui, vi, zt), np.linalg.inv(T))
        d, _ = self.source_tree.query(q)
        out[idx] = d <= 2 * self.spacing
        return out

    def separated(self, A: np.ndarray, B: np.ndarray, cells: np.ndarray, tau: float) -> bool:
        """Whether motions A and B put most points of ``cells`` apart: off the surface by more than tau,
        or (where optical flow sees the point) along it by more than tau plus the flow's tolerance.
        Closer than that, both motions explain the same points and the data cannot tell them apart
        (a bottle turned 7 or 8 degrees about its axis)."""
        use = np.isin(self.owner, cells)
        a, b = transform(self.pts, A), transform(self.pts, B)
        across = np.abs(np.einsum("ij,ij->i", a - b, self.normals))
        apart = ((across > tau) | self.flow.apart(a, b, self.normals, tau))[use]
        return bool(apart.mean() > 0.5)

    def local(self, c: int, g: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """Cell c's own ICP, from whole-object motion g and from the identity, with residuals."""
        if (c, g) not in self._local:
            i = self.cell_idx[c]
            src = to_o3d(self.src_points[i], self.src_normals[i])
            near = [4 * self.spacing, 2 * self.spacing]
            Ts = [
                icp_point_to_plane(src, self.tgt, self.hyps[g], near),
                icp_point_to_plane(src, self.tgt, np.eye(4), near),
            ]
            self._local[(c, g)] = list(zip(Ts, self.residuals(Ts)))
        return self._local[(c, g)]

    def union(self, cells: tuple, seeds: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
        """Motions fitted to the points of ``cells`` together (depth and flow), from each of ``seeds``,
        with the residuals of all points."""
        key = (cells, tuple(T.tobytes() for T in seeds))
        if key not in self._unions:
            group = np.flatnonzero(np.isin(self.owner, cells))
            use = group[self.has_flow[group]]
            direct = []  # what the flow alone says: a rigid fit, and a plain slide
            if len(use) >= MIN_FLOW_POINTS:
                slide = np.eye(4)
                slide[:3, 3] = np.median(self.flow.target[use] - self.pts[use], axis=0)
                direct = [trimmed_kabsch(self.pts[use], self.flow.target[use]), slide]
            seeds = seeds + direct
            Ts = direct + self.flow_fit(seeds, [group] * len(seeds), rounds=8)
            self._unions[key] = list(zip(Ts, self.residuals(Ts)))
        return self._unions[key]

    def refit(self, cells: tuple, T0: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
        """One ICP refit from T0 on the scoring points of ``cells``, with the residuals of all points. Its
        coarse stages do not depend on tau and are kept apart: a new tau only runs the last one."""
        key = (cells, T0.tobytes())
        if key not in self._refits:
            src = to_o3d(self.pts[np.isin(self.owner, cells)])
            self._refits[key] = (
                src,
                icp_point_to_plane(src, self.tgt, T0, [self.extent / 10, 2 * self.spacing, self.spacing]),
                {},
            )
        src, coarse, fine = self._refits[key]
        if tau not in fine:
            T = icp_point_to_plane(src, self.tgt, coarse, [2 * tau])
            fine[tau] = (T, self.excuse(self.residuals([T])[0], T))
        return fine[tau]


def trimmed_kabsch(p: np.ndarray, q: np.ndarray, *, keep: float = 0.7, rounds: int = 3) -> np.ndarray:
    """Rigid fit of p onto q, refitted on the best ``keep`` share of its own residuals ``rounds`` times."""
    use = np.arange(len(p))
    for _ in range(rounds):
        T = kabsch(p[use], q[use])
        err = np.linalg.norm(transform(p, T) - q, axis=1)
        use = np.argsort(err)[: max(3, int(keep * len(p)))]
    return T


def joint_like(A: np.ndarray, B: np.ndarray, centre: np.ndarray, size: float) -> bool:
    """Whether B moves relative to A as a part moves on a joint: by a translation (a turn of under
    ``JOINT_MIN_TURN_RAD``: a drawer), or by a turn about an axis that passes within half the object's
    ``size`` of its ``centre``, sliding along that axis by at most ``JOINT_MAX_SLIDE`` of its size (a
    hinge). A screw motion of centimetres about a far axis is what two poorly fitted regions of one
    rigid object look like, not a part."""
    T = B @ np.linalg.inv(A)
    rotvec = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    turn = float(np.linalg.norm(rotvec))
    if turn < JOINT_MIN_TURN_RAD:
        return True
    axis, t = rotvec / turn, T[:3, 3]
    slide = float(t @ axis)
    point = np.linalg.lstsq(np.eye(3) - T[:3, :3], t - slide * axis, rcond=None)[0]  # a point on the axis
    off = centre - point
    return bool(
        abs(slide) <= JOINT_MAX_SLIDE * size and np.linalg.norm(off - (off @ axis) * axis) <= 0.5 * size
    )


def _in_front(depth_m: np.ndarray, K, points: np.ndarray):
    """How far in front of each point (m) the surface in the depth image lies along the point's ray
    (> 0 when it is nearer; -inf where the image has no depth there or the ray leaves it), and the
    pixel columns, rows and depths read."""
    h, w = depth_m.shape
    z = points[:, 2]
    u, v = (np.round(c) for c in K.pixels(points))
    inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    ui, vi = np.where(inside, u, 0).astype(int), np.where(inside, v, 0).astype(int)
    zt = np.where(inside, depth_m[vi, ui], 0.0)
    gap = np.where(zt > 0, z - zt, -np.inf)
    return gap, ui, vi, zt


def _evenly(idx: np.ndarray, n: int) -> np.ndarray:
    """At most n of the indices ``idx``, evenly spread over them."""
    return idx[np.linspace(0, len(idx) - 1, min(len(idx), n)).astype(int)]


def _explains(score: np.ndarray, best: np.ndarray, counts: np.ndarray, margin: float) -> np.ndarray:
    """Whether each hypothesis' inlier share on each cell is as good as the best, within ``margin`` plus
    two standard errors of the difference of two shares measured on the cell's n points."""
    pooled = (score + best) / 2.0
    return score >= best - margin - 2.0 * np.sqrt(2.0 * pooled * (1.0 - pooled) / np.maximum(counts, 1))


def surface_noise(points: np.ndarray, tree: cKDTree, *, n_samples: int = 400, k: int = 12) -> float:
    """Robust standard deviation (m) of points about the plane of their k nearest neighbours.

    Measured on an even subsample; curvature inflates it slightly, which errs on the safe side.
    """
    if len(points) < k + 1:
        return 0.0
    sample = points[np.linspace(0, len(points) - 1, min(n_samples, len(points))).astype(int)]
    _, nn = tree.query(sample, k=k)
    hood = points[nn] - points[nn].mean(axis=1, keepdims=True)  # (S, k, 3)
    _, s, vt = np.linalg.svd(hood, full_matrices=False)
    off = np.abs(np.einsum("skj,sj->sk", hood, vt[:, 2, :]))  # distances to the plane
    return float(1.4826 * np.median(off) * np.sqrt(k / (k - 3)))  # 3 dof used by the fit


def _sum_by(group: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sums of the rows of ``values`` (M, D) by ``group`` (M,) -> (n, D)."""
    d = values.shape[1]
    flat = (group[:, None] * d + np.arange(d)).ravel()
    return np.bincount(flat, weights=values.ravel(), minlength=n * d).reshape(n, d)


def _per_cell(values: np.ndarray, owner: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Mean of ``values`` (H, P) over each cell's points -> (H, C)."""
    out = np.stack([np.bincount(owner, weights=v.astype(float), minlength=len(counts)) for v in values])
    return out / np.maximum(counts, 1)


def _displacement(points: np.ndarray, T: np.ndarray) -> float:
    """How far (m) T moves the farthest of ``points``."""
    return float(np.max(np.linalg.norm(transform(points, T) - points, axis=1)))


def _describe(T: np.ndarray) -> str:
    return f"{np.degrees(rotation_angle_rad(T[:3, :3])):.1f} deg, {1000 * np.linalg.norm(T[:3, 3]):.1f} mm"
