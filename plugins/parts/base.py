"""Steps 2 and 3, the base and its poses: the part left still, its motions chained through the
pairs into a pose per frame, and the moving tracks linked by their motions relative to it."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np

from artclass_core import RunResult
from artclass_core.geometry import transform

from .joints import _relative_motions
from .motions import _screw, _twist_log
from .observations import _Observation
from .tracks import _Groups, _seen_tracks


def _still_track(result: RunResult, track: dict[tuple, int], size: dict[int, int], *, min_pairs: int) -> int:
    """The base: of the tracks seen in at least ``min_pairs`` AM pairs, the one found still (its
    points moved by no more than the rule's motion threshold, ``threshold_m`` of the pair's info) in
    the most AM pairs; the larger one breaks a tie, and when none is ever still (the object carried
    throughout, or a rule that gives no threshold) the track with the most labelled points is the base.

    A hand moves the part it holds; what it leaves on the table is the base, which need not be the
    largest part (a drawer's front, a lamp's shade)."""
    if not size:
        return 0
    candidates = _seen_tracks(result, track, min_pairs=min_pairs) if result.label == "articulated" else set()
    still = dict.fromkeys(candidates, 0)
    for (pair, m), t in track.items():
        p = result.pairs[pair]
        if (
            t in candidates
            and p.decision == "AM"
            and p.motions[m].displacement_m <= p.info.get("threshold_m", -1.0)
        ):
            still[t] += 1
    if not any(still.values()):
        return max(size, key=size.get)
    return max(still, key=lambda t: (still[t], size[t]))


def _one_body_pairs_on(base: int, result: RunResult, track: dict[tuple, int]) -> dict[tuple, int]:
    """``track`` with the motion of every pair that found one motion on the base: the whole object
    moved as one body there, so that motion is the base's too (and the moving parts are at rest
    relative to it)."""
    one_body = {pair for (pair, m) in track if len(result.pairs[pair].motions) == 1}
    return {node: base if node[0] in one_body else t for node, t in track.items()}


def _track_motions(
    result: RunResult, track: dict[tuple, int], *, base: int
) -> dict[int, dict[int, np.ndarray]]:
    """Each track's motion T_target_from_source (4, 4) in each pair that found it (at most one a pair);
    the base's as :func:`_base_motions` gives them."""
    motions: dict[int, dict[int, np.ndarray]] = {}
    for (pair, m), t in sorted(track.items()):
        if t != base:
            motions.setdefault(t, {})[pair] = result.pairs[pair].motions[m].T_target_from_source
    motions[base] = _base_motions(result, track, base)
    return motions


def _base_motions(result: RunResult, track: dict[tuple, int], base: int) -> dict[int, np.ndarray]:
    """The base's motion T_target_from_source (4, 4) in each pair that found it: the identity where
    the rule found no motion in the pair, where the motion moves its points by no more than the
    rule's motion threshold (``threshold_m`` of the pair's info), which the rule cannot tell from
    staying still, and where the base stayed still over the pairs from the frame before and the frame
    after, which together span the pair's frames.

    A fit of the whole object over a still base and a moving part drags the base's points by a
    fraction of the part's motion. Below the threshold such a drift is noise to the rule, but
    chained from pair to pair it would carry the base's poses away, and with them the axes of its
    joints. Above it, between two pairs that saw the base still, the base would have had to move
    and stop again within a frame: the fit is a blend of the base's motion and a part's."""
    own = {pair: m for (pair, m), t in track.items() if t == base}
    still = {
        pair: result.pairs[pair].decision == "NM"
        or result.pairs[pair].motions[m].displacement_m <= result.pairs[pair].info.get("threshold_m", -1.0)
        for pair, m in own.items()
    }
    starts = {result.pairs[pair].i: pair for pair in own}

    def framed(pair: int) -> bool:
        p = result.pairs[pair]
        before, after = starts.get(p.i - 1), starts.get(p.i + 1)
        return (
            before is not None
            and after is not None
            and still[before]
            and still[after]
            and max(result.pairs[before].j, result.pairs[after].j) >= p.j
        )

    return {
        pair: np.eye(4) if still[pair] or framed(pair) else result.pairs[pair].motions[m].T_target_from_source
        for pair, m in own.items()
    }


def chain_pair_motions(n_frames: int, pairs, *, origin_m: np.ndarray) -> np.ndarray:
    """Per-frame poses of a part from its motions between frame pairs.

    Parameters
    ----------
    n_frames : int
    pairs : iterable of (i, j, T_j_from_i)
        ``T_j_from_i`` (4, 4) moves the part, in its parent's frame, from where it is in frame i to
        where it is in frame j (metres).
    origin_m : ndarray, shape (3,)
        The part's origin (e.g. its centroid) in the parent's frame in the first frame reached.

    Returns
    -------
    ndarray, shape (n_frames, 4, 4): the part's pose in each frame, identity rotation and ``origin_m``
    in the first frame of any pair; NaN for frames no chain of pairs reaches from it. Each frame is
    reached by the fewest pairs (breadth first), so errors add up over as few steps as possible.
    """
    links: dict[int, list[tuple[int, np.ndarray]]] = {}
    for i, j, T in pairs:
        T = np.asarray(T, float)
        if not np.isfinite(T).all():
            continue
        links.setdefault(int(i), []).append((int(j), T))
        links.setdefault(int(j), []).append((int(i), np.linalg.inv(T)))
    poses = np.full((n_frames, 4, 4), np.nan)
    if not links:
        return poses
    root = min(links)
    poses[root] = np.eye(4)
    poses[root, :3, 3] = origin_m
    frontier = [root]
    while frontier:
        following = []
        for i in frontier:
            for j, T in links[i]:
                if np.isnan(poses[j, 0, 0]):
                    poses[j] = T @ poses[i]
                    following.append(j)
        frontier = following
    return poses


