"""Step 5, the kinematic tree grown from the base, and the parts' points at state 0."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from artclass_core import RunResult
from artclass_core.articulation import JointEstimate, Part
from artclass_core.geometry import transform
from artclass_core.interfaces import JointEstimator
from artclass_core.video import MIN_PAIRS

from .joints import _pair_joint, _relative_motions
from .observations import _mask, _Observation, _stride
from .params import PartsParams


@dataclass
class _Link:
    """A part in the tree: its parent track (None for the base), its joint on it, and ``placement``
    (n_frames, 4, 4): the motion, in the base's first-frame coordinates, that takes the part from
    where it is with every joint between it and the base at state 0 to where it is in each frame
    (NaN where unknown)."""

    parent: int | None
    estimate: JointEstimate | None
    n_pairs: int
    placement: np.ndarray


def _kinematic_tree(
    result: RunResult,
    base: int,
    moving: list[int],
    motions: dict[int, dict[int, np.ndarray]],
    base_poses: np.ndarray,
    points: dict[int, dict[int, np.ndarray]],
    n_frames: int,
    *,
    estimator: JointEstimator,
    params: PartsParams,
) -> dict[int, _Link]:
    """The tree of parts grown from the base, in the spirit of Sturm et al.'s minimum spanning tree
    of joint costs: each step attaches the moving part whose joint on a part already in the tree
    costs least (:func:`_joint_cost`), so the outer arm of a chain hangs on the inner arm, relative
    to which it has one degree of freedom. A joint that fewer than the video's ``MIN_PAIRS`` pairs
    tell is untested (a line or an axis passes through any two poses, at a cost near nothing): it
    is chosen only when no tested joint is on offer, so that a part seen in two pairs does not
    become the parent of one tracked over the video. Parts in tree order (parents first); a part that no
    ``min_pairs`` pairs relate to the tree, or whose joint explains fewer of them (one relative
    motion is always a screw motion, so it tells no joint), is left out."""
    tree = {base: _Link(None, None, 0, np.tile(np.eye(4), (n_frames, 1, 1)))}

    def joint_on(child: int, parent: int) -> tuple[JointEstimate, int] | None:
        placement = tree[parent].placement
        relative = _relative_motions(result, motions[child], motions[parent], base_poses @ placement)
        if len(relative) < params.min_pairs or not points.get(child):
            return None
        own = _placed(points[child], placement)
        centre = np.median(own, axis=0)
        reach = _reach(own, points.get(parent, {}), placement, centre)
        fit = _pair_joint(
            relative, centre, n_frames, estimator=estimator, smoothness=params.smoothness, reach_m=reach
        )
        # one pair's motion is always a screw about some axis: a joint is told by at least min_pairs
        return None if fit[0].type != "free" and fit[1] < params.min_pairs else fit

    fits: dict[tuple[int, int], tuple[JointEstimate, int] | None] = {}
    waiting = list(moving)
    while waiting:
        options = []
        for order, child in enumerate(waiting):
            for rank, parent in enumerate(tree):
                if (child, parent) not in fits:
                    fits[(child, parent)] = joint_on(child, parent)
                if fits[(child, parent)] is not None:
                    estimate, n_pairs = fits[(child, parent)]
                    untested = n_pairs < MIN_PAIRS
                    options.append((untested, _joint_cost(estimate), order, rank, child, parent))
        if not options:
            break
        *_, child, parent = min(options)
        estimate, n_pairs = fits[(child, parent)]
        tree[child] = _Link(parent, estimate, n_pairs, _placement(tree[parent].placement, estimate))
        waiting.remove(child)
    return tree


def _joint_cost(estimate: JointEstimate) -> float:
    """What a joint costs in the tree: the BIC of the chosen model per pose it explains, plus the
    misfit per pose that is smooth in time (:func:`smooth_misfit`), which the estimator's noise
    level, taken from the residuals, hides (lower is better; infinite for a free motion or an
    estimator that gives no score). A lamp's arm carried along a circle by a parallelogram keeps
    its orientation relative to the base and passes for a slide there, but its travel turns from
    pair to pair; it hangs on the arm it turns against."""
    score = estimate.scores.get(estimate.type)
    n = estimate.info.get("n_poses_explained", 0)
    if score is None or not np.isfinite(score) or not n:
        return float("inf")
    return float(score) / n + float(estimate.info.get("smooth_misfit", 0.0))


def _placement(parent: np.ndarray, estimate: JointEstimate) -> np.ndarray:
    """A child's placement (n_frames, 4, 4): its parent's, then its joint's motion at each frame's
    state (NaN where the state is unknown)."""
    known = np.isfinite(estimate.states)
    out = np.full_like(parent, np.nan)
    out[known] = parent[known] @ estimate.motion(estimate.states[known])
    return out


def _placed(own: dict[int, np.ndarray], placement: np.ndarray) -> np.ndarray:
    """A part's points (per frame, base's first-frame coordinates) in its parent's coordinates at
    state 0: each frame's points with the parent's ``placement`` undone (all the points as they are
    when the parent is placed in none of the frames)."""
    placed = [f for f in own if np.isfinite(placement[f]).all()]
    clouds = [transform(own[f], np.linalg.inv(placement[f])) for f in placed] or list(own.values())
    return np.concatenate(clouds)


def _reach(
    own_m: np.ndarray, parent: dict[int, np.ndarray], placement: np.ndarray, centre_m: np.ndarray
) -> float:
    """How far (metres) a part's points ``own_m`` (as :func:`_placed` gives them) and its parent's
    points, placed the same way, reach from ``centre_m``."""
    from ._compiled import farthest  # Numba, loaded on first use

    placed = [f for f in parent if np.isfinite(placement[f]).all()]
    # a rigid motion keeps distances: a frame's parent points are measured from the centre placed there
    parent_from = [(parent[f], placement[f][:3, :3] @ centre_m + placement[f][:3, 3]) for f in placed]
    clouds = [(own_m, centre_m)] + (parent_from or [(points, centre_m) for points in parent.values()])
    return max(farthest(np.ascontiguousarray(points), centre) for points, centre in clouds)


def _part(
    index: int, parent: int, own: dict[int, np.ndarray], link: _Link, n_labelled: int, *, shown: set[int]
) -> Part:
    """A part, its points from the frame where it shows most (among the frames where it is placed, and
    of those where its children are ``shown`` apart from it, if any: where a pair saw the object move
    as one body, the base's points hold its parts too), brought back to state 0."""
    frames = [f for f in own if np.isfinite(link.placement[f]).all()] or list(own)
    frames = [f for f in frames if f in shown] or frames
    cloud = np.zeros((0, 3))
    if frames:
        f = max(frames, key=lambda f: len(own[f]))
        cloud = own[f]
        if np.isfinite(link.placement[f]).all():
            cloud = transform(cloud, np.linalg.inv(link.placement[f]))
    return Part(index, "base" if index == 0 else f"part{index}", parent, cloud, sorted(own), n_labelled)


def _part_points(
    result: RunResult,
    observations: list[_Observation],
    track: dict[tuple, int],
    base_poses: np.ndarray,
) -> tuple[dict, dict[int, dict[int, np.ndarray]]]:
    """Each frame's track labelling (-1 for no track; one per frame: a pair's source side first) and
    each track's points per frame, in the base's first-frame coordinates (the frames where the base's
    pose is known)."""
    points: dict[int, dict[int, np.ndarray]] = {}
    views = {}
    for o in sorted(observations, key=lambda o: (o.frame, not o.forward)):
        if o.frame in views or not np.isfinite(base_poses[o.frame]).all():
            continue
        n_motions = len(result.pairs[o.pair].motions)
        lookup = np.array([track.get((o.pair, m), -1) for m in range(n_motions)] + [-1])
        part = lookup[np.where(o.labels >= 0, o.labels, n_motions)]
        views[o.frame] = (o.pixels, part, _mask(result, o.frame), _stride(result, o.frame))
        local = transform(o.points, np.linalg.inv(base_poses[o.frame]))
        for p in np.unique(part[part >= 0]):
            points.setdefault(int(p), {})[o.frame] = local[part == p]
    return views, points


def _numbered(views: dict, number: dict[int, int]) -> dict:
    """The frames' track labellings as part numbers, keeping the points of the parts only (and the
    frames whose mask is kept)."""
    out = {}
    for frame, (pixels, tracks, mask, stride) in views.items():
        if mask is None:
            continue
        lookup = np.full(int(tracks.max(initial=-1)) + 2, -1)
        for t, n in number.items():
            if t < len(lookup) - 1:
                lookup[t] = n
        part = lookup[tracks]  # track -1 reads the last entry, -1
        keep = part >= 0
        out[frame] = (pixels[keep], part[keep], mask, stride)
    return out
