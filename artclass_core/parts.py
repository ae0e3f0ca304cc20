"""Parts and joints over a whole video, from the per-pair motions and point labels of a finished run.

A rule that decides from motions gives every pair (i, j) its rigid motions and labels each point of
frame i (and, judged the other way, of frame j) with the motion that explains it. This module links
those per-pair segments through the frames into parts, and grows the tree of joints between them:

1. **Tracks.** A pair's motion and another pair's motion are the same part when their labelled points
   overlap (intersection over union of at least ``min_overlap``): on the same frame (a pair's source
   and an earlier pair's target are one cloud) or on neighbouring frames (the same pixels, which
   move little in one frame). Overlaps are merged greedily, largest first, never putting two motions
   of one pair into one part.
2. **Base.** The part found still (its motion below the rule's threshold) in the most pairs that
   show the object articulated: the hand moves the part it holds and leaves the base on the table,
   and the base need not be the largest part. When no part is ever still (the object is carried),
   the part with the most labelled points. A pair that found one motion saw the whole object move
   as one body: its motion is the base's.
3. **Base poses.** The base's motions are chained through the pairs into its pose in every frame,
   relative to the first frame. A motion the rule cannot tell from staying still (below its motion
   threshold, or in a pair it found without motion) is the identity: a fit that drags a still base
   by a fraction of a moving part's motion would otherwise carry its poses away, pair after pair.
   So is a motion between two pairs, from the frame before and the frame after, that saw the base
   still over all the pair's frames: a blend of the base's motion and a part's.
   Pairs (i, i + k) link only every k-th frame; the k interleaved chains
   are tied together by interpolating the first chain's poses in time (constant velocity).
   A small part's regions in two pairs may overlap too little to be linked in step 1; two of its
   tracks are then linked by their motions relative to the base, which for one joint are one
   velocity field scaled by each pair's change of state (within ``link_sigmas`` of the depth
   noise). Every part other than the base seen moving in at least ``min_pairs`` pairs is a moving
   part.
4. **Joints.** Each pair that sees a moving part and a candidate parent gives the part's motion
   relative to the parent, in the parent's coordinates at its state 0 (for the base: its coordinates
   of the first frame, the camera frame of frame 0 when the base does not move). For a
   one-degree-of-freedom joint each is ``exp(Δq ξ)``, one twist ξ whatever the pair, so the joint
   estimator is given the part's pose moved by each relative motion and by its inverse, and told
   that only one pose per pair is independent (so its chi-square tests and BIC count each pair's
   evidence once). The states per frame follow by least squares from the
   pairs' differences ``q_j - q_i = Δq``, the interleaved chains of pairs tied by a weak smoothness
   term between neighbouring frames.
5. **Tree.** Grown from the base, it attaches at each step the moving part whose joint on a part
   already in the tree has the lowest BIC per pose, as Sturm et al. choose the kinematic tree: the
   outer arm of a chain (a lamp's, a folding ruler's) hangs on the inner arm, relative to which it
   has one degree of freedom, not on the base. A joint's residuals that neighbouring pairs share are
   counted as misfit, not noise: a part carried along a curve by a linkage (a desk lamp's head)
   keeps its orientation relative to the base and passes for a slide there, but its travel turns
   from pair to pair. Every joint and every part's points are given in the base's first-frame
   coordinates with all joints at state 0.
6. **Part images.** Each frame's segmentation comes from the parts' motions over the whole video,
   not from one pair's labels (which may be wrong near a seam, or missing where no pair separated
   the parts): each object point, moved by each part's motion to the frames where the parts' motions
   differ most, takes the part that puts it on the surface seen there, as multi-body trackers keep
   their segmentation consistent. Where the depth cannot tell (a part sliding along a surface puts
   the surface's points on it too), the texture can: the point takes the part whose motion leaves its
   intensity as it was. In a frame where no pair gave a part's state, the state is found
   first by looking the part's points up in the frame at each state of its joint. Where too few of
   them are found there (the part hidden, or turned away), the state is the one between the nearest
   frames that gave one (held at the ends of the video), and where no pair separated the parts
   either, each of the frame's points takes the part whose points, placed there by the joints, are
   nearest: every frame gets its parts, and a part hidden for a while keeps its track. A frame no
   pair reaches is labelled so too, with the base placed between the frames before and after it.
"""

from __future__ import annotations

import functools
import inspect
import itertools
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from .errors import ArtclassError
from .geometry import transform
from .interfaces import JointEstimate, JointEstimator
from .params import Params, param
from .types import RunResult


