"""Benchmark of the segmenters: milliseconds per 640x480 frame, and mask quality (IoU).

Not a test: it prints numbers. Run from the repository root::

    .venv/bin/python benchmarks/bench_segmenters.py                    # mask, depth_threshold, u2net
    .venv/bin/python benchmarks/bench_segmenters.py --maskrcnn-model /path/MaskRCNN-12.onnx
    .venv/bin/python benchmarks/bench_segmenters.py --repeat 3 --segmenters depth_threshold
    .venv/bin/python benchmarks/bench_segmenters.py --segmenters depth_threshold --param exclude_hands=false

Timing: the YCB-Video excerpts (../shared/data/ycbv, 640x480 real RGB-D, 15 frames) are read into
memory first, so disk reading is excluded; each repeat segments every frame with a fresh segmenter
object (no cached masks), so the time per frame covers the per-frame work (instances) and the
manipulated-instance selection. The best of ``--repeat`` runs is reported, with the median, and the
CPU time (all threads), which a busy machine inflates less than the wall time.

The hand step (:mod:`artclass_plugins.segmenters.hands`) is also timed alone, on the same frames
and on copies with a skin-coloured forearm and hand drawn in from the right border, 0.45 m from the
camera: CPU ms per frame of ``find_hands`` (given the background mask) and ``held``.

Quality: on YCB-Video, the IoU of the chosen mask with the union of the labelled objects and with
the best-matching single object; on the synthetic ``sample_data/`` sequences, the IoU with the
ground-truth mask.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from artclass_core import ArtclassError, Frame, Sequence, load_registry, open_sequences
from artclass_plugins.segmenters.depth_threshold import DepthThresholdParams, DepthThresholdSegmenter
from artclass_plugins.segmenters.hands import find_hands, held
from artclass_plugins.segmenters.selection import mask_iou

ROOT = Path(__file__).resolve().parents[1]
YCBV = (ROOT / ".." / "shared" / "data" / "ycbv").resolve()


class Preloaded(Sequence):
    """A sequence held in memory (frames copied from a reader's sequence, with its settings, such as
    the gripper's colour)."""

    def __init__(self, source: Sequence):
        super().__init__(
            name=source.name,
            path=source.path,
            intrinsics=source.intrinsics,
            n_frames=len(source),
            has_masks=source.has_masks,
            meta=source.meta,
        )
        self.frames = [source[i] for i in range(len(source))]
        self.cache_frames = len(source)

    def load(self, i: int) -> Frame:
        return self.frames[i]


def make(registry, name: str, overrides: dict[str, str]):
    cls = registry.get("segmenter", name)
    fields = {k: v for k, v in overrides.items() if k in cls.Params.__dataclass_fields__}
    return cls(cls.Params(**fields))


def parse_overrides(items: list[str]) -> dict:
    """``NAME=VALUE`` strings as a dict, values as int, float or bool where they read as one."""
    out: dict = {}
    for item in items:
        key, _, value = item.partition("=")
        out[key] = {"true": True, "false": False}.get(value.lower(), value)
        for cast in (int, float):
            try:
                out[key] = cast(value)
                break
            except ValueError:
                pass
    return out


def time_segmenter(
    registry, name: str, sequences: list[Sequence], *, repeat: int, overrides
) -> tuple[list[float], list[float]]:
    """Wall and CPU (all threads) ms per frame of each repeat (fresh segmenter each time, all frames
    of all sequences)."""
    wall, cpu = [], []
    n = sum(len(s) for s in sequences)
    for _ in range(repeat):
        seg = make(registry, name, overrides)
        t0, c0 = time.perf_counter(), time.process_time()
        for seq in sequences:
            for i in range(len(seq)):
                seg.segment(seq[i], sequence=seq)
        wall.append(1000 * (time.perf_counter() - t0) / n)
        cpu.append(1000 * (time.process_time() - c0) / n)
    return wall, cpu


def with_drawn_hand(frame: Frame, fx: float, *, depth_m: float = 0.45) -> tuple[Frame, np.ndarray]:
    """A copy of ``frame`` with a light-skin forearm (7 cm wide) and palm (9 x 8 cm) drawn in from the
    right border at ``depth_m`` from the camera (in front of the tables and objects of these scenes);
    and the drawn mask. ``fx``: focal length, pixels."""
    h, w = frame.depth_m.shape
    px = fx / depth_m  # pixels per metre at the hand's depth
    palm = (int(0.7 * w), h // 2)
    shape = np.zeros((h, w), np.uint8)
    cv2.line(shape, (w - 1, h // 2 + h // 8), palm, 1, int(0.07 * px))
    cv2.ellipse(shape, palm, (int(0.045 * px), int(0.04 * px)), 0, 0, 360, 1, -1)
    hand = shape > 0
    rgb, depth = frame.rgb.copy(), frame.depth_m.copy()
    rgb[hand] = (224, 172, 140)
    depth[hand] = depth_m
    return Frame(frame.index, frame.name, rgb, depth), hand


def time_hands(sequences: list[Sequence], *, repeat: int) -> str:
    """CPU ms per frame of the hand step alone (find_hands + held), without and with a drawn hand,
    and the drawn hand's mean IoU."""
    params = DepthThresholdParams()
    parts = []
    for drawn in (False, True):
        cases = []
        for seq in sequences:
            seg = DepthThresholdSegmenter(params)
            for i in range(len(seq)):
                frame, truth = with_drawn_hand(seq[i], seq.intrinsics.fx) if drawn else (seq[i], None)
                _, background, _ = seg.scene(frame, sequence=seq)
                cases.append((frame, background, seq, truth))
        best = float("inf")
        for _ in range(repeat):
            c0 = time.process_time()
            hands = []
            for frame, background, seq, _ in cases:
                hand = find_hands(frame, background, seq.intrinsics, params=params, sequence_path=seq.path)
                held([background & ~hand], hand, frame.depth_m, touch_m=params.hand_touch_m)
                hands.append(hand)
            best = min(best, 1000 * (time.process_time() - c0) / len(cases))
        text = f"{'with' if drawn else 'without'} a drawn hand {best:.1f} ms/frame"
        if drawn:
            text += f" (hand IoU {np.mean([mask_iou(h, c[3]) for h, c in zip(hands, cases)]):.3f})"
        else:
            text += f" ({sum(int(h.any()) for h in hands)} of {len(hands)} frames with a hand found)"
        parts.append(text)
    return "hand step alone (CPU): " + "; ".join(parts)


def ycbv_quality(registry, name: str, scenes: dict[str, list[Sequence]], overrides) -> str:
    parts = []
    for scene, seqs in scenes.items():
        seg = make(registry, name, overrides)
        union, best = [], []
        for i in range(len(seqs[0])):
            mask = seg.segment(seqs[0][i], sequence=seqs[0])
            labelled = [s[i].mask for s in seqs]
            if mask is None:
                union.append(0.0)
                best.append(0.0)
                continue
            union.append(mask_iou(mask, np.any(labelled, axis=0)))
            best.append(max(mask_iou(mask, m) for m in labelled))
        parts.append(
            f"ycbv/{scene}: IoU union {np.mean(union):.3f} (min {np.min(union):.3f}), "
            f"best single {np.mean(best):.3f}"
        )
    return "; ".join(parts)


def synthetic_quality(registry, name: str, folders: list[Path], overrides) -> str:
    parts = []
    for folder in folders:
        seq = open_sequences(registry, folder)[0]
        seg = make(registry, name, overrides)
        ious = []
        for i in range(len(seq)):
            mask = seg.segment(seq[i], sequence=seq)
            ious.append(0.0 if mask is None else mask_iou(mask, seq[i].mask))
        parts.append(f"{folder.name} {np.mean(ious):.3f}")
    return "synthetic IoU: " + ", ".join(parts)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--segmenters", default="mask,depth_threshold,u2net")
    ap.add_argument("--maskrcnn-model", help="a MaskRCNN-10/12 ONNX file: also benchmark maskrcnn")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-quality", action="store_true", help="timings only")
    ap.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="segmenter parameter (applied where the segmenter has it)",
    )
    args = ap.parse_args(argv)
    if not YCBV.is_dir():
        print(
            f"bench_segmenters: {YCBV} is absent; it holds the 640x480 frames this benchmark times",
            file=sys.stderr,
        )
        return 1
    overrides = parse_overrides(args.param)
    names = [n for n in args.segmenters.split(",") if n]
    if args.maskrcnn_model:
        names.append("maskrcnn")
        overrides["model_path"] = args.maskrcnn_model
    registry = load_registry()
    scenes = {
        scene: [Preloaded(s) for s in open_sequences(registry, YCBV / scene, reader="ycbv")]
        for scene in ("0000", "0001")
    }
    timed = [seqs[0] for seqs in scenes.values()]
    n = sum(len(s) for s in timed)
    w, h = timed[0].intrinsics.width, timed[0].intrinsics.height
    synthetic = (
        sorted(p for p in (ROOT / "sample_data").iterdir() if (p / "meta.json").is_file())
        if (ROOT / "sample_data").is_dir()
        else []
    )
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(
        f"segmenters on {n} YCB-Video frames of {w}x{h} (in memory), best / median of {args.repeat} runs; "
        f"{os.cpu_count()} CPUs, load average {load:.1f} at the start"
    )
    for name in names:
        try:
            runs, cpu = time_segmenter(registry, name, timed, repeat=args.repeat, overrides=overrides)
        except ArtclassError as exc:
            print(f"  {name:<16} error: {exc}")
            continue
        line = (
            f"  {name:<16} {min(runs):8.1f} ms/frame (median {statistics.median(runs):.1f}; "
            f"CPU {min(cpu):.1f} ms/frame over all threads)"
        )
        print(line, flush=True)
        if name == "depth_threshold":
            print(f"  {'':<16} {time_hands(timed, repeat=args.repeat)}", flush=True)
        if not args.no_quality:
            print(f"  {'':<16} {ycbv_quality(registry, name, scenes, overrides)}", flush=True)
            if synthetic and name != "maskrcnn":
                print(f"  {'':<16} {synthetic_quality(registry, name, synthetic, overrides)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
