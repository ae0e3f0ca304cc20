"""Hand and object masks of the mask-free segmenters against a labelled benchmark folder.

Not a test: it prints numbers. Run from the repository root::

    .venv/bin/python benchmarks/hand_iou.py benchmark_data/vga2
    .venv/bin/python benchmarks/hand_iou.py benchmark_data/vga2 --segmenters depth_threshold --every 3
    .venv/bin/python benchmarks/hand_iou.py benchmark_data/vga2 --param exclude_hands=false

For each sequence folder with ``hand/*.png`` (non-zero = the hand or gripper with its arm) and
``mask/*.png`` (the object) beside its frames, and each segmenter:

* **hand IoU**: the segmenter's hand mask (before its margin) against ``hand/``, pooled over the
  frames (intersection over union of all pixels of all frames with a hand in the truth), the mean
  per-frame IoU, and that mean over the frames where the true hand reaches the image border (its
  arm enters the picture, as a real arm does); by holder (``hand``, ``gripper``, from
  ``meta.json``). Also how many frames without a hand in the truth had a hand found (false alarms).
* **object IoU**: the chosen (manipulated) mask against ``mask/``, mean per frame, by holder.
* **arm in the object's mask**: the share of the frames with a hand in the truth where more than
  ``--arm-share`` (1 %) of the chosen mask is the true hand or arm: a few mixed pixels along the
  contact are not counted, a wrist or a sleeve is.
* **segmenting time**: CPU milliseconds a frame of ``segment`` (the hand mask comes with it).

``--every N`` scores every N-th frame only (the chosen masks still see every frame before it, as
the choice of one frame depends on the previous ones). ``--param NAME=VALUE`` sets a segmenter
parameter where the segmenter has it (as ``artclass evaluate --param``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
from bench_segmenters import make, parse_overrides

from artclass_core import ArtclassError, find_sequences, load_registry
from artclass_core.evaluate import HAND_COUNTS, score_hands
from artclass_core.io import read_mask
from artclass_plugins.segmenters.selection import mask_iou


def empty_scores() -> dict:
    return dict(
        hand_ious=[], border_ious=[], object_ious=[], cpu_s=0.0, frames=0, **dict.fromkeys(HAND_COUNTS, 0)
    )


def holder_of(seq) -> str:
    meta = json.loads((Path(seq.path) / "meta.json").read_text())
    return str(meta.get("hand") or "none")


def score_sequence(seg, seq, *, every: int, arm_share: float) -> dict:
    """Pooled hand counts (:func:`~artclass_core.evaluate.score_hands`), per-frame hand IoUs and object
    IoUs of a sequence, and its segmenting time."""
    out = empty_scores()
    hand_dir = Path(seq.path) / "hand"
    for i in range(0, len(seq), every):
        frame = seq[i]
        c0 = time.process_time()
        mask = seg.segment(frame, sequence=seq)
        out["cpu_s"] += time.process_time() - c0
        out["frames"] += 1
        if frame.mask is not None:
            out["object_ious"].append(0.0 if mask is None else mask_iou(mask, frame.mask))
        truth_file = hand_dir / f"{frame.name}.png"
        truth = read_mask(truth_file) if truth_file.is_file() else None
        if truth is not None and truth.any():
            found = seg.hand_mask(frame, sequence=seq)
            found = np.zeros_like(truth) if found is None else found
            out["hand_ious"].append(mask_iou(found, truth))
            if truth[0].any() or truth[-1].any() or truth[:, 0].any() or truth[:, -1].any():
                out["border_ious"].append(mask_iou(found, truth))
    out.update(score_hands(seg, seq, arm_share=arm_share, every=every) or {})
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path, help="a folder of labelled sequences with hand/ and mask/ truth")
    ap.add_argument("--segmenters", default="depth_threshold,u2net")
    ap.add_argument("--every", type=int, default=1, help="score every N-th frame")
    ap.add_argument(
        "--arm-share", type=float, default=0.01, help="share of the object's mask an arm must take"
    )
    ap.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="segmenter parameter (applied where the segmenter has it)",
    )
    args = ap.parse_args(argv)
    overrides = parse_overrides(args.param)
    registry = load_registry()
    try:
        sequences, _ = find_sequences(registry, args.folder)
    except ArtclassError as exc:
        print(f"hand_iou: {exc}", file=sys.stderr)
        return 2
    print(f"{len(sequences)} sequences in {args.folder}, every {args.every}. frame scored")
    for name in [n for n in args.segmenters.split(",") if n]:
        totals: dict[str, dict] = defaultdict(empty_scores)
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            for seq in sequences:
                seg = make(registry, name, overrides)
                scores = score_sequence(seg, seq, every=args.every, arm_share=args.arm_share)
                for key in (holder_of(seq), "all"):
                    for k, v in scores.items():
                        totals[key][k] += v
        except ArtclassError as exc:
            print(f"  {name:<16} error: {exc}")
            continue
        print(f"  {name} ({time.perf_counter() - t0:.0f} s, CPU {time.process_time() - c0:.0f} s)")
        for key in sorted(totals, key=lambda k: (k == "all", k)):
            t = totals[key]
            hand = (
                f"hand IoU pooled {t['intersection'] / t['union']:.3f}, mean {np.mean(t['hand_ious']):.3f} "
                f"({len(t['hand_ious'])} frames), mean {np.mean(t['border_ious']):.3f} where it reaches the "
                f"border ({len(t['border_ious'])} frames)"
                if t["border_ious"]
                else "no hand in the truth"
                if not t["union"]
                else f"hand IoU pooled {t['intersection'] / t['union']:.3f}, mean {np.mean(t['hand_ious']):.3f}"
            )
            alarms = (
                f"hand found in {t['found_without_hand']} of {t['frames_without_hand']} frames without"
                if t["frames_without_hand"]
                else ""
            )
            with_hand = len(t["hand_ious"])
            arm = (
                f"arm in the object's mask in {t['arm_in_mask'] / with_hand:.1%} of them" if with_hand else ""
            )
            objects = f"object IoU {np.mean(t['object_ious']):.3f} ({len(t['object_ious'])} frames)"
            cpu = f"segmenting {1000 * t['cpu_s'] / t['frames']:.1f} ms CPU a frame"
            print(f"    {key:<8} " + "; ".join(x for x in (objects, hand, arm, alarms, cpu) if x), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