@dataclass(frozen=True)
class PartsParams(Params):
    min_overlap: float = param(
        0.25,
        unit="fraction",
        bounds=(0.05, 1.0),
        help="Two labelled regions (of two pairs, on one frame or neighbouring frames) may be "
        "one part when their intersection over union reaches this (the larger overlaps "
        "are merged first, and never two motions of one pair).",
    )
    link_sigmas: float = param(
        5.0,
        unit="sigma",
        bounds=(0.0, 100.0),
        help="Two moving regions that overlap (however little) are one part when their motions "
        "relative to the base move the regions' points alike, one scaled to the other, within this "
        "many depth-noise levels of the two pairs together (and each moves them by more than this "
        "many of its own pair's).",
    )
    min_pairs: int = param(
        2,
        unit="pairs",
        bounds=(1, 10_000),
        help="A moving part must be seen moving relative to the base in at least this many pairs.",
    )
    smoothness: float = param(
        1e-3,
        unit="1",
        bounds=(1e-9, 1.0),
        help="Weight of the smoothness term between neighbouring frames' states, relative to a "
        "pair difference: it only places the interleaved chains of pairs relative to each "
        "other.",
    )
    ambiguity_sigmas: float = param(
        3.0,
        unit="sigma",
        bounds=(0.0, 100.0),
        help="An object point takes the part whose motion puts it nearest a surface seen in the "
        "other frames when the next part's puts it farther by more than this many depth-noise "
        "levels; else the part whose motion changes its intensity least, when the next part's "
        "changes it more by over this many intensity-noise levels; otherwise the part of the "
        "nearest point that was decided.",
    )
    n_views: int = param(
        4,
        unit="frames",
        bounds=(0, 100),
        help="Each frame's part segmentation comes from the parts' motions: its points are looked up "
        "in this many other frames (those where the parts' motions move them most differently). "
        "0: each frame keeps the labels of one pair.",
    )
    min_seen: float = param(
        0.5,
        unit="fraction",
        bounds=(0.0, 1.0),
        help="A part's state is found in a frame no pair relates it in when at least this share of "
        "its points, moved there by its joint, lands on a surface seen in the frame.",
    )
    reach_sigmas: float = param(
        5.0,
        unit="sigma",
        bounds=(0.0, 100.0),
        help="A part's motion puts an object point on a surface seen in another frame when it lands "
        "within this many depth-noise levels of it (plus the spacing of the points) along the "
        "camera's ray.",
    )


@dataclass
class Part:
    """A part of the object over the video.

    Attributes
    ----------
    index : int, 0 for the base
    name : str
    parent : int, the parent part's index (-1 for the base)
    points_m : ndarray, shape (N, 3), metres: the part's points with every joint at state 0, in the
        base's coordinates of the first frame (the URDF moves a child's into its joint frame)
    frames : list of int: the frames in which the part was labelled
    n_labelled : int: its labelled points over all frames
    """

    index: int
    name: str
    parent: int
    points_m: np.ndarray
    frames: list[int]
    n_labelled: int

    def to_dict(self) -> dict[str, Any]:
        return dict(
            index=self.index,
            name=self.name,
            parent=self.parent,
            n_frames=len(self.frames),
            n_labelled=self.n_labelled,
            n_points=len(self.points_m),
        )


@dataclass
class PartJoint:
    """The joint of ``child`` on ``parent`` (part indices): the estimate in the base's coordinates of
    the first frame with every joint at state 0, and a state per frame of the video."""

    parent: int
    child: int
    estimate: JointEstimate
    n_pairs: int

    def to_dict(self, *, up: np.ndarray) -> dict[str, Any]:
        e = self.estimate

        def vec(v):
            return None if v is None else [round(float(x), 6) for x in v]

        def num(x):
            return None if x is None or not np.isfinite(x) else round(float(x), 6)

        return dict(
            parent=self.parent,
            child=self.child,
            type=e.type,
            summary=e.summary(up=up),
            axis_direction=vec(e.axis_direction),
            axis_point_m=vec(e.axis_point_m),
            axis_direction_std_rad=num(e.axis_direction_std_rad),
            axis_point_std_m=num(e.axis_point_std_m),
            state_unit=e.state_unit,
            states=[num(q) for q in e.states],
            states_std=[num(q) for q in (e.states_std if e.states_std is not None else e.states * np.nan)],
            n_pairs=self.n_pairs,
            scores={k: round(v, 3) for k, v in e.scores.items()},
            info={k: (round(v, 6) if isinstance(v, float) else v) for k, v in e.info.items()},
        )


