"""Step 6, part images: every frame's segmentation from the parts' motions over the whole video."""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial import cKDTree

from artclass_core import RunResult
from artclass_core.articulation import JointEstimate
from artclass_core.geometry import transform

from .base import _interpolated
from .observations import _frame_clouds, _has_depth, _mask, _noise, _Observation, _spacing, _stride
from .params import PartsParams
from .tree import _Link


def _relabelled(
    result: RunResult,
    observations: list[_Observation],
    views: dict,
    tree: dict[int, _Link],
    base_poses: np.ndarray,
    *,
    params: PartsParams,
) -> dict:
    """Every frame's track labelling from the parts' motions over the video, not from one pair's.

    A frame's object points are moved by each part's motion to the ``n_views`` frames where the
    parts' motions move them most differently and looked up in those frames' depth images
    (:func:`_look`); each point takes the part that puts it nearest the surface seen there (the
    nearer of those frames, so that a point hidden in one is judged by the other). A point that two
    parts explain about as well (within ``ambiguity_sigmas`` depth-noise levels) is judged by its
    intensity there (:func:`_by_shade`), and where that cannot tell either, left unlabelled: the part
    image gives its pixel the part of the nearest labelled point. A frame where no point is
    decided keeps its pair's labels. This is done first in the frames where every part's pose is
    known from the pairs, then, once each part's state is found in the others
    (:func:`_track_states`), in every frame where the parts are placed. A frame where a state could
    only be guessed is not judged so (nor judges others): where a pair separated the parts it keeps
    that pair's labels, elsewhere its points take the nearest part placed at the guessed states
    (:func:`_nearest_part_labels`)."""
    from ._compiled import by_depth, smoothed_at  # Numba, loaded on first use

    tracks = np.asarray(list(tree))
    # the base's pose where no pair reached: between the frames that have one (a guess, as below)
    reached = np.isfinite(base_poses).all(axis=(1, 2))
    base_poses = np.stack(
        [
            p if k else _interpolated(base_poses, reached, f)
            for f, (p, k) in enumerate(zip(base_poses, reached))
        ]
    )
    clouds = _frame_clouds(result, observations)
    images = {f: result.frames[f].cloud.view for f in clouds if _has_depth(result, f)}
    noise, spacing = _noise(result), _spacing(result)
    reach = spacing + params.reach_sigmas * noise
    prior = {f: views[f][1] if f in views else np.full(len(clouds[f][1]), -1) for f in clouds}
    sure: dict[int, np.ndarray] = {}

    def placed(placements: dict[int, np.ndarray]) -> list[int]:
        return [
            f
            for f in sorted(images)
            if all(np.isfinite(base_poses[f] @ p[f]).all() for p in placements.values())
        ]

    def label(placements: dict[int, np.ndarray], frames: list[int]) -> dict[int, np.ndarray]:
        poses = np.stack([base_poses @ placements[t] for t in tracks])  # (parts, frames, 4, 4)
        others = placed(placements)
        if len(others) < 2 or not frames:
            return {}
        views_of = _most_apart(poses, frames, others, clouds, n=params.n_views)
        points = {f: np.ascontiguousarray(clouds[f][1][::_LABELLED_EVERY]) for f in frames}
        # a part's motion is known to about a pixel: intensities are compared smoothed over a pixel's
        # neighbours, here and where the points land
        shade = {f: smoothed_at(images[f].gray, clouds[f][0][::_LABELLED_EVERY].copy()) for f in frames}
        residual = {f: np.full((len(tracks), len(points[f])), np.nan) for f in frames}
        # per part and point: the summed change of intensity where the motion lands it on a surface, and
        # in how many of the frames looked in it did
        change = {f: np.zeros((len(tracks), len(points[f]))) for f in frames}
        landings = {f: np.zeros((len(tracks), len(points[f]))) for f in frames}
        for f in frames:
            back = np.linalg.inv(poses[:, f])  # each part's frame-f points in its own coordinates
            for g in views_of[f]:
                _look_into(
                    images[g],
                    points[f],
                    poses[:, g] @ back,
                    reach_m=reach,
                    out=residual[f],
                    gray=images[g].gray,
                    shade=shade[f],
                    change=change[f],
                    landings=landings[f],
                )
        margin = params.ambiguity_sigmas * noise
        decided = {f: by_depth(residual[f], change[f], landings[f], reach, margin) for f in frames}
        shade_noise = _shade_noise(decided.values())
        out = {}
        for f, (best, decisive, change_by_part) in decided.items():
            best, decisive = _by_shade(
                best, decisive, change_by_part, limit=params.ambiguity_sigmas * shade_noise
            )
            sure[f] = np.full(len(clouds[f][1]), -1)
            sure[f][::_LABELLED_EVERY] = np.where(decisive, tracks[best], -1)
            out[f] = sure[f] if decisive.any() else prior[f]
        return out

    placements = {t: link.placement for t, link in tree.items()}
    known = placed(placements)
    hidden = [f for f in sorted(images) if f not in known and np.isfinite(base_poses[f]).all()]
    labels = {}
    if hidden and known:  # the parts' states there are found from the labels of the nearest frames
        nearest = {g for f in hidden for g in sorted(known, key=lambda g: abs(g - f))[: params.n_views]}
        labels = label(placements, sorted(nearest))
        placements, guessed = _track_states(
            tree, base_poses, clouds, sure, images, reach=reach, spacing=spacing, params=params
        )
        guessed |= ~reached
        # a frame where a state was only guessed is neither judged by the motions nor a view to judge by
        looked = {t: np.where(guessed[:, None, None], np.nan, p) for t, p in placements.items()}
        labels.update(label(looked, [f for f in placed(looked) if f not in labels]))
        # ... and where no pair separated the parts, they are placed at the guessed states
        separated = [f for f, part in prior.items() if len(np.intersect1d(part, tracks)) > 1]
        guessed[separated] = False
        labels.update(_nearest_part_labels(clouds, sure, base_poses, placements, looked, guessed))
    else:
        labels.update(label(placements, [f for f in placed(placements) if f not in labels]))
    out = dict(views)
    for f, part in labels.items():
        if (part >= 0).any():  # a frame no pair labelled and where nothing was decided stays unlabelled
            out[f] = (clouds[f][0], part, _mask(result, f), _stride(result, f))
    return out


