"""Base classes for plugin implementations, with the exact signatures the pipeline calls.

Subclassing is optional (the registry checks for the method, not the base class), but it gives a
plugin the constructor, the defaults and the documentation for free.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from .articulation import JOINT_TYPES, Articulation, JointEstimate  # noqa: F401  (JOINT_TYPES: re-exported)
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
    RunResult,
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

    def covered(self, frame: Frame, *, sequence: Sequence) -> np.ndarray | None:
        """Boolean mask (H, W) of the pixels left out of the object's mask because something the
        segmenter found there (a hand and its outline) may cover the object: an object point seen
        there later is hidden, not gone. ``None``: no such pixels."""
        return None


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


class PartFinder(Plugin):
    """Parts and joints over a whole video, from a finished run.

    The stage runs after the pipeline: it is given the :class:`~artclass_core.types.RunResult` of a
    run made with ``keep_clouds=True`` (every frame's cloud and every pair's motions, point labels and
    evidence) and returns the object's parts, the joints between them and each frame's part image.
    """

    #: What the run's decision rule must decide from for this stage to work on it: ``"motions"`` (each
    #: pair's rigid motions and the points each explains), ``"cells"``, or ``"any"``.
    needs: ClassVar[str] = "motions"

    def works_on(self, rule: DecisionRule) -> bool:
        """Whether this stage can find parts in the runs of ``rule``."""
        return self.needs in ("any", rule.needs)

    def find(self, result: RunResult, *, estimator: JointEstimator, images: bool = True) -> Articulation:
        """The parts and joints of ``result``; each joint is fitted by ``estimator``.

        A sequence not labelled articulated gets its base only and no joint. With ``images`` false the
        frames' part images may be left out: the pipeline asks for the joints only, to label a run
        that kept each pair's labelled points (:attr:`~artclass_core.types.PairResult.points`) but
        not its clouds. Raises :class:`~artclass_core.errors.ArtclassError` when the run kept too
        little.
        """
        raise NotImplementedError


KINDS["part_finder"] = ("register_part_finders", "find")
