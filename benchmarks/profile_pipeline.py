"""Profile one pipeline run (CPU time, so a busy machine does not distort it) and print where the time
goes: by kind of work, then the top calls.

    .venv/bin/python benchmarks/profile_pipeline.py [SEQUENCE] [--segmenter mask] [--registrar ...]
        [--rule ...] [--preprocessor ...] [--workers 1] [--runs 1] [--sort tottime] [--top 30]

Without SEQUENCE it profiles the cached synthetic benchmark sequence of ``artclass bench`` (rendered
on first use). With ``--runs N`` the same pipeline runs N times in this process and the last run is
profiled; each run's user and system CPU and page faults are printed, so the cost of a process's first
run (memory touched for the first time) shows beside a warm one. The profiled run's CPU is also given
per stage: milliseconds per frame (read, segment, preprocess) and per pair (register, decide), the
profile's cumulative time of the function that does each stage. Prints numbers; never fails on a timing.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import resource
import time

import cv2

from artclass_core import Config, Pipeline, load_registry, open_sequences
from artclass_plugins.bench import bench_sequence, start_up

_DECODING = {"_decode_png", "_decode_plain_png", "_image_data", "unfilter"}


def kind_of(function: tuple[str, int, str]) -> str:
    """The kind of work of a profiled function, from its (file, line, name) key."""
    path, _, name = function
    if name == "<method 'calc' of 'cv2.DenseOpticalFlow' objects>":
        return "optical flow (OpenCV DIS)"
    # OpenCV's and imagecodecs' decoders, and the steps and compiled loop of artclass_core.io's own
    if (
        name == "<imdecode>"
        or "imagecodecs" in name
        or (path.endswith("artclass_core/io.py") and name in _DECODING)
    ):
        return "PNG decoding"
    if path.endswith("_compiled.py"):
        return "compiled loops (Numba)"
    if path == "~" and name.startswith("<") and hasattr(cv2, name.strip("<>")):
        return "other OpenCV calls"
    return "NumPy and Python"


def by_kind(stats: pstats.Stats) -> dict[str, float]:
    """Own (not cumulative) CPU seconds of each kind of work, largest first."""
    seconds: dict[str, float] = {}
    for function, (_, _, own, _, _) in stats.stats.items():
        kind = kind_of(function)
        seconds[kind] = seconds.get(kind, 0.0) + own
    return dict(sorted(seconds.items(), key=lambda kv: -kv[1]))


def stage_functions(pipe: Pipeline, seq) -> dict[str, tuple]:
    """The functions that do each stage of ``pipe`` on ``seq``, as the profile names them."""
    functions = {
        "read": [type(seq).load],
        "segment": [type(pipe.segmenter(seq)).segment],
        "preprocess": [type(pipe.preprocessor).process],
        "register": [Pipeline._register_raw],
        "decide": [Pipeline.decide_motions, Pipeline.decide],
    }
    return {
        stage: [(f.__code__.co_filename, f.__code__.co_firstlineno, f.__code__.co_name) for f in fs]
        for stage, fs in functions.items()
    }


def by_stage(stats: pstats.Stats, functions: dict[str, list[tuple]]) -> dict[str, tuple[float, int]]:
    """Cumulative CPU seconds and calls of each stage's functions."""
    out = {}
    for stage, keys in functions.items():
        rows = [stats.stats[k] for k in keys if k in stats.stats]
        out[stage] = (sum(r[3] for r in rows), sum(r[1] for r in rows))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("sequence", nargs="?")
    p.add_argument("--segmenter", default="mask")
    p.add_argument("--preprocessor")
    p.add_argument("--registrar")
    p.add_argument("--rule")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--runs", type=int, default=1, help="run this many times, profile the last")
    p.add_argument("--sort", default="tottime", help="pstats sort key (tottime, cumulative, ...)")
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
    for run in range(1, args.runs + 1):
        profile = cProfile.Profile(time.process_time) if run == args.runs else None
        before, wall0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        if profile:
            profile.enable()
        result = pipe.run(seq, workers=args.workers)
        if profile:
            profile.disable()
        wall, after = time.perf_counter() - wall0, resource.getrusage(resource.RUSAGE_SELF)
        print(
            f"run {run}: {seq.name}: {len(seq)} frames, {len(result.pairs)} pairs, label {result.label}; "
            f"wall {wall:.2f} s, CPU user {after.ru_utime - before.ru_utime:.2f} s + system "
            f"{after.ru_stime - before.ru_stime:.2f} s, {after.ru_minflt - before.ru_minflt} page faults"
            + (" (profiled)" if profile else "")
        )
    print(f"stage wall times {result.timing_s}\nplugins {result.plugins}")
    stats = pstats.Stats(profile)
    print("CPU by stage (cumulative, profiled run):")
    for stage, (seconds, calls) in by_stage(stats, stage_functions(pipe, seq)).items():
        per = "frame" if stage in ("read", "segment", "preprocess") else "pair"
        print(
            f"  {stage:<12}{seconds:7.2f} s {calls:5d} calls {1e3 * seconds / max(calls, 1):7.2f} ms a {per}"
        )
    total = sum(by_kind(stats).values())
    print("CPU by kind of work (own time, profiled run):")
    for kind, seconds in by_kind(stats).items():
        print(f"  {kind:<28}{seconds:7.2f} s {100 * seconds / total:5.1f} %")
    stats.sort_stats(args.sort).print_stats(args.top)


if __name__ == "__main__":
    main()