def _interpolated(poses: np.ndarray, known: np.ndarray, frame: int) -> np.ndarray:
    """The pose at ``frame`` between the nearest known frames, moving at constant velocity along the
    screw motion between them (beyond the ends, that of the nearest two)."""
    frames = np.flatnonzero(known)
    if len(frames) == 1:
        return poses[frames[0]]
    after = int(np.clip(np.searchsorted(frames, frame), 1, len(frames) - 1))
    a, b = frames[after - 1], frames[after]
    return _screw(poses[b] @ np.linalg.inv(poses[a]), (frame - a) / (b - a)) @ poses[a]


def chain_interleaved(n_frames: int, pairs: list[tuple[int, int, np.ndarray]]) -> np.ndarray:
    """Poses (n_frames, 4, 4) of a body in every frame from its motions ``T_j_from_i`` between frame
    pairs, relative to the first frame reached (identity there); chains of pairs that do not meet
    (pairs (i, i + k) form k of them) are placed by interpolating the first chain's poses in time.
    NaN where no pair reaches."""
    poses = chain_pair_motions(n_frames, pairs, origin_m=np.zeros(3))
    while True:
        known = np.isfinite(poses).all(axis=(1, 2))
        rest = [(i, j, T) for i, j, T in pairs if not (known[i] or known[j])]
        if not rest:
            return poses
        part = chain_pair_motions(n_frames, rest, origin_m=np.zeros(3))
        root = int(np.flatnonzero(np.isfinite(part).all(axis=(1, 2)))[0])
        start = _interpolated(poses, known, root)
        reached = np.isfinite(part).all(axis=(1, 2))
        poses[reached] = part[reached] @ start


def _linked_by_motion(
    result: RunResult,
    observations: list[_Observation],
    track: dict[tuple, int],
    base: int,
    base_poses: np.ndarray,
    *,
    link_sigmas: float,
) -> dict[tuple, int]:
    """The tracks with two moving tracks joined where a motion of each moves the part alike relative
    to the base, as one joint does: a one-degree-of-freedom joint moves by ``exp(Δq ξ)``, so the
    velocity fields ``log`` of the two relative motions give at the two regions' points are one
    field scaled by the pairs' Δq. They are when one, scaled to fit the other, misses it by less than
    ``link_sigmas`` times the depth noise of the two pairs together (the root sum of squares: the
    miss is a difference of their fields; median over the points), and each moves the points by
    more than ``link_sigmas`` times its own pair's depth noise (a field is one pair's measurement).
    Best fit first, never two motions of one pair in one track; small parts whose regions in two
    pairs overlap too little to be joined by :func:`_tracks` are joined here."""
    moving = _moving_nodes(result, observations, track, base, base_poses)
    links = []
    for (a, va), (b, vb) in itertools.combinations(moving.items(), 2):
        if track[a] == track[b]:
            continue
        field_a, field_b = va[1](np.vstack([va[0], vb[0]])), vb[1](np.vstack([va[0], vb[0]]))
        scale = float(np.sum(field_a * field_b)) / max(float(np.sum(field_b * field_b)), 1e-18)
        noise_a, noise_b = result.pairs[a[0]].points.noise_m, result.pairs[b[0]].points.noise_m
        noise = float(np.hypot(noise_a, noise_b))  # of a difference of the two pairs' fields
        moves = all(
            np.median(np.linalg.norm(f, axis=1)) > link_sigmas * n
            for f, n in ((field_a, noise_a), (field_b, noise_b))
        )
        miss = float(np.median(np.linalg.norm(field_a - scale * field_b, axis=1)))
        if moves and miss < link_sigmas * noise:
            links.append((miss / noise, track[a], track[b]))
    pairs: dict[int, set[int]] = {}
    for node, t in track.items():
        pairs.setdefault(t, set()).add(node[0])
    groups = _Groups(pairs)
    for _, ta, tb in sorted(links):
        groups.join(ta, tb)
    return {node: groups.root(t) for node, t in track.items()}


def _moving_nodes(
    result: RunResult,
    observations: list[_Observation],
    track: dict[tuple, int],
    base: int,
    base_poses: np.ndarray,
) -> dict[tuple, tuple[np.ndarray, Any]]:
    """Each moving node (pair, motion) of an AM pair that also found the base: its points (N, 3) in
    the base's first-frame coordinates, and the velocity field (points (M, 3) -> (M, 3), metres) of
    the log of its motion relative to the base."""
    base_of = {pair: m for (pair, m), t in track.items() if t == base}
    base_motions = _base_motions(result, track, base)
    out = {}
    for o in observations:
        G = base_poses[o.frame]
        if not o.forward or not np.isfinite(G).all() or o.pair not in base_of:
            continue
        p = result.pairs[o.pair]
        local = transform(o.points, np.linalg.inv(G))
        for m in np.unique(o.labels[(o.labels >= 0) & (o.labels != base_of[o.pair])]):
            motion = {o.pair: p.motions[m].T_target_from_source}
            parent = {o.pair: base_motions[o.pair]}
            relative = _relative_motions(result, motion, parent, base_poses)
            if relative:
                w, v = _twist_log(relative[0][2])
                out[(o.pair, int(m))] = (local[o.labels == m], lambda x, w=w, v=v: np.cross(w, x) + v)
    return out
