"""Reading a long recording as a bag against the folder layout: milliseconds a frame and peak memory.

Writes one N-frame sequence (default 1000 frames at 640x480, a synthetic laptop of 40 rendered frames
played over and over) in the folder layout and as bags (ROS 1, ROS 2 sqlite3, ROS 2 MCAP, the
RealSense SDK's layout, whose depth is registered to colour on reading), then, each in a fresh
process: opens it and reads every frame in order (what the pipeline does), timing it, and records
the peak resident memory. With ``--pipeline`` it also runs the pipeline over the folder and the
ROS 1 bag (``Pipeline.run``, streaming, as ``artclass bench``'s 1000-frame memory row does) and
records their time and peak memory. Numbers only, never pass/fail::

    python benchmarks/bag_reading.py                        # 1000 frames, 640x480, in a temporary folder
    python benchmarks/bag_reading.py --frames 200 --pipeline --out /tmp/bags
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from itertools import cycle, islice
from pathlib import Path

FORMATS = {  # name: (file or folder name, write_bag keywords)
    "ros1": ("rec.bag", {}),
    "ros2-sqlite3": ("rec_db3", {}),
    "ros2-mcap": ("rec_mcap", dict(storage="mcap")),
    "realsense-ros1": ("rec_rs.bag", dict(layout="realsense")),
}


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def read_all(path: str) -> dict:
    """Open ``path`` and read every frame in order, in this process: seconds and peak memory."""
    from artclass_core import load_registry, open_sequences

    registry = load_registry()
    t0 = time.perf_counter()
    (seq,) = open_sequences(registry, path)
    opened = time.perf_counter() - t0
    for i in range(len(seq)):
        seq[i]
    total = time.perf_counter() - t0
    return dict(
        frames=len(seq),
        open_s=opened,
        read_ms=1000 * (total - opened) / len(seq),
        ms_per_frame=1000 * total / len(seq),
        peak_rss_mb=_peak_rss_mb(),
    )


def run_pipeline(path: str, workers: int) -> dict:
    """The pipeline over ``path`` in this process (mask-free, streaming): seconds, label, peak memory."""
    from artclass_core import Config, Pipeline, load_registry, open_sequences

    registry = load_registry()
    (seq,) = open_sequences(registry, path)
    t0 = time.perf_counter()
    result = Pipeline(registry, Config(segmenter="depth_threshold")).run(seq, workers=workers)
    return dict(seconds=time.perf_counter() - t0, label=result.label, peak_rss_mb=_peak_rss_mb())


def in_child(*argv: str) -> dict:
    """One measurement in a fresh process (its own peak memory), as JSON on the last line."""
    out = subprocess.run(
        [sys.executable, __file__, "--child", *argv], check=True, capture_output=True, text=True
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


def write_inputs(
    out: Path, *, n_frames: int, width: int, height: int, seed: int
) -> tuple[Path, dict[str, Path]]:
    """The folder layout (the rendered PNGs, linked over and over) and each bag of :data:`FORMATS`."""
    from artclass_core import load_registry, open_sequences
    from artclass_plugins.readers.bag import write_bag
    from artclass_plugins.synth import generate_sequence

    rendered = out / "rendered"
    if not (rendered / "meta.json").is_file():
        generate_sequence(
            rendered,
            object_name="laptop",
            motion="articulate",
            noise="low",
            n_frames=40,
            seed=seed,
            width=width,
            height=height,
        )
    folder = out / "folder"
    if not (folder / "meta.json").is_file():
        for sub in ("rgb", "depth"):
            (folder / sub).mkdir(parents=True, exist_ok=True)
            files = sorted((rendered / sub).iterdir())
            for i, src in enumerate(islice(cycle(files), n_frames)):
                os.link(src, folder / sub / f"{i:06d}.png")
        meta = json.loads((rendered / "meta.json").read_text())
        (folder / "meta.json").write_text(
            json.dumps({k: meta[k] for k in ("fx", "fy", "cx", "cy", "depth_scale")})
        )
    (seq,) = open_sequences(load_registry(), folder)
    bags = {}
    for name, (file, kw) in FORMATS.items():
        bags[name] = out / file
        if not bags[name].exists():
            write_bag((seq[i] for i in range(len(seq))), bags[name], intrinsics=seq.intrinsics, **kw)
    return folder, bags


def size_mb(path: Path) -> float:
    files = [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file()]
    return sum(p.stat().st_size for p in files) / 2**20


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=1000)
    p.add_argument("--size", default="640x480", help="WIDTHxHEIGHT (default %(default)s)")
    p.add_argument("--out", help="where to write the recordings (default: a temporary folder, removed)")
    p.add_argument(
        "--pipeline", action="store_true", help="also run the pipeline over the folder and the ROS 1 bag"
    )
    p.add_argument("--workers", type=int, default=2, help="for --pipeline (default %(default)s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        what, path, *rest = args.child
        print(json.dumps(read_all(path) if what == "read" else run_pipeline(path, int(rest[0]))))
        return
    width, height = (int(v) for v in args.size.split("x"))
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="artclass-bags-"))
    out.mkdir(parents=True, exist_ok=True)
    try:
        t0 = time.perf_counter()
        folder, bags = write_inputs(out, n_frames=args.frames, width=width, height=height, seed=args.seed)
        print(
            f"{args.frames} frames, {width}x{height}, written in {time.perf_counter() - t0:.0f} s to {out}\n"
        )
        rows = {"folder": (folder, in_child("read", str(folder)))}
        rows.update((name, (path, in_child("read", str(path)))) for name, path in bags.items())
        base = rows["folder"][1]["ms_per_frame"]
        print("reading every frame in order (ms/frame counts the opening too)")
        head = ("layout", "size MB", "open s", "read ms", "ms/frame", "vs folder", "peak RSS MB")
        print("{:<16} {:>8} {:>7} {:>8} {:>9} {:>10} {:>12}".format(*head))
        for name, (path, r) in rows.items():
            print(
                f"{name:<16} {size_mb(path):>8.0f} {r['open_s']:>7.2f} {r['read_ms']:>8.2f} "
                f"{r['ms_per_frame']:>9.2f} {r['ms_per_frame'] - base:>+10.2f} {r['peak_rss_mb']:>12.0f}"
            )
        if args.pipeline:
            print(
                f"\nPipeline.run, depth_threshold, {args.workers} workers (streaming: clouds dropped after use)"
            )
            for name, path in (("folder", folder), ("ros1", bags["ros1"])):
                r = in_child("pipeline", str(path), str(args.workers))
                print(
                    f"{name:<16} {r['seconds']:>7.1f} s {1000 * r['seconds'] / args.frames:>7.1f} ms/frame  "
                    f"peak RSS {r['peak_rss_mb']:>6.0f} MB  label {r['label']}"
                )
    finally:
        if not args.out:
            shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
    main()
