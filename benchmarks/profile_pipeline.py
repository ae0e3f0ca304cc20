"""Profile one pipeline run (CPU time, so a busy machine does not distort it) and print the top calls.

    .venv/bin/python benchmarks/profile_pipeline.py [SEQUENCE] [--segmenter mask] [--registrar ...]
        [--rule ...] [--preprocessor ...] [--workers 1] [--top 30]

Without SEQUENCE it profiles the cached synthetic benchmark sequence of ``artclass bench`` (rendered
on first use). Prints numbers; never fails on a timing.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time

from artclass_core import Config, Pipeline, load_registry, open_sequences
from artclass_plugins.bench import bench_sequence, start_up


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("sequence", nargs="?")
    p.add_argument("--segmenter", default="mask")
    p.add_argument("--preprocessor")
    p.add_argument("--registrar")
    p.add_argument("--rule")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--top", type=int, default=30)
    args = p.parse_args()
    registry = load_registry()
    seq = open_sequences(registry, args.sequence or bench_sequence())[0]
    chosen = {
        k: v
        for k, v in dict(
            segmenter=args.segmenter, preprocessor=args.preprocessor, registrar=args.registrar, rule=args.rule
        ).items()
        if v
    }
    pipe = Pipeline(registry, Config(**chosen))
    print(f"start-up (loading compiled code, not profiled): {start_up():.2f} s")
    profile = cProfile.Profile(time.process_time)
    cpu0, wall0 = time.process_time(), time.perf_counter()
    profile.enable()
    result = pipe.run(seq, workers=args.workers)
    profile.disable()
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    print(
        f"{seq.name}: {len(seq)} frames, {len(result.pairs)} pairs, label {result.label}; "
        f"wall {wall:.2f} s, CPU {cpu:.2f} s; stage wall times {result.timing_s}"
    )
    print(f"plugins {result.plugins}")
    pstats.Stats(profile).sort_stats("tottime").print_stats(args.top)


if __name__ == "__main__":
    main()
