"""The whole: steps 1 to 6 as one short script (see the package docstring)."""

from __future__ import annotations

from artclass_core import ArtclassError, RunResult
from artclass_core.articulation import Articulation, PartJoint
from artclass_core.interfaces import JointEstimator

from .base import _linked_by_motion, _one_body_pairs_on, _still_track, _track_motions, chain_interleaved
from .images import _relabelled
from .observations import _observations
from .params import PartsParams
from .tracks import _seen_tracks, _track_sizes, _tracks
from .tree import _kinematic_tree, _numbered, _part, _part_points


def find_articulation(
    result: RunResult, *, estimator: JointEstimator, params: PartsParams | None = None, images: bool = True
) -> Articulation:
    """Parts and joints over the video of a finished run (see the package docstring).

    Parameters
    ----------
    result : RunResult
        A run of a rule that decides from motions, with ``keep_clouds=True`` (the pairs' labelled
        points are needed). A sequence not labelled articulated gets the base only and no joint.
    estimator : JointEstimator
        The joint estimator (``registry.create("joint_estimator", "bic")`` for the built-in one).
    params : PartsParams, or None for the defaults
    images : False leaves out each frame's part image (step 6): parts and joints only

    Returns
    -------
    Articulation
    """
    params = PartsParams() if params is None else params
    if images and not any(f.cloud is not None for f in result.frames):
        raise ArtclassError("part images need the frames' clouds: run with keep_clouds=True")
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
    if images and len(tree) > 1 and params.n_views:
        views = _relabelled(result, observations, views, tree, base_poses, params=params)
    joints = [
        PartJoint(number[link.parent], number[t], link.estimate, link.n_pairs)
        for t, link in tree.items()
        if link.estimate is not None
    ]
    children = {t: [c for c, child in tree.items() if child.parent == t] for t in tree}
    shared = {
        t: set.intersection(*(set(points.get(c, {})) for c in cs)) if cs else set()
        for t, cs in children.items()
    }
    parts = [
        _part(
            number[t], number.get(link.parent, -1), points.get(t, {}), link, size.get(t, 0), shown=shared[t]
        )
        for t, link in tree.items()
    ]
    return Articulation(parts, joints, base_poses, _numbered(views, number))
