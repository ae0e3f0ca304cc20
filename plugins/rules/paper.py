"""The paper's rule (Algorithm 2), faithful to the text: quantise each cell's motion and hash it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from artclass_core import CellMotion, Cloud, DecisionRule, Params, RuleDecision, param
from artclass_core.geometry import quaternion_wxyz

# floor(q / q_bar) computed in floating point puts exact multiples (1.0 / 0.1 = 9.999...) one bin low;
# a nudge far below any real signal keeps exact values in their own bin.
_NUDGE = 1e-9


@dataclass(frozen=True)
class PaperRuleParams(Params):
    q_bar: float = param(
        0.1,
        symbol="q_bar",
        unit="1",
        bounds=(1e-4, 2.0),
        help="Quantisation step of the quaternion components.",
    )
    t_bar: float = param(
        0.1,
        symbol="t_bar",
        unit="m",
        bounds=(1e-5, 10.0),
        help="Quantisation step of the translation components.",
    )
    rounding: str = param(
        "floor",
        choices=("floor", "round"),
        help="Quantiser: floor, as written in Algorithm 2, or round to the nearest step.",
    )


def quantise(values: np.ndarray, step: float, rounding: str) -> tuple[int, ...]:
    scaled = np.asarray(values) / step
    bins = np.floor(scaled + _NUDGE) if rounding == "floor" else np.round(scaled)
    return tuple(int(b) for b in bins)


class PaperRule(DecisionRule):
    """Algorithm 2: hash the quantised [q | t] of every matched cell; 2+ keys = AM, 1 key = RM, the
    zero key alone = NM.

    Choices the paper leaves open, made here:

    - The transform of a cell is ICP's ``T_target_from_source`` in the camera frame, exactly as
      Algorithm 2 takes it (about the camera origin, not the cell's centroid).
    - Quaternions are (w, x, y, z) with the sign fixed so that w >= 0 (q and -q are one rotation).
    - Quantisation is ``floor(q / q_bar) * q_bar`` as written (``rounding="round"`` is offered).
    - "The zero key" is read as the key of the identity motion: q = (1, 0, 0, 0), t = 0, since a unit
      quaternion can never be all zeros.
    - Skipped cells (too few points, no correspondence, low fitness) do not get a key; the alpha
      check on how many cells matched is done by the pipeline before the rule is called.
    """

    name = "paper"
    description = "Algorithm 2 of the paper: quantise each cell's (q, t) and count distinct hash keys"
    Params = PaperRuleParams

    def key(self, T: np.ndarray) -> tuple[int, ...]:
        p = self.params
        return quantise(quaternion_wxyz(T[:3, :3]), p.q_bar, p.rounding) + quantise(
            T[:3, 3], p.t_bar, p.rounding
        )

    def decide(self, cells: list[CellMotion], *, source: Cloud, target: Cloud) -> RuleDecision:
        table: dict[tuple[int, ...], int] = {}
        clusters: list[int | None] = []
        for cell in cells:
            if not cell.matched:
                clusters.append(None)
                continue
            clusters.append(table.setdefault(self.key(cell.registration.T_target_from_source), len(table)))
        zero = self.key(np.eye(4))
        keys = [self._readable(k) for k in table]
        if len(table) >= 2:
            decision = "AM"
        elif len(table) == 1:
            decision = "NM" if zero in table else "RM"
        else:
            return RuleDecision("skipped", clusters, keys, reason="no matched cell")
        return RuleDecision(
            decision, clusters, keys, reason=f"{len(table)} distinct key(s)", info=dict(n_keys=len(table))
        )

    def _readable(self, key: tuple[int, ...]) -> str:
        p = self.params
        q = ",".join(f"{b * p.q_bar:+.2f}" for b in key[:4])
        t = ",".join(f"{b * p.t_bar:+.2f}" for b in key[4:])
        return f"q[{q}] t[{t}]"
