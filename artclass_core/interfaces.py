"""Base classes for plugin implementations, with the exact signatures the pipeline calls.

Subclassing is optional (the registry checks for the method, not the base class), but it gives a
plugin the constructor, the defaults and the documentation for free.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from .params import Params
from .types import (
    CellMotion,
    Cloud,
    Decision,
    Frame,
    Intrinsics,
    Motion,
    MotionEvidence,
    Registration,
    Sequence,
)


class Plugin:
    """Common part: a unique lowercase ``name``, a one-line ``description`` and a ``Params`` dataclass."""

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    Params: ClassVar[type[Params]] = Params

    def __init__(self, params: Params | None = None):
        self.params = params if params is not None else self.Params()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.params!r})"


class Reader(Plugin):
    def sequences(self, path: Path) -> list[Sequence]:
        """The sequences stored at ``path``; ``[]`` if the path is not in this reader's layout."""
        raise NotImplementedError


class Segmenter(Plugin):
    def segment(self, frame: Frame, *, sequence: Sequence) -> np.ndarray | None:
        """Boolean mask (H, W) of the handled object in ``frame``, or ``None`` when there is none."""
        raise NotImplementedError


class Preprocessor(Plugin):
    def process(self, frame: Frame, mask: np.ndarray, *, intrinsics: Intrinsics) -> Cloud:
        """The object's filtered point cloud (metres, camera frame) from the masked depth."""
        raise NotImplementedError


class Registrar(Plugin):
    #: What registration gives the rule: ``"cells"`` (a motion per grid cell, from :meth:`register`) or
    #: ``"motions"`` (a :class:`MotionEvidence` for the whole pair, from :meth:`PairRegistrar.register_pair`).
    gives: ClassVar[str] = "cells"

    def register(
        self,
        source: np.ndarray,
        target: np.ndarray,
        *,
        source_normals: np.ndarray | None,
        target_normals: np.ndarray | None,
        cell_size_m: float,
    ) -> Registration:
        """Register the source points of one cell onto the target points, starting from identity."""
        raise NotImplementedError


class PairRegistrar(Registrar):
    """A registrar that explains the whole pair at once: rigid-motion hypotheses and, for every source
    point, how well each of them explains it (no grid of cells)."""

    gives = "motions"

    def register_pair(self, source: Cloud, target: Cloud) -> MotionEvidence:
        """The motion hypotheses of the pair and the evidence for and against each."""
        raise NotImplementedError

    def register(self, source, target, *, source_normals, target_normals, cell_size_m) -> Registration:
        raise NotImplementedError(f"registrar {self.name!r} registers whole pairs (register_pair), not cells")


@dataclass
class RuleDecision:
    """What a decision rule says about one pair. ``clusters`` has one entry per cell (None = none);
    a rule that decides from motions gives ``motions`` and each evidence point's ``labels`` instead."""

    decision: Decision
    clusters: list[int | None]
    keys: list[str] = field(default_factory=list)  # readable name of each cluster, by cluster index
    reason: str = ""
    info: dict[str, Any] = field(default_factory=dict)
    motions: list[Motion] = field(default_factory=list)
    labels: np.ndarray | None = None


class DecisionRule(Plugin):
    #: What the rule decides from: ``"cells"`` (``decide(cells, ...)``) or ``"motions"``
    #: (``decide(evidence, ...)`` with the :class:`MotionEvidence` of a :class:`PairRegistrar`).
    needs: ClassVar[str] = "cells"

    #: True for a rule that wants the clouds of the frames between a pair's two as well (to follow the
    #: images from frame to frame): the pipeline then passes them as ``between``, in frame order.
    uses_frames_between: bool = False

    #: True for a rule that keeps work its parameters do not change (motion hypotheses, residuals ...)
    #: between calls: the pipeline then passes ``scratch``, a dict that belongs to the pair and lives as
    #: long as its registration is kept (in a :class:`~artclass_core.cache.StageCache`, or in a
    #: result's :attr:`PairResult.scratch`), so re-deciding under other thresholds finds it again. Key
    #: the entries on what they depend on besides the pair, e.g. ``("my_rule", params.max_points)``.
    uses_scratch: bool = False

    def decide(
        self,
        cells: list[CellMotion],
        *,
        source: Cloud,
        target: Cloud,
        between: tuple[Cloud, ...] = (),
        scratch: dict | None = None,
    ) -> RuleDecision:
        """Decide AM / RM / NM (or skipped) for a pair from its registered cells."""
        raise NotImplementedError