def _look(motions: np.ndarray, points: np.ndarray, view, *, reach_m: float) -> np.ndarray:
    """How far (metres, along the ray) each point (N, 3), moved by each motion (H, 4, 4), lands from
    the surface seen in ``view`` at the pixel it projects onto (projective look-up, as KinectFusion's):
    (H, N); inf where the camera measured nothing there, NaN where the surface is more than
    ``reach_m`` in front of the point (it hides the point) or the point leaves the image: no
    evidence. A surface far behind the point means the camera sees past it: evidence against."""
    out = np.full((len(motions), len(points)), np.nan)
    _look_into(view, np.ascontiguousarray(points, dtype=float), motions, reach_m=reach_m, out=out)
    return out


def _look_into(
    view,
    points: np.ndarray,
    motions: np.ndarray,
    *,
    reach_m: float,
    out: np.ndarray,
    gray: np.ndarray | None = None,
    shade: np.ndarray | None = None,
    change: np.ndarray | None = None,
    landings: np.ndarray | None = None,
) -> None:
    """:func:`_look` into ``out`` (H, N), keeping each point's nearest yet. With the view's intensities
    ``gray`` and the points' own ``shade`` (N,): where a point lands on the surface, ``change`` (H, N)
    += its change of intensity and ``landings`` += 1."""
    from ._compiled import look_kernel  # Numba, loaded on first use

    k = view.intrinsics
    depth = view.scene_depth_m if view.scene_depth_m is not None else view.depth_m
    unused = np.zeros((0, 0))
    look_kernel(
        points,
        np.ascontiguousarray(motions, dtype=float),
        depth,
        _NO_IMAGE if gray is None else gray,
        np.array([k.fx, k.fy, k.cx, k.cy], float),
        float(reach_m),
        np.zeros(0) if shade is None else shade,
        out,
        unused if change is None else change,
        unused if landings is None else landings,
    )


#: An intensity image to look nothing up in.
_NO_IMAGE = np.zeros((0, 0), np.uint8)


def _shade_noise(decided) -> float:
    """The noise of a point's intensity from one frame to another (grey levels, at least one): the
    robust standard deviation of the change that the part the depth chose gives each point it chose
    decisively (``decided``: per frame, the best part, whether decisive, and the mean change by part,
    as :func:`._compiled.by_depth` gives them)."""
    changes = np.concatenate(
        [change[best[sure], np.flatnonzero(sure)] for best, sure, change in decided] or [np.zeros(0)]
    )
    changes = changes[np.isfinite(changes)]
    return max(1.4826 * float(np.median(changes)), 1.0) if len(changes) else np.inf


