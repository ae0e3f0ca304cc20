"""The video's label from the whole video, not from its pairs one by one.

A pair can show two motions where there is one body: real depth error, a calibration a few percent off,
a motion too large to register. Such pairs are isolated, and the "parts" they find move at random. So a
video is articulated only when a part is tracked across pairs and a joint (prismatic, revolute or screw)
over the whole trajectory explains its motion relative to the base better than no motion does: the
selection of Sturm, Stachniss & Burgard (JAIR 2011) between the rigid model and the joint models, made
by the run's part finder (its kinematic tree) and joint estimator.

A part that a hand moves moves continuously: its joint state at one frame is close to its state at the
next. The states of a "part" made by noise jump back and forth from frame to frame. So the states, in
the order of their frames, must change less from frame to frame than the same values in a random
order do: a permutation test of von Neumann's successive differences, one-sided at 5 %.

A turning joint that leaves its parent's surface where it was tells nothing either: a body of
revolution turning about its own axis (a kettle spun by its handle) looks still in depth, while it may
turn with the part; so does a plate turning in its own plane (a carried ruler). Nor does one that
leaves its part's surface where it was: two fits of a thin body that differ by a roll about its own
length (a carried pair of pliers) make a "joint" whose part shows no motion. The rigid object
explains such a video as well as the joint does. A parent that only partly slides along itself (a
microwave's carcass, whose top turns in its own plane under the door's hinge) is told by the rest:
its depth would change over a region as large as a part, and the pairs saw no such region move. A
sliding joint is kept: a drawer's carcass shows where it ends. And a joint keeps its parts in
contact: two bodies that separate (a kettle lifted off its base) are two objects.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.stats import permutation_test

from .articulation import Articulation, PartJoint
from .config import JOINT_ESTIMATOR, PART_FINDER
from .errors import ArtclassError
from .geometry import transform
from .plugins import Registry
from .types import RunResult

#: Joint models that make an object articulated: one degree of freedom along a trajectory.
JOINT_MODELS = ("prismatic", "revolute", "screw")
#: A part farther than this from its parent at an end of its travel is not held by a joint.
CONTACT_M = 0.03
#: A joint is told from a trajectory: two pairs' relative motions fit some joint almost always (a line
#: or an axis through two poses); each further pair tests it.
MIN_PAIRS = 3
#: A part counts as moving when states in a random order change as little from frame to frame as its
#: own do at most this often.
SIGNIFICANCE = 0.05
#: Random orders tried when there are more of them (all are tried for up to 7 states); seeded.
PERMUTATIONS = 9999
#: A parent whose points, moved by a step of its joint, land on its own surface for at least this share
#: (of those the step moves) is symmetric under the joint: it may move with the part unseen.
SYMMETRIC_SHARE = 0.5


def joints_over_video(
    registry: Registry, result: RunResult, *, part_finder: str = PART_FINDER, estimator: str = JOINT_ESTIMATOR
) -> tuple[bool, str]:
    """Whether a part of ``result`` (a run whose pairs kept their labelled points) moves about a joint
    over the video, and why, in a sentence."""
    am = [f"{p.i}-{p.j}" for p in result.pairs if p.decision == "AM"]
    shown = f"{len(am)} pairs show parts moving apart ({', '.join(am[:4])}{', ...' if len(am) > 4 else ''})"
    try:
        articulation = registry.create("part_finder", part_finder).find(
            result, estimator=registry.create("joint_estimator", estimator), images=False
        )
    except ArtclassError as exc:
        return False, f"{shown}, but no part could be tracked over the video ({exc})"
    joints = [j for j in articulation.joints if j.estimate.type in JOINT_MODELS and j.n_pairs >= MIN_PAIRS]
    if not joints:
        return False, f"{shown}, but no part moves about a joint over the video"
    tests = (
        (
            "the part's state jumps back and forth between frames, as noise does, not as a body moves",
            lambda j: moves_continuously(j.estimate.states),
        ),
        (
            f"the part leaves its parent (by over {CONTACT_M * 100:g} cm): two bodies that separate",
            lambda j: not separated(articulation, j),
        ),
        (
            "the joint turns its parent or its part within its own surface (a body about its own "
            "axis): the whole object may turn as one, or the part not at all",
            lambda j: (
                j.estimate.type == "prismatic"
                or not any(symmetric(result, articulation, j, k) for k in (j.parent, j.child))
            ),
        ),
    )
    for why, keeps in tests:
        joints = [j for j in joints if keeps(j)]
        if not joints:
            return False, f"{shown}, but {why}"
    j = max(joints, key=lambda j: j.n_pairs)
    return True, f"{shown}; part {j.child} moves about a {j.estimate.type} joint over {j.n_pairs} pairs"


def moves_continuously(states: np.ndarray) -> bool:
    """Whether the joint's ``states`` (one per frame, NaN where the part was not tracked) change from
    frame to frame less than chance allows: the sum of each step's squared change over the frames it
    spans, against the same values in random orders over the same frames: a continuous motion
    changes little in one frame and more over ten, noise as much in one as in ten. Four states never
    pass: two of their 24 orders are as smooth as any line."""
    frames = np.flatnonzero(np.isfinite(states))
    if len(frames) < 3 or np.ptp(states[frames]) == 0:
        return False
    gaps = np.diff(frames)

    def roughness(values, axis=-1):
        return np.sum(np.diff(values, axis=axis) ** 2 / gaps, axis=axis)

    test = permutation_test(
        (states[frames],),
        roughness,
        permutation_type="pairings",
        alternative="less",
        n_resamples=PERMUTATIONS,
        vectorized=True,
        random_state=0,
    )
    return bool(test.pvalue < SIGNIFICANCE)


def separated(articulation: Articulation, joint: PartJoint) -> bool:
    """Whether the part, moved by its joint to an end of the states seen, is nowhere within
    :data:`CONTACT_M` of its parent's points: a joint keeps its parts in contact at every state (a
    hinge, a slide in its guide); an object lifted off its stand does not."""
    child, parent = articulation.parts[joint.child].points_m, articulation.parts[joint.parent].points_m
    states = joint.estimate.states[np.isfinite(joint.estimate.states)]
    if not len(child) or not len(parent) or not len(states):
        return False
    tree = cKDTree(parent)
    ends = (float(states.min()), float(states.max()))
    return any(tree.query(transform(child, joint.estimate.motion(s)))[0].min() > CONTACT_M for s in ends)


def symmetric(result: RunResult, articulation: Articulation, joint: PartJoint, part: int) -> bool:
    """Whether the joint's typical step (the median change of its state over the run's pairs) could
    move ``part`` (the joint's parent or its child) unseen: it moves no point of the part by what a
    pair can see (three noise sigmas and a pixel), or it leaves at least :data:`SYMMETRIC_SHARE` of
    those it moves so on the part's surface (within three noise sigmas of the tangent plane at the
    nearest point, and three point spacings of that point), and the step one way or the other changes
    the depth the part shows the camera over no region as large as the run's rule takes a part to be
    (its smallest share of the object's points: :func:`depth_change`). A parent so moved may turn with
    its child unseen; a child so moved (a thin part rolled about its own length) shows no joint."""
    points, states = articulation.parts[part].points_m, joint.estimate.states
    steps = [abs(states[p.j] - states[p.i]) for p in result.pairs if p.j < len(states)]
    steps = [s for s in steps if np.isfinite(s) and s > 0]
    seen = [p.points for p in result.pairs if p.points is not None]
    if len(points) < 10 or not steps or not seen:
        return False
    noise = 3 * float(np.median([s.noise_m for s in seen]))
    visible = noise + float(np.median([s.pixel_m for s in seen]))
    step = float(np.median(steps))
    moved = transform(points, joint.estimate.motion(step))
    far = np.linalg.norm(moved - points, axis=1) > visible
    if not far.any():
        return True
    tree = cKDTree(points)
    neighbours = points[tree.query(points, k=8)[1]]  # (N, 8, 3)
    spread = neighbours - neighbours.mean(axis=1, keepdims=True)
    normals = np.linalg.eigh(np.einsum("nki,nkj->nij", spread, spread))[1][:, :, 0]
    spacing = float(np.median(np.linalg.norm(neighbours[:, 1] - points, axis=1)))
    gap, nearest = tree.query(moved[far])
    across = np.abs(np.einsum("ni,ni->n", moved[far] - points[nearest], normals[nearest]))
    if np.mean((gap <= 3 * spacing) & (across <= noise)) < SYMMETRIC_SHARE:
        return False
    rule = result.params.get("rule", {})
    n_object = sum(len(articulation.parts[k].points_m) for k in (joint.parent, joint.child))
    least = max(rule.get("min_part_points", 1), rule.get("min_part_share", 0.0) * n_object)
    moves = (transform(points, joint.estimate.motion(s)) for s in (step, -step))
    return any(depth_change(points, m, spacing, visible) < least for m in moves)


def depth_change(before: np.ndarray, after: np.ndarray, spacing_m: float, tolerance_m: float) -> int:
    """The most points of ``before`` in one connected region of the image where the depth that the
    points show a camera at the origin changes, moved to ``after``, by over ``tolerance_m``. The image
    has cells two point spacings wide, so that a seen surface fills each; a cell counts where both
    fill it. Its depth is its nearest point's, known to within half the depth its points span (where
    in the cell the nearest one falls: a steep surface, an edge), which the tolerance grows by."""
    both = np.vstack([before, after])
    cells = np.floor(both[:, :2] / both[:, 2:] / (2 * spacing_m / np.median(before[:, 2]))).astype(int)
    cells -= cells.min(axis=0)
    index, ranges = (np.repeat([0, 1], [len(before), len(after)]), *cells.T), np.linalg.norm(both, axis=1)
    near, far = np.full((2, 2, *(cells.max(axis=0) + 1)), [[[[np.inf]]], [[[-np.inf]]]])
    np.minimum.at(near, index, ranges)
    np.maximum.at(far, index, ranges)
    seen = np.isfinite(near).all(axis=0)
    near, span = np.where(seen, near, 0), np.where(seen, far - near, 0).max(axis=0)
    regions, count = ndimage.label(seen & (np.abs(near[0] - near[1]) > tolerance_m + span / 2))
    u, v = cells[: len(before)].T
    return int(np.bincount(regions[u, v], minlength=count + 1)[1:].max(initial=0))