@dataclass
class Articulation:
    """The parts and joints found in a run.

    ``base_poses[f]`` maps the base's coordinates of the first frame to camera coordinates of frame f
    (NaN where unknown). ``label_image(f)`` gives frame f's part segmentation.
    """

    parts: list[Part]
    joints: list[PartJoint]
    base_poses: np.ndarray
    _views: dict[int, tuple] = field(default_factory=dict, repr=False)

    #: The camera's vertical (y points down), the reference of "from vertical" in the summaries.
    UP = np.array([0.0, -1.0, 0.0])

    def summary(self) -> str:
        """One line per joint (naming its two parts when there are several), or why there is none."""
        if not self.joints:
            return "no joint: no part moves relative to the rest"
        if len(self.joints) == 1:
            return self.joints[0].estimate.summary(up=self.UP)
        name = {p.index: p.name for p in self.parts}
        return "; ".join(
            f"{name[j.child]} on {name[j.parent]}: {j.estimate.summary(up=self.UP)}" for j in self.joints
        )

    def to_dict(self) -> dict[str, Any]:
        return dict(
            parts=[p.to_dict() for p in self.parts], joints=[j.to_dict(up=self.UP) for j in self.joints]
        )

    @property
    def frames(self) -> list[int]:
        """Frames with a part segmentation."""
        return sorted(self._views)

    def label_image(self, frame: int) -> np.ndarray | None:
        """Frame ``frame``'s part segmentation, shape (H, W), uint8: 0 = not the object, 1 + part index;
        each pixel of the segmenter's mask takes the part of the nearest labelled point. None when no
        pair labelled the frame."""
        if frame not in self._views:
            return None
        pixels, part, mask, stride = self._views[frame]
        seeds = np.zeros(mask.shape, np.uint8)
        seeds[pixels[:, 1], pixels[:, 0]] = part + 1
        if not mask.any():
            mask = cv2.dilate((seeds > 0).astype(np.uint8), np.ones((stride, stride), np.uint8)) > 0
        _, (rows, cols) = distance_transform_edt(seeds == 0, return_indices=True)
        return np.where(mask, seeds[rows, cols], 0).astype(np.uint8)


# -- the pairs' labelled points ------------------------------------------------------------------------


@dataclass
class _Observation:
    """One pair's labelling of one frame: pixels (N, 2), points (N, 3, camera frame) and motion labels."""

    pair: int
    frame: int
    pixels: np.ndarray
    points: np.ndarray
    labels: np.ndarray
    forward: bool

    @functools.cached_property
    def counts(self) -> np.ndarray:
        """How many points each motion (by number) labels."""
        return np.bincount(self.labels[self.labels >= 0])

    @property
    def motions(self) -> np.ndarray:
        """The motions (numbers) that label some of the points."""
        return np.flatnonzero(self.counts)

    @functools.cached_property
    def keys(self) -> tuple[np.ndarray, np.ndarray]:
        """Each point's pixel as one number, and the order that sorts them (to find shared pixels)."""
        keys = self.pixels[:, 1].astype(np.int64) * 1_000_000 + self.pixels[:, 0]
        return keys, np.argsort(keys)


def _observations(result: RunResult) -> list[_Observation]:
    """Each labelled pair's labelling of its source frame and of its target frame."""
    clouds = {f.index: f.cloud for f in result.frames if f.cloud is not None}
    out = []
    for n, p in enumerate(result.pairs):
        if p.labels is None or not p.motions or p.decision == "skipped":
            continue
        ev = p.evidence
        if ev is not None:
            cut = ev.n_source if ev.n_source is not None else len(ev.points)
            sides = ((p.i, slice(0, cut), True), (p.j, slice(cut, len(ev.points)), False))
            for frame, part, forward in sides:
                out.append(_Observation(n, frame, ev.pixels[part], ev.points[part], p.labels[part], forward))
        elif p.i in clouds and clouds[p.i].pixels is not None:
            c = clouds[p.i]
            out.append(_Observation(n, p.i, c.pixels, c.points, p.labels[: len(c.points)], True))
        else:
            raise ArtclassError("finding parts needs each pair's labelled points: run with keep_clouds=True")
    return out


# -- 1. tracks: which motions of which pairs are one part -------------------------------------------------