def _by_shade(
    best: np.ndarray, decisive: np.ndarray, change: np.ndarray, *, limit: float
) -> tuple[np.ndarray, np.ndarray]:
    """Points the depth leaves undecided (a part sliding along a surface puts them on it as well as
    the surface's own part does) decided by their texture: the part, among those that put a point on
    a surface about as well (the others' ``change`` (parts, N) is infinite), whose motion changes its
    intensity least (the mean over the frames looked in), when the next one changes it by more than
    ``limit`` grey levels more. Returns the best part and whether it is decided, (N,) each."""
    from ._compiled import by_shade  # Numba, loaded on first use

    return by_shade(best, decisive, change, limit)


def _most_apart(
    poses: np.ndarray, frames: list[int], others: list[int], clouds: dict, *, n: int
) -> dict[int, list[int]]:
    """For each of ``frames``, the ``n`` of ``others`` to which the parts' motions (poses (parts,
    frames, 4, 4)) move its points most differently: the median, over a thinning of its points, of
    the largest distance between two parts' predictions."""
    sample = np.stack([_thinned(clouds[f][1], _SAMPLE) for f in frames])  # (F, S, 3)
    inverse = np.linalg.inv(poses[:, frames])  # (parts, F, 4, 4)
    own = sample @ inverse[..., :3, :3].swapaxes(-1, -2) + inverse[:, :, None, :3, 3]  # (parts, F, S, 3)
    there = poses[:, others]  # (parts, G, 4, 4)
    moved = own[:, :, None] @ there[:, None, :, :3, :3].swapaxes(-1, -2) + there[:, None, :, None, :3, 3]
    spread = np.zeros((len(frames), len(others)))
    for a, b in itertools.combinations(range(len(poses)), 2):
        spread = np.maximum(spread, np.median(np.linalg.norm(moved[a] - moved[b], axis=-1), axis=-1))
    spread[np.asarray(frames)[:, None] == np.asarray(others)[None]] = -1.0  # never the frame itself
    return {
        f: [others[k] for k in np.argsort(-row, kind="stable")[:n] if row[k] >= 0]
        for f, row in zip(frames, spread)
    }


def _thinned(points: np.ndarray, n: int) -> np.ndarray:
    """``n`` of the points (N, 3), evenly through their order (repeated when there are fewer)."""
    return points[np.linspace(0, len(points) - 1, n).astype(int)]


#: Points of a frame used to choose the frames it is judged in, and of a part looked up per state.
_SAMPLE = 32


_TRACKED_POINTS = 200


#: Points of a part's model, by which frames where its state was only guessed are labelled.
_MODEL_POINTS = 5000


#: Every how many of a frame's points are labelled: the part image gives each pixel the part of the
#: nearest labelled point anyway, so every second one gives the same images at half the cost.
_LABELLED_EVERY = 2


def _track_states(
    tree: dict[int, _Link],
    base_poses: np.ndarray,
    clouds: dict[int, tuple[np.ndarray, np.ndarray]],
    labels: dict[int, np.ndarray],
    images: dict,
    *,
    reach: float,
    spacing: float,
    params: PartsParams,
) -> dict[int, np.ndarray]:
    """Each part's placement (frames, 4, 4) with its joint's state found in the frames where no pair
    gave it: the part's points of the nearest frames where they were labelled for sure, brought to
    state 0 and moved by the joint to each state of a grid (steps that move the part's farthest point
    by one point spacing, over the states seen and as far again either side), are looked up in the
    frame; the state that puts most of them on the surface seen there (at least ``min_seen`` of
    them) is the frame's. Where none does, the state is interpolated between the nearest frames that
    have one and held beyond them, and the frame is marked as guessed. Parents first, so a chain's
    outer part moves with its inner one (also where its own state is known from the pairs but its
    parent's was not).

    Returns the placements and the guessed frames (n_frames,) bool."""
    placements = {t: link.placement.copy() for t, link in tree.items()}
    guessed = np.zeros(len(base_poses), bool)
    for t, link in tree.items():
        e = link.estimate
        if e is None or e.type not in ("revolute", "prismatic") or e.axis_direction is None:
            continue
        parent = placements[link.parent]
        known = np.isfinite(e.states)
        # a chain's outer part, where its own state is known and its parent's was just found
        again = known & np.isnan(placements[t]).any(axis=(1, 2)) & np.isfinite(parent).all(axis=(1, 2))
        placements[t][again] = parent[again] @ e.motion(e.states[again])
        local = {
            f: transform(clouds[f][1][part == t], np.linalg.inv(base_poses[f] @ placements[t][f]))
            for f, part in labels.items()
            if known[f] and np.count_nonzero(part == t)
        }
        todo = [f for f in sorted(images) if not known[f] and np.isfinite(base_poses[f] @ parent[f]).all()]
        if not todo or not known.any():
            continue
        states = e.states.copy()
        if local:
            states[todo] = _looked_up_states(
                e, local, todo, base_poses, parent, images, reach, spacing, params
            )
        # where the look-up found too little of the part (hidden, or turned away), the state between
        # the nearest frames that gave one, held at the ends
        found = np.flatnonzero(np.isfinite(states))
        guessed[todo] |= np.isnan(states[todo])
        states[todo] = np.interp(todo, found, states[found])
        placements[t][todo] = parent[todo] @ e.motion(states[todo])
    return placements, guessed


