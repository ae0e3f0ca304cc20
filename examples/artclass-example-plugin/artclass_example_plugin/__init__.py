"""Example third-party artclass plugin: the ``example_centroid`` decision rule.

The rule looks only at where each matched cell's centre goes under the cell's registered motion
(``T_target_from_source`` applied to the cell centre):

- at least ``min_part_cells`` cells move differently (by more than ``max_spread_m``) from the median
  displacement of all matched cells: articulated (AM);
- else the median displacement is below ``min_motion_m``: no motion (NM);
- else: one rigid motion (RM).

Unlike the paper's rule it measures motion in metres at the cell, not as (q, t) about the camera
origin, so a small rotation error does not turn into a large translation difference. It is meant as
a readable example of the plugin interface, not as a better classifier.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from artclass_core import CellMotion, Cloud, DecisionRule, Params, RuleDecision, hookimpl, param

__all__ = ["CentroidRule", "CentroidRuleParams", "register_rules"]


@dataclass(frozen=True)
class CentroidRuleParams(Params):
    min_motion_m: float = param(
        0.004, unit="m", bounds=(0.0, 1.0), help="A cell centre displaced by less than this has not moved."
    )
    max_spread_m: float = param(
        0.01,
        unit="m",
        bounds=(1e-4, 1.0),
        help="Cells whose displacement differs from the median by more than this move "
        "differently from the rest of the object.",
    )
    min_part_cells: int = param(
        2,
        unit="cells",
        bounds=(1, 1000),
        help="A differently moving part must hold at least this many matched cells.",
    )


class CentroidRule(DecisionRule):
    """Decide AM / RM / NM from the displacement of every matched cell's centre, in metres."""

    name = "example_centroid"
    description = "example third-party rule: compares the displacements of the cell centres, in metres"
    Params = CentroidRuleParams

    def decide(self, cells: list[CellMotion], *, source: Cloud, target: Cloud) -> RuleDecision:
        p = self.params
        matched = [n for n, c in enumerate(cells) if c.matched]
        clusters: list[int | None] = [None] * len(cells)
        if not matched:
            return RuleDecision("skipped", clusters, reason="no matched cell")
        moves = np.array([_displacement(cells[n]) for n in matched])  # (M, 3) metres
        median = np.median(moves, axis=0)
        off = np.linalg.norm(moves - median, axis=1)
        outliers = off > p.max_spread_m
        info = dict(
            median_displacement_m=float(np.linalg.norm(median)),
            max_spread_m=float(off.max()),
            n_outlier_cells=int(outliers.sum()),
        )
        for n, out in zip(matched, outliers):
            clusters[n] = int(out)
        keys = ["with the median", "differently"]
        if outliers.sum() >= p.min_part_cells:
            return RuleDecision(
                "AM", clusters, keys, reason=f"{int(outliers.sum())} cells move differently", info=info
            )
        if np.linalg.norm(median) < p.min_motion_m:
            return RuleDecision("NM", clusters, keys, reason="the cell centres did not move", info=info)
        return RuleDecision("RM", clusters, keys, reason="the cell centres move together", info=info)


def _displacement(cell: CellMotion) -> np.ndarray:
    """Where the cell centre goes under the cell's motion, minus where it was (metres)."""
    T = cell.registration.T_target_from_source
    return T[:3, :3] @ cell.centre_m + T[:3, 3] - cell.centre_m


@hookimpl
def register_rules(register):
    register(CentroidRule)