def _overlaps(a: _Observation, b: _Observation) -> list[tuple[float, tuple, tuple]]:
    """(IoU, node a, node b) of every pair of motions of two labellings of one or neighbouring frames,
    over the pixels both label."""
    from ._looks import contingency  # Numba, loaded on first use

    if not len(a.labels) or not len(b.labels):
        return []
    table = contingency(*a.keys, np.asarray(a.labels, np.int64), *b.keys, np.asarray(b.labels, np.int64))
    in_a, in_b = table.sum(axis=1)[1:], table.sum(axis=0)[1:]  # row and column 0: no motion
    table = table[1:, 1:]
    m, n = np.nonzero(table)
    iou = table[m, n] / (in_a[m] + in_b[n] - table[m, n])
    return [(float(x), (a.pair, int(i)), (b.pair, int(j))) for x, i, j in zip(iou, m, n)]


class _Groups:
    """Disjoint groups of nodes (union-find), each holding a set of pairs: two groups are joined only
    when they hold no pair in common (one part has at most one motion in a pair)."""

    def __init__(self, pairs: dict[Any, set[int]]):
        self.parent = {n: n for n in pairs}
        self.pairs = {n: set(p) for n, p in pairs.items()}  # by root

    def root(self, n):
        while self.parent[n] != n:
            self.parent[n] = self.parent[self.parent[n]]
            n = self.parent[n]
        return n

    def join(self, a, b) -> None:
        ra, rb = self.root(a), self.root(b)
        if ra != rb and not self.pairs[ra] & self.pairs[rb]:
            self.parent[rb] = ra
            self.pairs[ra] |= self.pairs.pop(rb)


def _tracks(observations: list[_Observation], *, min_overlap: float) -> dict[tuple, int]:
    """Track number of every node (pair, motion): greedy merging by overlap, largest first, never two
    motions of one pair in one track."""
    nodes = {(o.pair, int(m)) for o in observations for m in o.motions}
    by_frame: dict[int, list[_Observation]] = {}
    for o in observations:
        by_frame.setdefault(o.frame, []).append(o)
    edges = []
    for f, here in by_frame.items():
        for x in range(len(here)):
            for y in range(x + 1, len(here)):
                if here[x].pair != here[y].pair:
                    edges += _overlaps(here[x], here[y])
        for other in by_frame.get(f + 1, []):
            for o in here:
                if o.pair != other.pair:
                    edges += _overlaps(o, other)
    groups = _Groups({n: {n[0]} for n in nodes})
    root = groups.root

    def merge(edges):
        for iou, a, b in sorted(edges, key=lambda e: -e[0]):
            if iou < min_overlap:
                break
            groups.join(a, b)

    merge(edges)
    # a part hidden for a while: the track that ends before another begins, on the frames either side
    frames: dict[tuple, set] = {}
    for o in observations:
        for m in o.motions:
            frames.setdefault(root((o.pair, int(m))), set()).add(o.frame)
    gaps = []
    for ra, fa in frames.items():
        for rb, fb in frames.items():
            if ra != rb and max(fa) < min(fb) and not groups.pairs[ra] & groups.pairs[rb]:
                gaps += [
                    e
                    for x in by_frame[max(fa)]
                    for y in by_frame[min(fb)]
                    for e in _overlaps(x, y)
                    if root(e[1]) == ra and root(e[2]) == rb
                ]
    merge(gaps)
    roots = sorted({root(n) for n in nodes})
    return {n: roots.index(root(n)) for n in nodes}


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
        noise_a, noise_b = result.pairs[a[0]].evidence.noise_m, result.pairs[b[0]].evidence.noise_m
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


# -- poses chained through pairs ---------------------------------------------------------------------------


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


# -- 3. base poses --------------------------------------------------------------------------------------


def _V(w: np.ndarray) -> np.ndarray:
    """The matrix (3, 3) by which exp of the twist (w, v) moves the origin: V(w) v."""
    theta = float(np.sqrt(w @ w))
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])  # K v = w x v
    if theta < 1e-9:
        return np.eye(3) + K / 2
    return np.eye(3) + (1 - np.cos(theta)) / theta**2 * K + (theta - np.sin(theta)) / theta**3 * (K @ K)