KINDS: dict[str, tuple[str, str]] = {
    # kind: (hook name, method every class of that kind must have)
    "reader": ("register_readers", "sequences"),
    "segmenter": ("register_segmenters", "segment"),
    "preprocessor": ("register_preprocessors", "process"),
    "registrar": ("register_registrars", "register"),
    "rule": ("register_rules", "decide"),
}


#: Joint types a :class:`JointEstimate` can carry, simplest first.
JOINT_TYPES = ("fixed", "prismatic", "revolute", "screw", "free")


@dataclass
class JointEstimate:
    """The joint between a moving part and its parent, as a joint estimator finds it.

    Everything is in the parent's frame, in metres and radians. ``states[i]`` is the joint state in
    frame ``i`` relative to the first frame whose pose the model explains: an angle in radians for ``revolute``
    and ``screw``, a travel in metres for ``prismatic``; NaN where the pose is unknown or an outlier.

    Attributes
    ----------
    type : one of :data:`JOINT_TYPES`
    axis_direction : ndarray, shape (3,), unit vector, or None (``fixed``, ``free``)
    axis_point_m : ndarray, shape (3,), metres, or None: a point on a revolute or screw axis (the one
        nearest the part), or the part's point a prismatic axis runs through
    states : ndarray, shape (N,), radians or metres
    inliers : ndarray, shape (N,), bool: the poses the chosen model explains
    axis_direction_std_rad : float, one standard deviation of the axis direction (NaN if unknown)
    axis_point_std_m : float, one standard deviation of the axis position across the axis
    states_std : ndarray, shape (N,), one standard deviation of each state
    scores : dict, the BIC of every model tried (lower is better); empty if the estimator has none
    info : dict, JSON-ready extra evidence (noise levels found, outlier count, screw pitch ...)
    """

    type: str
    axis_direction: np.ndarray | None
    axis_point_m: np.ndarray | None
    states: np.ndarray
    inliers: np.ndarray
    axis_direction_std_rad: float = float("nan")
    axis_point_std_m: float = float("nan")
    states_std: np.ndarray | None = None
    scores: dict[str, float] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def state_unit(self) -> str:
        """``"m"`` for a prismatic joint, ``"rad"`` otherwise."""
        return "m" if self.type == "prismatic" else "rad"

    def summary(self, *, up: np.ndarray) -> str:
        """One readable line, e.g. ``"revolute joint, axis 2 deg from vertical, 0-74 deg over the video"``.

        Parameters
        ----------
        up : ndarray, shape (3,): the vertical in the parent's frame (the camera's up, or -gravity)
        """
        if self.type == "fixed":
            return "fixed joint: the part does not move relative to its parent"
        if self.type == "free" or self.axis_direction is None:
            return (
                f"free motion: no single joint explains the part's motion ({int(self.inliers.sum())} of "
                f"{len(self.inliers)} poses fit the best one)"
            )
        up = np.asarray(up, float) / np.linalg.norm(up)
        tilt = np.degrees(np.arccos(np.clip(abs(float(self.axis_direction @ up)), 0.0, 1.0)))
        word = "direction" if self.type == "prismatic" else "axis"
        scale, unit = (1000.0, "mm") if self.type == "prismatic" else (np.degrees(1.0), "deg")
        known = self.states[np.isfinite(self.states)] * scale
        low, high = (float(known.min()), float(known.max())) if len(known) else (0.0, 0.0)
        span = f"{max(low, 0.0) + 0.0:.0f}-{high:.0f}" if round(low) >= 0 else f"{low:.0f} to {high:.0f}"
        return f"{self.type} joint, {word} {tilt:.0f} deg from vertical, {span} {unit} over the video"


class JointEstimator(Plugin):
    def estimate(
        self, poses: np.ndarray, *, n_independent: int | None = None, reach_m: float | None = None
    ) -> JointEstimate:
        """The joint of a part from its poses in its parent's frame.

        ``poses`` has shape (N, 4, 4): ``poses[i]`` maps the part's frame (its origin at the part, e.g.
        its centroid) to the parent's frame in frame ``i`` of the video, metres; NaN where unknown.
        ``n_independent`` says how many of the known poses carry independent errors (None: all of
        them); an estimator that weighs evidence (a chi-square test, a BIC) should count that many.
        ``reach_m`` is how far the object's points (the part's and its parent's) reach from the
        part's origin: a joint lies where the two meet, so its axis passes near them (None: unknown).
        An ``estimate`` without one of these arguments still works: it is then not passed.
        """
        raise NotImplementedError


KINDS["joint_estimator"] = ("register_joint_estimators", "estimate")
