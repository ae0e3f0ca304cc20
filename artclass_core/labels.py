"""From pair decisions to a sequence label: the longer pair of a slow motion, the shorter pair of a
motion too large to register, the moving max-count filter and the label rule."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable
from typing import Any

from .types import DECISIONS, FrameResult, PairResult, RunResult

SEVERITY = {"NM": 0, "RM": 1, "AM": 2}


def max_count_filter(decisions: list[str], *, w: int) -> list[str]:
    """Moving max-count (mode) filter with a centred window of ``w`` decisions.

    A tie goes to the least severe of the tied (NM < RM < AM), so an isolated AM cannot win a tie,
    not even in the truncated windows at the ends of the sequence.
    """
    out = []
    before = (w - 1) // 2
    for t in range(len(decisions)):
        window = decisions[max(0, t - before) : t - before + w]
        counts = Counter(window)
        top = max(counts.values())
        tied = [d for d in counts if counts[d] == top]
        out.append(min(tied, key=SEVERITY.__getitem__))
    return out


def with_longer(pair: PairResult, longer: PairResult) -> PairResult:
    """``longer``, the pair (i, i + slow_factor k), in place of ``pair`` (i, i + k), which showed no
    motion, when it shows one; else ``pair``. Each keeps the other as :attr:`PairResult.other`."""
    if longer.decision in ("AM", "RM"):
        longer.other = pair
        longer.reason = (
            f"no motion over {pair.j - pair.i} frames; over {longer.j - longer.i}: {longer.reason}"
        )
        return longer
    if longer.decision != "skipped":
        pair.other = longer
    return pair


def with_shorter(pair: PairResult, shorter: PairResult) -> PairResult:
    """``shorter``, a pair (i, i + k/2), in place of ``pair`` (i, i + k), which no model explained (a
    motion beyond what registration reaches), when it is decided; else ``pair``. Each keeps the other
    as :attr:`PairResult.other`."""
    if shorter.decision in DECISIONS:
        shorter.other = pair
        shorter.reason = (
            f"no model explains {pair.j - pair.i} frames; over {shorter.j - shorter.i}: {shorter.reason}"
        )
        return shorter
    pair.other = shorter
    return pair


def chosen_pair(over: Callable[[int], PairResult | None], *, k: int, far: int) -> PairResult:
    """The pair decided for a frame i: ``over(k)``, the pair (i, i + k); when no model explains it,
    :func:`with_shorter` the pair (i, i + k/2); when it shows no motion, :func:`with_longer` the pair
    (i, i + far). ``over(n)`` gives the pair (i, i + n), or None where the frames do not reach."""
    pair = over(k)
    if pair.decision == "undecided" and k > 1:
        return with_shorter(pair, over(k // 2))
    longer = over(far) if pair.decision == "NM" and far != k else None
    return pair if longer is None else with_longer(pair, longer)


def sequence_label(filtered: Iterable[str]) -> str:
    """``articulated`` if any filtered decision is AM, else ``rigid`` if any is RM, else ``static``."""
    seen = set(filtered)
    return "articulated" if "AM" in seen else "rigid" if "RM" in seen else "static"


def fractions(decided: list[str]) -> dict[str, float]:
    """Share of the decided pairs in each class (the paper's per-sequence "probabilities")."""
    n = len(decided)
    return {d: (decided.count(d) / n if n else 0.0) for d in DECISIONS}


def labelled_result(
    sequence: dict[str, Any],
    frames: list[FrameResult],
    pairs: list[PairResult],
    *,
    w: int,
    params: dict[str, dict],
    plugins: dict[str, str],
    timing: dict[str, float],
    confirm: Callable[[RunResult], tuple[bool, str]] | None = None,
) -> RunResult:
    """The :class:`RunResult` of a sequence's pair decisions: filtered with window ``w``, the label and
    the class fractions, recorded with the ``params`` and ``plugins`` that produced them, the stage
    ``timing`` (s) and the artclass version.

    Undecided and skipped pairs are left out of the filter. With ``confirm``, a sequence whose filtered
    decisions hold AM is articulated only if ``confirm(result)`` says so (the parts over the whole
    video: :func:`artclass_core.video.joints_over_video`); otherwise its AM pairs count as RM (they
    show that something moved)."""
    decided = [p.decision for p in pairs if p.decision in DECISIONS]
    filtered = max_count_filter(decided, w=w)
    result = RunResult(
        sequence=sequence,
        label=sequence_label(filtered),
        fractions=fractions(decided),
        pairs=pairs,
        filtered=filtered,
        frames=frames,
        params=params,
        plugins=plugins,
        timing_s={k: round(v, 4) for k, v in timing.items()},
        version=_version(),
        reason=_reason(filtered, len(pairs)),
    )
    if result.label == "articulated" and confirm is not None:
        confirmed, result.reason = confirm(result)
        if not confirmed:
            result.label = sequence_label("RM" if d == "AM" else d for d in filtered)
    return result


def _reason(filtered: list[str], n_pairs: int) -> str:
    """Why the filtered decisions give their label, in a few words."""
    counts = Counter(filtered)
    top = "AM" if counts["AM"] else "RM" if counts["RM"] else "NM"
    what = {"AM": "show parts moving apart", "RM": "show one rigid motion", "NM": "show no motion"}[top]
    return f"{counts[top]} of {n_pairs} pairs {what} after the max-count filter"


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("artclass")
    except PackageNotFoundError:
        return "unknown"