def _nearest_part_labels(
    clouds: dict[int, tuple[np.ndarray, np.ndarray]],
    sure: dict[int, np.ndarray],
    base_poses: np.ndarray,
    placements: dict[int, np.ndarray],
    looked: dict[int, np.ndarray],
    guessed: np.ndarray,
) -> dict[int, np.ndarray]:
    """The labels of the frames where a part's state was only guessed (``guessed``): each part's
    points labelled for sure in the frames where the parts are placed (``looked``), brought to
    state 0 and placed in the frame at the guessed states (``placements``); each of the frame's
    points takes the part with the nearest of them."""
    models = {}
    for t, placement in looked.items():
        frames = [f for f in sure if np.isfinite(base_poses[f] @ placement[f]).all()]
        step = max(1, sum(np.count_nonzero(sure[f] == t) for f in frames) // _MODEL_POINTS)
        local = [
            transform(clouds[f][1][sure[f] == t][::step], np.linalg.inv(base_poses[f] @ placement[f]))
            for f in frames
        ]
        if sum(map(len, local)):
            models[t] = np.concatenate(local)
    if len(models) < 2:
        return {}
    owner = np.concatenate([np.full(len(points), t) for t, points in models.items()])
    out = {}
    for f in np.flatnonzero(guessed):
        poses = [base_poses[f] @ placements[t][f] for t in models]
        if f not in clouds or not all(np.isfinite(P).all() for P in poses):
            continue
        placed = np.concatenate([transform(points, P) for points, P in zip(models.values(), poses)])
        _, nearest = cKDTree(placed).query(clouds[f][1][::_LABELLED_EVERY])
        out[int(f)] = np.full(len(clouds[f][1]), -1)
        out[int(f)][::_LABELLED_EVERY] = owner[nearest]
    return out


def _looked_up_states(
    e: JointEstimate,
    local: dict[int, np.ndarray],
    todo: list[int],
    base_poses: np.ndarray,
    parent: np.ndarray,
    images: dict,
    reach: float,
    spacing: float,
    params: PartsParams,
) -> np.ndarray:
    """The joint's state (len(todo),) in each frame of ``todo`` that puts most of the part's points
    (``local``: per frame where they were labelled for sure, at state 0) on the surface seen there, on
    a grid of states (steps that move its farthest point by one point spacing, over the states seen
    and as far again either side); NaN where fewer than ``min_seen`` of them land on it."""
    seen = e.states[np.isfinite(e.states)]
    span = float(seen.max() - seen.min())
    if e.type == "revolute":
        everything = np.concatenate(list(local.values()))
        lever = np.linalg.norm(np.cross(everything - e.axis_point_m, e.axis_direction), axis=1).max()
        step = spacing / max(float(lever), spacing)
    else:
        step = spacing
    grid = np.arange(seen.min() - span, seen.max() + span + step, step)
    motions = e.motion(grid)  # (G, 4, 4)
    out = np.full(len(todo), np.nan)
    for n, f in enumerate(todo):
        near = sorted(local, key=lambda g: abs(g - f))[: params.n_views]
        X = np.concatenate([local[g] for g in near])
        X = X[:: max(1, len(X) // _TRACKED_POINTS)]
        residual = _look(base_poses[f] @ parent[f] @ motions, X, images[f], reach_m=reach)
        share = (residual < reach).mean(axis=1)
        best = int(np.argmax(share))
        if share[best] >= params.min_seen:
            out[n] = grid[best]
    return out
