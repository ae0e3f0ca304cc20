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
from .types import CellMotion, Cloud, Decision, Frame, Intrinsics, Motion, MotionEvidence, Registration, Sequence


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

    def register(self, source: np.ndarray, target: np.ndarray, *, source_normals: np.ndarray | None,
                 target_normals: np.ndarray | None, cell_size_m: float) -> Registration:
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
    keys: list[str] = field(default_factory=list)   # readable name of each cluster, by cluster index
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

    def decide(self, cells: list[CellMotion], *, source: Cloud, target: Cloud,
               between: tuple[Cloud, ...] = ()) -> RuleDecision:
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
