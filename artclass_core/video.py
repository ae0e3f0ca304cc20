"""The video's label from the whole video, not from its pairs one by one.

A pair can show two motions where there is one body: real depth error, a calibration a few percent off,
a motion too large to register. Such pairs are isolated, and the "parts" they find move at random. So a
video is articulated only when a part is tracked across pairs and a joint (prismatic, revolute or screw)
over the whole trajectory explains its motion relative to the base better than no motion does: the
selection of Sturm, Stachniss & Burgard (JAIR 2011) between the rigid model and the joint models, made
by the run's part finder (its kinematic tree) and joint estimator.
"""

from __future__ import annotations

from .config import JOINT_ESTIMATOR, PART_FINDER
from .errors import ArtclassError
from .plugins import Registry
from .types import RunResult

#: Joint models that make an object articulated: one degree of freedom along a trajectory.
JOINT_MODELS = ("prismatic", "revolute", "screw")
#: A joint is told from a trajectory: two pairs' relative motions fit some joint almost always (a line
#: or an axis through two poses); each further pair tests it.
MIN_PAIRS = 3


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
    j = max(joints, key=lambda j: j.n_pairs)
    return True, f"{shown}; part {j.child} moves about a {j.estimate.type} joint over {j.n_pairs} pairs"