def _twist_log(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The twist (w, v), radians and metres, with exp(w, v) the rigid motion T (4, 4)."""
    w = cv2.Rodrigues(np.ascontiguousarray(T[:3, :3]))[0].ravel()  # as scipy's Rotation, 20 times faster
    return w, np.linalg.solve(_V(w), T[:3, 3])


def _screw(T: np.ndarray, s: float) -> np.ndarray:
    """The rigid motion T (4, 4) taken ``s`` times along its screw: ``exp(s log T)``."""
    w, v = _twist_log(T)
    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(s * w)[0]
    out[:3, 3] = _V(s * w) @ (s * v)
    return out


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


# -- 4. joints ----------------------------------------------------------------------------------------


def _translation(v: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = v
    return T


def frame_states(
    n_frames: int, pairs: list[tuple[int, int]], deltas: np.ndarray, stds: np.ndarray, *, smoothness: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame states (n_frames,) and their standard deviations from pair differences
    ``q_j - q_i = deltas`` (with standard deviations ``stds``), by weighted least squares.

    Neighbouring frames are tied by ``q_{f-1} - 2 q_f + q_{f+1} = 0`` (constant speed) at
    ``smoothness`` times the weight of the best pair: this decides only what the pairs leave open (how
    the interleaved chains of pairs (i, i + k) sit relative to each other, and a part's motion while
    it was hidden), as the smoothest motion. States are relative to the first
    frame of any pair; NaN for frames no pair reaches.
    """
    seen = sorted({f for p in pairs for f in p})
    states, std = np.full(n_frames, np.nan), np.full(n_frames, np.nan)
    if not seen:
        return states, std
    frames = list(range(seen[0], seen[-1] + 1))  # frames between the pairs' are tied through too
    col = {f: c for c, f in enumerate(frames)}
    weights = 1.0 / np.maximum(np.asarray(stds, float), 1e-12)
    tie = smoothness * float(weights.max())
    A = np.zeros((len(pairs) + len(frames), len(frames)))
    y = np.zeros(len(A))
    for r, ((i, j), d, w) in enumerate(zip(pairs, deltas, weights)):
        A[r, col[j]], A[r, col[i]], y[r] = w, -w, d * w
    for r, c in enumerate(range(1, len(frames) - 1), start=len(pairs)):
        A[r, c - 1], A[r, c], A[r, c + 1] = tie, -2 * tie, tie
    A[-1, 0] = tie  # the first frame's state is 0
    q = np.linalg.lstsq(A, y, rcond=None)[0]
    cov = np.linalg.pinv(A.T @ A)
    rows = [col[f] for f in seen]
    states[seen] = q[rows] - q[0]
    std[seen] = np.sqrt(np.clip(np.diag(cov) + cov[0, 0] - 2 * cov[:, 0], 0, None))[rows]
    return states, std


def _pair_joint(
    relative: list[tuple[int, int, np.ndarray]],
    centre_m: np.ndarray,
    n_frames: int,
    *,
    estimator: JointEstimator,
    smoothness: float,
    reach_m: float | None = None,
) -> tuple[JointEstimate, int]:
    """The joint from a part's relative motions (i, j, motion in the base's first-frame coordinates)
    and the number of pairs it explains. The estimator sees the part's pose (origin ``centre_m``)
    moved by each relative motion and by its inverse, and unmoved: for a one-degree-of-freedom joint
    all lie on one path, ``exp(±Δq ξ)``; one pose per pair is independent. ``reach_m``: how far the
    object reaches from ``centre_m``."""
    start = _translation(centre_m)
    poses = np.stack(
        [start] + [M @ start for _, _, M in relative] + [np.linalg.inv(M) @ start for _, _, M in relative]
    )
    n = len(relative)
    estimate = estimate_joint(estimator, poses, n_independent=n, reach_m=reach_m)
    forward, backward = np.arange(1, n + 1), np.arange(n + 1, 2 * n + 1)
    explained = (
        estimate.inliers[forward]
        & estimate.inliers[backward]
        & np.isfinite(estimate.states[forward])
        & np.isfinite(estimate.states[backward])
    )
    keep = np.flatnonzero(explained) if estimate.type not in ("fixed", "free") else np.zeros(0, int)
    states = np.full(n_frames, np.nan)
    std = np.full(n_frames, np.nan)
    direction = estimate.axis_direction
    misfit = 0.0
    if len(keep):
        deltas = (estimate.states[forward[keep]] - estimate.states[backward[keep]]) / 2
        misfit = smooth_misfit(_pair_residuals(estimate, [relative[k][2] for k in keep], deltas, centre_m))
        spread = estimate.states_std if estimate.states_std is not None else np.ones(len(poses))
        pair_std = np.nan_to_num(np.hypot(spread[forward[keep]], spread[backward[keep]]) / 2, nan=1.0)
        states, std = frame_states(
            n_frames, [relative[k][:2] for k in keep], deltas, pair_std, smoothness=smoothness
        )
        if states[np.nanargmax(np.abs(states))] < 0:
            states, direction = -states, -direction  # rising states; the axis turns with them
    elif estimate.type == "fixed":
        states[sorted({f for i, j, _ in relative for f in (i, j)})] = 0.0
        std = np.where(np.isfinite(states), 0.0, np.nan)
    info = dict(
        estimate.info,
        n_pairs=n,
        n_pairs_explained=int(explained.sum()),
        n_poses_explained=float(estimate.inliers.sum() * n / len(poses)),  # independent ones
        smooth_misfit=misfit,
    )
    return JointEstimate(
        estimate.type,
        direction,
        estimate.axis_point_m,
        states,
        np.isfinite(states),
        estimate.axis_direction_std_rad,
        estimate.axis_point_std_m,
        std,
        estimate.scores,
        info,
    ), int(explained.sum())


def _pair_residuals(
    estimate: JointEstimate, motions: list[np.ndarray], deltas: np.ndarray, centre_m: np.ndarray
) -> np.ndarray:
    """How far each pair's relative motion (4, 4) is from the joint's motion over the pair's change of
    state ``deltas`` (K,): the part's centre ``centre_m`` moved by the difference (metres), then the
    rotation vector of the difference (radians), (K, 6)."""
    predicted = joint_motion(estimate, deltas)
    error = np.linalg.inv(predicted) @ np.stack(motions)
    moved = error[:, :3, :3] @ centre_m + error[:, :3, 3] - centre_m
    return np.hstack([moved, Rotation.from_matrix(error[:, :3, :3]).as_rotvec()])


#: Pairs a joint must explain before its residuals are judged against their neighbours' (two
#: differences of neighbouring pairs, the fewest a median of them needs).
_MIN_NEIGHBOURS = 3


def smooth_misfit(residuals: np.ndarray) -> float:
    """How much of a joint's misfit is smooth in time, per pose: 0 when its residuals are noise.

    Parameters
    ----------
    residuals : ndarray, shape (K, 6)
        Each pair's position (metres) and rotation (radians) residual against the joint, pairs in
        the order of their frames.

    Returns
    -------
    float
        ``3 (rho_pos - 1) + 3 (rho_rot - 1)`` (each term at least 0), with rho the median squared
        residual over half the median squared difference of neighbouring pairs' residuals: the noise
        of two pairs is independent, so their difference has twice its variance; a path the joint
        does not follow (a part carried along a curve by a linkage, which keeps its orientation
        and is fitted as a slide) leaves residuals that neighbouring pairs share, small differences
        and a large rho. With the noise taken from the differences, rho - 1 per component is what
        the misfit adds to the chi-square of a pose. 0 for fewer than ``_MIN_NEIGHBOURS`` pairs.
    """
    residuals = np.asarray(residuals, float)
    if len(residuals) < _MIN_NEIGHBOURS:
        return 0.0
    steps = np.diff(residuals, axis=0)
    out = 0.0
    for part in (slice(0, 3), slice(3, 6)):
        spread = float(np.median(np.sum(residuals[:, part] ** 2, axis=1)))
        noise = float(np.median(np.sum(steps[:, part] ** 2, axis=1))) / 2
        if noise > 0:
            out += 3 * max(spread / noise - 1, 0.0)
    return out


def estimate_joint(estimator: JointEstimator, poses: np.ndarray, **evidence: Any) -> JointEstimate:
    """``estimator.estimate(poses, **evidence)``, leaving out the keywords (``n_independent``,
    ``reach_m``) that an estimator written before they existed does not take."""
    parameters = inspect.signature(estimator.estimate).parameters.values()
    if not any(p.kind is p.VAR_KEYWORD for p in parameters):
        taken = {p.name for p in parameters}
        evidence = {k: v for k, v in evidence.items() if k in taken}
    return estimator.estimate(poses, **evidence)


def joint_motion(estimate: JointEstimate, state) -> np.ndarray:
    """The motion of the child, in the parent's coordinates, from state 0 to ``state``: (4, 4) for
    one state, (N, 4, 4) for states (N,) (the identity where a state is not finite)."""
    states = np.asarray(state, float)
    q = np.where(np.isfinite(states), states, 0.0).reshape(-1)
    T = np.tile(np.eye(4), (len(q), 1, 1))
    if estimate.axis_direction is not None:
        d = np.asarray(estimate.axis_direction, float)
        if estimate.type == "prismatic":
            T[:, :3, 3] = q[:, None] * d
        else:
            R = Rotation.from_rotvec(q[:, None] * d).as_matrix()
            c = np.asarray(estimate.axis_point_m, float)
            pitch = estimate.info.get("pitch_m_per_rad", 0.0)
            T[:, :3, :3], T[:, :3, 3] = R, c - R @ c + q[:, None] * d * pitch
    return T.reshape(states.shape + (4, 4))


# -- the whole ---------------------------------------------------------------------------------------------


def find_articulation(
    result: RunResult, *, estimator: JointEstimator, params: PartsParams = PartsParams()
) -> Articulation:
    """Parts and joints over the video of a finished run (see the module docstring).

    Parameters
    ----------
    result : RunResult
        A run of a rule that decides from motions, with ``keep_clouds=True`` (the pairs' labelled
        points are needed). A sequence not labelled articulated gets the base only and no joint.
    estimator : JointEstimator
        The joint estimator (``registry.create("joint_estimator", "bic")`` for the built-in one).
    params : PartsParams

    Returns
    -------
    Articulation
    """
    n_frames = int(result.sequence.get("n_frames") or len(result.frames))
    observations = _observations(result)
    if result.label == "articulated":
        track = _tracks(observations, min_overlap=params.min_overlap)
    else:  # one body: each pair's first motion is the object's
        track = {(o.pair, int(m)): 0 if m == 0 else 1 for o in observations for m in o.motions}
    size = _track_sizes(observations, track)
    base = _still_track(result, track, size, min_pairs=params.min_pairs)
    track = _one_body_pairs_on(base, result, track)
    size = _track_sizes(observations, track)
    motions = _track_motions(result, track, base=base)
    base_poses = chain_interleaved(
        n_frames, [(result.pairs[n].i, result.pairs[n].j, T) for n, T in motions.get(base, {}).items()]
    )
    if result.label == "articulated":
        track = _linked_by_motion(
            result, observations, track, base, base_poses, link_sigmas=params.link_sigmas
        )
        size, motions = _track_sizes(observations, track), _track_motions(result, track, base=base)
    seen = _seen_tracks(result, track, min_pairs=params.min_pairs) if result.label == "articulated" else set()
    views, points = _part_points(result, observations, track, base_poses)
    tree = _kinematic_tree(
        result,
        base,
        sorted(seen - {base}, key=lambda t: -size[t]),
        motions,
        base_poses,
        points,
        n_frames,
        estimator=estimator,
        params=params,
    )
    number = {t: n for n, t in enumerate(tree)}
    if len(tree) > 1 and params.n_views:
        views = _relabelled(result, observations, views, tree, base_poses, params=params)
    joints = [
        PartJoint(number[link.parent], number[t], link.estimate, link.n_pairs)
        for t, link in tree.items()
        if link.estimate is not None
    ]
    parts = [
        _part(number[t], number.get(link.parent, -1), points.get(t, {}), link, size.get(t, 0))
        for t, link in tree.items()
    ]
    return Articulation(parts, joints, base_poses, _numbered(views, number))


def _track_sizes(observations: list[_Observation], track: dict[tuple, int]) -> dict[int, int]:
    """Labelled points of each track over all frames."""
    size: dict[int, int] = {}
    for o in observations:
        for m in o.motions:
            t = track[(o.pair, int(m))]
            size[t] = size.get(t, 0) + int(o.counts[m])
    return size


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


def _seen_tracks(result: RunResult, track: dict[tuple, int], *, min_pairs: int) -> set[int]:
    """The parts of an articulated object: the tracks found in at least ``min_pairs`` AM pairs."""
    count: dict[int, int] = {}
    for (pair, _), t in track.items():
        count[t] = count.get(t, 0) + (result.pairs[pair].decision == "AM")
    return {t for t, n in count.items() if n >= min_pairs}


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
    """The frames' track labellings as part numbers, keeping the points of the parts only."""
    out = {}
    for frame, (pixels, tracks, mask, stride) in views.items():
        lookup = np.full(int(tracks.max(initial=-1)) + 2, -1)
        for t, n in number.items():
            if t < len(lookup) - 1:
                lookup[t] = n
        part = lookup[tracks]  # track -1 reads the last entry, -1
        keep = part >= 0
        out[frame] = (pixels[keep], part[keep], mask, stride)
    return out


# -- the kinematic tree -------------------------------------------------------------------------------------


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
    to which it has one degree of freedom. Parts in tree order (parents first); a part that no
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
                    options.append((_joint_cost(fits[(child, parent)][0]), order, rank, child, parent))
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
    out[known] = parent[known] @ joint_motion(estimate, estimate.states[known])
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
    from ._looks import farthest  # Numba, loaded on first use

    placed = [f for f in parent if np.isfinite(placement[f]).all()]
    # a rigid motion keeps distances: a frame's parent points are measured from the centre placed there
    parent_from = [(parent[f], placement[f][:3, :3] @ centre_m + placement[f][:3, 3]) for f in placed]
    clouds = [(own_m, centre_m)] + (parent_from or [(points, centre_m) for points in parent.values()])
    return max(farthest(np.ascontiguousarray(points), centre) for points, centre in clouds)


def _relative_motions(
    result: RunResult,
    child: dict[int, np.ndarray],
    parent: dict[int, np.ndarray],
    parent_poses: np.ndarray,
) -> list[tuple[int, int, np.ndarray]]:
    """(i, j, the child's motion relative to the parent) of each AM pair that found both, in the
    parent's coordinates at state 0: ``G_i^-1 Q^-1 P G_i`` with P and Q the pair's child and parent
    motions and G_i (``parent_poses[i]``) the parent's pose in frame i."""
    relative = []
    for pair, P in child.items():
        p = result.pairs[pair]
        G = parent_poses[p.i]
        if pair in parent and p.decision == "AM" and np.isfinite(G).all():
            relative.append((p.i, p.j, np.linalg.inv(G) @ np.linalg.inv(parent[pair]) @ P @ G))
    return relative


def _part(index: int, parent: int, own: dict[int, np.ndarray], link: _Link, n_labelled: int) -> Part:
    """A part, its points from the frame where it shows most (among the frames where it is placed),
    brought back to state 0."""
    frames = [f for f in own if np.isfinite(link.placement[f]).all()] or list(own)
    cloud = np.zeros((0, 3))
    if frames:
        f = max(frames, key=lambda f: len(own[f]))
        cloud = own[f]
        if np.isfinite(link.placement[f]).all():
            cloud = transform(cloud, np.linalg.inv(link.placement[f]))
    return Part(index, "base" if index == 0 else f"part{index}", parent, cloud, sorted(own), n_labelled)


def forget_clouds(result: RunResult) -> None:
    """Drop the clouds and evidence a run kept for :func:`find_articulation` (they are large)."""
    for f in result.frames:
        f.cloud = None
    for p in result.pairs:
        p.evidence = None


def _mask(result: RunResult, frame: int) -> np.ndarray:
    cloud = result.frames[frame].cloud if frame < len(result.frames) else None
    view = getattr(cloud, "view", None)
    if view is not None and view.mask is not None:
        return view.mask
    if view is not None:
        return np.zeros(view.gray.shape, bool)
    raise ArtclassError(f"frame {frame} has no image to segment: run with keep_clouds=True")


def _stride(result: RunResult, frame: int) -> int:
    return int(result.frames[frame].info.get("stride_px", 1) or 1)


# -- 6. every frame's segmentation from the parts' motions ---------------------------------------------------


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
    from ._looks import by_depth, smoothed_at  # Numba, loaded on first use

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
    from ._looks import look_kernel  # Numba, loaded on first use

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
    as :func:`._looks.by_depth` gives them)."""
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
    from ._looks import by_shade  # Numba, loaded on first use

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
        placements[t][again] = parent[again] @ joint_motion(e, e.states[again])
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
        placements[t][todo] = parent[todo] @ joint_motion(e, states[todo])
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
    motions = joint_motion(e, grid)  # (G, 4, 4)
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


def _has_depth(result: RunResult, frame: int) -> bool:
    cloud = result.frames[frame].cloud if frame < len(result.frames) else None
    view = getattr(cloud, "view", None)
    return view is not None and view.depth_m is not None


def _frame_clouds(
    result: RunResult, observations: list[_Observation]
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Each frame's object pixels (N, 2) and points (N, 3, camera frame): the ones a pair labelled (a
    pair's source side first), else the frame's cloud."""
    out = {}
    for o in sorted(observations, key=lambda o: (o.frame, not o.forward)):
        out.setdefault(o.frame, (o.pixels, o.points))
    for f in result.frames:
        if f.index not in out and f.cloud is not None and f.cloud.pixels is not None:
            out[f.index] = (f.cloud.pixels, f.cloud.points)
    return out


def _noise(result: RunResult) -> float:
    """The pairs' median depth noise, metres."""
    values = [p.evidence.noise_m for p in result.pairs if p.evidence is not None]
    return float(np.median(values)) if values else 0.0


def _spacing(result: RunResult) -> float:
    """The pairs' median spacing of the sampled points on the object (pixel size times the stride), metres."""
    values = [
        p.evidence.pixel_m * p.evidence.info.get("stride_px", 1)
        for p in result.pairs
        if p.evidence is not None
    ]
    return float(np.median(values)) if values else 0.0
