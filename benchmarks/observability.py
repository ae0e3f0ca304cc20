"""Which articulated pairs could the ``robust`` rule call AM at all, if it were handed the true motions?

    .venv/bin/python benchmarks/observability.py [ROOT] [--param NAME=VALUE ...] [--segmenter NAME]

ROOT is a benchmark folder written by ``artclass sample ROOT --preset benchmark-vga`` (default
``benchmark_data/vga``). Every pair whose truth is AM is run through the default pipeline; then the
rule's own evidence of that pair (its scoring points, the noise-scaled tau, the optical flow) scores
the two true motions from ``truth.json``: the object's and the moving part's. The rule's own tests
then decide whether the data shows two motions: the first is the one that explains more points,
and the other needs ``min_part_cells`` cells and the part share (``min_part_share``, or
``min_still_part_share`` when the first motion is within noise) that the first does not explain.

A pair that fails this is *not observable* at the rule's resolution: no better motion hypothesis can
make it AM, only other evidence (more points per part, a finer grid, lower noise) or other
thresholds. Prints, per sequence and in total, the AM pairs, those the rule called AM, those
observable, and those observable but missed (where better hypotheses would help); and, over every sequence, the pair
accuracy as ``artclass evaluate`` counts it and what it would be if the rule also found every
observable AM pair it misses. Prints numbers; never fails.
"""

from __future__ import annotations

import argparse

import numpy as np

from artclass_core import Config, Pipeline, find_sequences, load_registry
from artclass_plugins.rules import robust as R


def observable(ev, truth: dict, i: int, j: int, tau: float, p) -> bool:
    """Whether the rule's cover, given only the true object and part motions, finds two motions."""
    motions = [
        np.asarray(truth[key][j]) @ np.linalg.inv(np.asarray(truth[key][i]))
        for key in ("object_poses", "moving_part_poses")
    ]
    score = R._per_cell(ev.residuals(motions) <= tau, ev.owner, ev.counts)
    best = np.maximum(score.max(0), R._per_cell(ev.geo <= tau, ev.owner, ev.counts).max(0))
    informative = best >= p.min_cell_score
    explains = R._explains(score, best, ev.counts, p.explain_margin) & informative
    weight = ev.counts * informative
    first = int(np.argmax(explains @ weight))
    share = p.min_part_share if R._displacement(ev.pts, motions[first]) > tau else p.min_still_part_share
    part = explains[1 - first] & ~explains[first]
    return bool(part.sum() >= p.min_part_cells and weight[part].sum() >= share * weight.sum())


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("root", nargs="?", default="benchmark_data/vga")
    ap.add_argument("--param", action="append", default=[], help="NAME=VALUE, as for artclass classify")
    ap.add_argument("--segmenter", default="mask")
    args = ap.parse_args(argv)
    registry = load_registry()
    overrides = dict(a.split("=", 1) for a in args.param)
    pipe = Pipeline(registry, Config(segmenter=args.segmenter).with_overrides(registry, overrides))
    if pipe.config.rule != "robust":
        raise SystemExit("observability scores the robust rule's evidence")
    seqs, _ = find_sequences(registry, args.root)
    totals, n_truth, n_right = np.zeros(4, int), 0, 0
    print(f"{'sequence':36s} {'AM pairs':>8s} {'called AM':>9s} {'observable':>10s} {'obs. missed':>11s}")
    for seq in seqs:
        truth = getattr(seq, "truth", None) or {}
        scored = seq.label == "articulated" and "moving_part_poses" in truth
        run = pipe.run(seq, keep_clouds=scored, workers=2)
        counts = np.zeros(4, int)
        for pair in run.pairs:
            if pair.truth is not None and pair.decision != "skipped":  # as artclass evaluate counts
                n_truth += 1
                n_right += pair.decision == pair.truth
            if not scored or pair.truth != "AM" or "tau_m" not in pair.info:
                continue
            ev = next(v for k, v in pair.scratch.items() if k[0] == "robust")
            seen = observable(ev, truth, pair.i, pair.j, pair.info["tau_m"], pipe.rule.params)
            hit = pair.decision == "AM"
            counts += (1, hit, seen, seen and not hit)
        totals += counts
        if scored:
            print(f"{seq.name:36s} {counts[0]:8d} {counts[1]:9d} {counts[2]:10d} {counts[3]:11d}")
    print(f"{'total':36s} {totals[0]:8d} {totals[1]:9d} {totals[2]:10d} {totals[3]:11d}")
    print(
        f"pairs right (decided pairs with truth, every sequence): {n_right}/{n_truth} = "
        f"{100 * n_right / max(n_truth, 1):.1f}%; finding every observable AM pair as well: "
        f"{100 * (n_right + totals[3]) / max(n_truth, 1):.1f}%"
    )


if __name__ == "__main__":
    main()
