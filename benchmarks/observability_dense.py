"""Which articulated pairs could the default ``dense`` rule call AM at all, if its registrar found the
true motions?

    .venv/bin/python benchmarks/observability_dense.py [ROOT] [--segmenter NAME] [--only SUBSTRING]

ROOT is a benchmark folder with per-part truth (``artclass sample ... --preset benchmark-vga``,
default ``benchmark_data/vga3``). Every pair (i, i + k) whose observable truth is AM is registered as
the default pipeline does and decided by the rule; then the rule decides the same pair from the
true motions alone (the object's base and each moving part, from ``truth.json``), scored on depth in
both directions with the pair's own measured noise, without optical flow.

A pair the rule calls AM from the true motions is *observable by depth* at the rule's settings: when
the default pipeline misses it, better motion hypotheses would find it. A pair the rule does not call
AM even then is beyond what its depth test can see (too few points of a part show the motion in
depth: a part sliding in its own plane, a part seen on a few pixels), whatever the hypotheses; only
other evidence (texture, more frames) or other thresholds can help. Prints, per sequence and in
total, the AM pairs, those the rule calls AM, those the true motions make AM, and those it misses
although the true motions are AM. Prints numbers; never fails.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from collections import Counter

import numpy as np

from artclass_core import Config, MotionEvidence, Pipeline, StageCache, find_sequences, load_registry
from artclass_plugins.dense.projective import Target, look_all


def true_evidence(pipeline: Pipeline, ev: MotionEvidence, a, b, motions: np.ndarray) -> MotionEvidence:
    """``ev`` (the registered pair of clouds ``a`` and ``b``) with ``motions`` as its only hypotheses,
    judged on depth both ways as the registrar judges its own, and no optical flow."""
    reach = pipeline.registrar.reach
    target, source = Target.of(b), Target.of(a)
    fwd = look_all(motions, a.points, target, reach_m=reach(a, target.intrinsics.fx), off_object_px=2.0)
    back = look_all(
        np.linalg.inv(motions), b.points, source, reach_m=reach(b, source.intrinsics.fx), off_object_px=2.0
    )
    status, residual = np.hstack([fwd[0], back[0]]), np.hstack([fwd[1], back[1]])
    return dataclasses.replace(
        ev,
        motions=motions,
        names=["true base"] + [f"true part {m}" for m in range(1, len(motions))],
        residual_m=residual,
        status=status,
        flow_px=np.full(status.shape, np.nan, np.float32),
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("root", nargs="?", default="benchmark_data/vga3")
    parser.add_argument("--segmenter", default="mask")
    parser.add_argument("--only", default="", help="only the sequences whose name contains this")
    args = parser.parse_args()
    registry = load_registry()
    pipeline = Pipeline(registry, dataclasses.replace(Config(), segmenter=args.segmenter))
    k = pipeline.params.k
    total = Counter()
    print("| sequence | AM pairs | rule AM | AM from the true motions | missed although observable |")
    print("|---|---|---|---|---|")
    for seq in find_sequences(registry, args.root)[0]:
        if seq.label != "articulated" or args.only not in seq.name:
            continue
        poses = json.loads((seq.path / "truth.json").read_text())["part_poses"]
        cache = StageCache()  # a frame is the first of one pair and the last of another: prepared once
        row = Counter()
        for i in range(len(seq) - k):
            if seq.pair_truth(i, i + k) != "AM":
                continue
            a, b = (pipeline.frame(seq, m, cache=cache).cloud for m in (i, i + k))
            if a is None or b is None:
                continue
            ev, _ = pipeline.register(a, b)
            motions = np.stack([np.asarray(P[i + k]) @ np.linalg.inv(P[i]) for P in zip(*poses)])
            rule = pipeline.rule.decide(ev).decision == "AM"
            observable = pipeline.rule.decide(true_evidence(pipeline, ev, a, b, motions)).decision == "AM"
            row.update(pairs=1, rule=rule, observable=observable, missed=observable and not rule)
        total.update(row)
        print(f"| {seq.name} | {row['pairs']} | {row['rule']} | {row['observable']} | {row['missed']} |")
    print(
        f"| total | {total['pairs']} | {total['rule']} | {total['observable']} | {total['missed']} |",
    )


if __name__ == "__main__":
    main()
