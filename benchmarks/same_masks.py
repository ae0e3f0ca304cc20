"""The masks of a segmenter on a set of sequences, kept in a file and compared with a later run, with
the time it took: a speed-up must leave every mask as it was.

Not a test: it prints numbers and the frames whose masks differ. Run from the repository root::

    .venv/bin/python benchmarks/same_masks.py benchmark_data/vga3 --save /tmp/masks_before.npz
    .venv/bin/python benchmarks/same_masks.py benchmark_data/vga3 --compare /tmp/masks_before.npz
    .venv/bin/python benchmarks/same_masks.py benchmark_data/vga3 --only 00_,40_,54_ --profile 25

For each sequence folder under FOLDER (``--only``: those whose names start with one of the given
prefixes) the frames are read into memory first, then a fresh segmenter (``--segmenter``, default
``depth_threshold``) segments every frame in order. Kept per frame: the chosen (manipulated) mask,
the hand mask (segmenters that look for hands) and every instance. ``--compare`` prints each frame
whose masks differ from the file's, with the number of differing pixels, and exits with status 1
when any does. Timing: CPU and wall ms per frame of segmenting (CPU of all threads; the best of
``--repeat`` runs, each with a fresh segmenter, after one untimed frame that loads the compiled
loops); a busy machine inflates CPU time less than wall time, and ``--opencv-threads 1`` keeps
OpenCV's own threads from adding to it. ``--profile N`` also prints the N functions with the most
CPU time over all runs (cProfile; ``--sort``).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from bench_segmenters import Preloaded, make, parse_overrides

from artclass_core import find_sequences, load_registry


def run(seg, sequence) -> tuple[dict[str, np.ndarray], float, float]:
    """Every frame's chosen mask, hand mask and instances, as bit-packed arrays keyed by
    ``sequence/frame/kind``; and the CPU and wall seconds spent segmenting (the masks' packing
    excluded)."""
    out, cpu, wall = {}, 0.0, 0.0
    for i in range(len(sequence)):
        frame = sequence[i]
        c0, t0 = time.process_time(), time.perf_counter()
        chosen = seg.segment(frame, sequence=sequence)
        hand = seg.hand_mask(frame, sequence=sequence) if hasattr(seg, "hand_mask") else None
        instances = seg.frame_instances(frame, sequence=sequence) if hasattr(seg, "frame_instances") else []
        cpu, wall = cpu + time.process_time() - c0, wall + time.perf_counter() - t0
        key = f"{sequence.name}/{i:04d}"
        out[f"{key}/object"] = _pack(chosen, frame.depth_m.shape)
        out[f"{key}/hand"] = _pack(hand, frame.depth_m.shape)
        for k, m in enumerate(instances):
            out[f"{key}/instance{k}"] = _pack(m, frame.depth_m.shape)
    return out, cpu, wall


def _pack(mask: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    return np.packbits(np.zeros(shape, bool) if mask is None else mask)


def differences(now: dict[str, np.ndarray], before: dict[str, np.ndarray]) -> list[str]:
    """One line per mask that differs (or exists in one run only), with the differing pixels."""
    lines = []
    for key in sorted(set(now) | set(before)):
        if key not in now or key not in before:
            lines.append(f"{key}: only in the {'new' if key in now else 'saved'} run")
        elif not np.array_equal(now[key], before[key]):
            n = int(np.unpackbits(now[key] ^ before[key]).sum())
            lines.append(f"{key}: {n} pixels differ")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path, help="a folder of sequences")
    ap.add_argument("--only", default="", help="comma-separated prefixes of the sequence names to use")
    ap.add_argument("--segmenter", default="depth_threshold")
    ap.add_argument("--save", type=Path, help="write the masks to this .npz file")
    ap.add_argument("--compare", type=Path, help="compare the masks with this .npz file")
    ap.add_argument("--repeat", type=int, default=1, help="timed runs (the best is printed)")
    ap.add_argument("--profile", type=int, default=0, metavar="N", help="print the top N functions")
    ap.add_argument("--opencv-threads", type=int, help="cv2.setNumThreads (default: OpenCV's own)")
    ap.add_argument("--sort", default="tottime", help="the profile's order (tottime, cumulative, ...)")
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE")
    args = ap.parse_args(argv)
    if args.opencv_threads is not None:
        cv2.setNumThreads(args.opencv_threads)
    registry = load_registry()
    prefixes = tuple(p for p in args.only.split(",") if p)
    found, _ = find_sequences(registry, args.folder)
    found = [s for s in found if not prefixes or s.name.startswith(prefixes)]
    overrides = parse_overrides(args.param)
    masks, cpu, wall, n = {}, 0.0, 0.0, 0
    profile = cProfile.Profile(time.process_time) if args.profile else None
    if found:  # untimed: loads what the segmenter loads on first use (compiled loops)
        make(registry, args.segmenter, overrides).segment(found[0][0], sequence=found[0])
    for source in found:  # one sequence in memory at a time
        sequence = Preloaded(source)
        best = (float("inf"), float("inf"))
        for _ in range(max(args.repeat, 1)):
            seg = make(registry, args.segmenter, overrides)
            if profile:
                profile.enable()
            got, c, w = run(seg, sequence)
            if profile:
                profile.disable()
            best = min(best, (c, w))
        masks.update(got)
        cpu, wall, n = cpu + best[0], wall + best[1], n + len(sequence)
    print(
        f"{args.segmenter}: {len(found)} sequences, {n} frames, {1000 * cpu / max(n, 1):.1f} ms of CPU "
        f"and {1000 * wall / max(n, 1):.1f} ms of wall time per frame"
    )
    if profile:
        pstats.Stats(profile).sort_stats(args.sort).print_stats(args.profile)
    if args.save:
        np.savez_compressed(args.save, **masks)
        print(f"masks written to {args.save}")
    if args.compare:
        names = {f"{s.name}/" for s in found}
        with np.load(args.compare) as saved:  # the sequences of this run only
            lines = differences(masks, {k: saved[k] for k in saved.files if k[: k.index("/") + 1] in names})
        print("\n".join(lines) if lines else f"all {len(masks)} masks as in {args.compare}")
        return 1 if lines else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
