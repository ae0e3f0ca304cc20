"""Real recordings of rigid objects: how often is a rigid thing called articulated?

    .venv/bin/python benchmarks/real_recordings.py prepare DESK OUT
    .venv/bin/python benchmarks/real_recordings.py [--data ../shared/data] [--desk OUT] [--k 1,2,5]
                                                   [--segmenters mask,depth_threshold]

``prepare`` reads the hand-held RealSense D435 desk recording (a local copy of the public repository
Taeyoung96/Make-ORB-SLAM2-RGBD-dataset: ``rgb/``, ``depths/``, ``associations.txt``; depth in mm) with
the TUM reader and the D435's nominal colour intrinsics (fx = fy = 615, cx 320, cy 240), and writes
two stretches of 50 frames (every second frame: recorded frames 0-98 and 94-192) in the folder
layout under OUT, labelled rigid, with the scene within 1.5 m as the object's mask.

The default command classifies every real recording at each k with each segmenter: YCB-Video's
objects (``DATA/ycbv``), the TUM RGB-D cabinet circled by the camera (``DATA/real_moving``) and the
desk stretches (``--desk``, when prepared). Every object in them is rigid or static. It prints one
line per set, k and segmenter: sequences called articulated, the share of AM pairs among the decided
ones, the undecided pairs, and each sequence's label. Prints numbers; never fails.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from artclass_core import Config, Pipeline, find_sequences, load_registry
from artclass_plugins.readers.tum import TumParams
from artclass_plugins.synth.write import DEPTH_SCALE, prepare_sequence_dir, write_frame

D435_INTRINSICS = dict(fx=615.0, fy=615.0, cx=320.0, cy=240.0)
STRETCHES = {"desk_a": range(0, 100, 2), "desk_b": range(94, 193, 2)}
WITHIN_M = 1.5


def prepare(desk: Path, out: Path) -> None:
    registry = load_registry()
    reader = registry.create("reader", "tum", TumParams(**D435_INTRINSICS, depth_scale=1000.0))
    (recording,) = reader.sequences(desk)
    K = recording.intrinsics
    for name, frames in STRETCHES.items():
        folder = prepare_sequence_dir(out / name, overwrite=True)
        for n, i in enumerate(frames):
            frame = recording.load(i)
            mask = (frame.depth_m > 0) & (frame.depth_m <= WITHIN_M)
            write_frame(folder, n, rgb=frame.rgb, depth_m=frame.depth_m, mask=mask)
        meta = dict(
            fx=K.fx,
            fy=K.fy,
            cx=K.cx,
            cy=K.cy,
            depth_scale=DEPTH_SCALE,
            width=K.width,
            height=K.height,
            label="rigid",
            object="desk",
            source=f"Taeyoung96/Make-ORB-SLAM2-RGBD-dataset, recorded frames {frames.start}-{frames.stop - 1}, "
            f"every {frames.step}",
            note=f"hand-held RealSense D435 over a static desk; mask = the scene within {WITHIN_M} m",
        )
        (folder / "meta.json").write_text(json.dumps(meta, indent=1))
        print(f"{folder}: {len(frames)} frames")


def classify_all(roots: dict[str, Path], ks: list[int], segmenters: list[str]) -> None:
    registry = load_registry()
    print("| set | segmenter | k | articulated | AM pairs | undecided | labels |")
    print("|---|---|---|---|---|---|---|")
    for name, root in roots.items():
        sequences, errors = find_sequences(registry, root)
        for err in errors:
            print(f"skipping {err}")
        for segmenter in segmenters:
            for k in ks:
                config = Config(segmenter=segmenter).with_overrides(registry, dict(k=k))
                pipeline = Pipeline(registry, config)
                labels, am, decided, undecided = [], 0, 0, 0
                for seq in sequences:
                    try:
                        result = pipeline.run(seq, workers=1)
                    except Exception as exc:  # noqa: BLE001 - a benchmark reports, it does not stop
                        labels.append(f"{seq.name}: error ({exc})")
                        continue
                    ds = [p.decision for p in result.pairs]
                    am += ds.count("AM")
                    decided += sum(d in ("AM", "RM", "NM") for d in ds)
                    undecided += ds.count("undecided")
                    labels.append(f"{seq.name}: {result.label}")
                n_art = sum(s.endswith("articulated") for s in labels)
                share = am / decided if decided else np.nan
                print(
                    f"| {name} | {segmenter} | {k} | {n_art}/{len(sequences)} | {share:.1%} | {undecided} "
                    f"| {'; '.join(labels)} |",
                    flush=True,
                )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command")
    prep = sub.add_parser("prepare", help="write the desk stretches in the folder layout")
    prep.add_argument("desk", type=Path, help="local copy of Make-ORB-SLAM2-RGBD-dataset")
    prep.add_argument("out", type=Path)
    parser.add_argument("--data", type=Path, default=Path("../shared/data"))
    parser.add_argument("--desk", type=Path, help="the folder `prepare` wrote")
    parser.add_argument("--k", default="1,2,5")
    parser.add_argument("--segmenters", default="mask,depth_threshold")
    parser.add_argument("--only", default="", help="only the sets whose name contains this")
    args = parser.parse_args()
    if args.command == "prepare":
        prepare(args.desk, args.out)
        return
    roots = {"ycbv": args.data / "ycbv", "tum_cabinet": args.data / "real_moving"}
    if args.desk:
        roots["desk"] = args.desk
    roots = {n: r for n, r in roots.items() if args.only in n and r.is_dir()}
    classify_all(roots, [int(k) for k in args.k.split(",")], args.segmenters.split(","))


if __name__ == "__main__":
    main()
