"""The learned hand detector against the hand masks of a labelled benchmark folder.

Not a test: it prints numbers. Run from the repository root::

    .venv/bin/python benchmarks/hand_detector.py benchmark_data/vga2
    .venv/bin/python benchmarks/hand_detector.py benchmark_data/vga2 --every 5 --threads 1

For each sequence folder with ``hand/*.png`` beside its frames (non-zero = the hand or gripper
with its arm), every N-th frame's colour image goes through
:class:`~artclass_plugins.segmenters.hand_detector.HandDetector`, and by holder (``hand``,
``gripper``, ``none``, from ``meta.json``):

* **detected**: the share of the frames with a hand in the truth where a hand is found;
* **false alarms**: the frames without a hand in the truth where a hand is found;
* **IoU**: the detector's hand mask against the true hand-and-arm mask, pooled over the frames
  with a hand in the truth (the detector stops at the wrist, so the arm counts against it);
* **IoU in the box**: the same, both masks cut to the detector's boxes (the arm outside them left
  out; frames where nothing is found count with their whole true hand);
* **precision**: the share of the detector's mask pixels that are truly hand or arm;
* **ms/frame**: wall-clock and CPU milliseconds of ``detect`` a frame.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
from hand_iou import holder_of

from artclass_core import ArtclassError, find_sequences, load_registry
from artclass_core.io import read_mask
from artclass_plugins.segmenters.hand_detector import HandDetector, HandDetectorParams, hands_mask

COUNTS = ("frames", "with_hand", "detected", "empty", "alarms", "inter", "union", "box_inter", "box_union")


def boxes_mask(hands, shape: tuple[int, int]) -> np.ndarray:
    mask = np.zeros(shape, bool)
    for hand in hands:
        x0, y0, x1, y1 = np.round(hand.box_px).astype(int)
        mask[y0:y1, x0:x1] = True
    return mask


def score_sequence(detector: HandDetector, seq, *, every: int) -> dict:
    out = dict.fromkeys(COUNTS, 0) | dict(wall_s=0.0, cpu_s=0.0, found_px=0, found_true_px=0)
    hand_dir = Path(seq.path) / "hand"
    for i in range(0, len(seq), every):
        frame = seq[i]
        truth_file = hand_dir / f"{frame.name}.png"
        if not truth_file.is_file():
            continue
        truth = read_mask(truth_file)
        t0, c0 = time.perf_counter(), time.process_time()
        hands = detector.detect(frame.rgb)
        out["wall_s"] += time.perf_counter() - t0
        out["cpu_s"] += time.process_time() - c0
        out["frames"] += 1
        found = hands_mask(hands, truth.shape)
        out["found_px"] += int(found.sum())
        out["found_true_px"] += int(np.count_nonzero(found & truth))
        if not truth.any():
            out["empty"] += 1
            out["alarms"] += int(bool(hands))
            continue
        out["with_hand"] += 1
        out["detected"] += int(bool(hands))
        out["inter"] += int(np.count_nonzero(found & truth))
        out["union"] += int(np.count_nonzero(found | truth))
        boxes = boxes_mask(hands, truth.shape) if hands else np.ones_like(truth)
        out["box_inter"] += int(np.count_nonzero(found & truth & boxes))
        out["box_union"] += int(np.count_nonzero((found | truth) & boxes))
    return out


def ratio(a: float, b: float) -> str:
    return f"{a / b:.3f}" if b else "-"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path, help="a folder of labelled sequences with hand/ truth")
    ap.add_argument("--every", type=int, default=1, help="score every N-th frame")
    ap.add_argument("--threads", type=int, default=1, help="CPU threads of each model")
    args = ap.parse_args(argv)
    try:
        sequences, _ = find_sequences(load_registry(), args.folder)
        detector = HandDetector(HandDetectorParams(threads=args.threads))
    except ArtclassError as exc:
        print(f"hand_detector: {exc}", file=sys.stderr)
        return 2
    print(f"{len(sequences)} sequences in {args.folder}, every {args.every}. frame, {args.threads} thread(s)")
    totals: dict[str, dict] = defaultdict(lambda: defaultdict(float))
    for seq in sequences:
        scores = score_sequence(detector, seq, every=args.every)
        for key in (holder_of(seq), "all"):
            for k, v in scores.items():
                totals[key][k] += v
    for key in sorted(totals, key=lambda k: (k == "all", k)):
        t = totals[key]
        print(
            f"  {key:<8} {int(t['frames'])} frames: detected in {int(t['detected'])}/{int(t['with_hand'])} "
            f"with a hand ({ratio(t['detected'], t['with_hand'])}); false alarms {int(t['alarms'])}/"
            f"{int(t['empty'])} without; IoU {ratio(t['inter'], t['union'])}, in the box "
            f"{ratio(t['box_inter'], t['box_union'])}; precision {ratio(t['found_true_px'], t['found_px'])}; "
            f"{1000 * t['wall_s'] / t['frames']:.1f} ms/frame ({1000 * t['cpu_s'] / t['frames']:.1f} ms CPU)",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
