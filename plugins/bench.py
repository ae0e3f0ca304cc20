"""``artclass bench``: throughput and memory of the pipeline, printed as numbers (never pass/fail).

What it measures, on a synthetic 640x480 sequence of an articulated object that is carried
(``artclass_plugins.synth.generate_sequence(..., motion="carry_articulate")``, rendered once and
cached under ``$XDG_CACHE_HOME/artclass/bench`` keyed by the generator's version and parameters):

- per stage (read, segment, preprocess, register, decide) and in total: seconds, frames/s, pairs/s,
  ms per frame and per pair, for each segmenter (``mask``, ``depth_threshold``) x each worker count;
  and the peak resident memory of the run;
- the paper's pipeline as written on the same sequence, and the default's time per pair as a share
  of its time;
- the time to re-decide the sequence after a decision-rule parameter changes (reusing the cached
  registrations through :class:`artclass_core.pipeline.StageCache`), next to a full re-run;
- the cost of finding the parts and joints (the part finder, ``tracks`` by default) on top of
  the classification, as a share of its run time, on a clip whose part is found (:data:`PARTS_SEQUENCE`,
  rendered and cached the same way; with ``--sequence``, that sequence);
- a long sequence (default 1000 frames, the rendered frames played back and forth by
  :class:`CycledSequence`, so nothing long has to be rendered): peak resident memory and the
  resident memory after 10 % of the pairs and at the end (it must not grow with the length).

Every measurement runs in a fresh (spawned) process so that its peak memory is its own. Stage times
are wall-clock times summed over the worker threads; with more than one worker they add up to more
than the wall time, and the throughput that counts is the ``total`` row (wall clock). On a shared,
busy machine wall times stretch with the load average (printed with every run); the process CPU
time ("pairs per CPU-second") does not.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import inspect
import json
import multiprocessing
import os
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from artclass_core import Frame, Sequence, hookimpl
from artclass_core.types import DECISIONS

STAGES = ("read", "segment", "preprocess", "register", "decide")
FRAME_STAGES = ("read", "segment", "preprocess")
DEFAULT_SEQUENCE = dict(
    object_name="drawer", motion="carry_articulate", noise="low", n_frames=60, seed=0, width=640, height=480
)
#: The clip the parts-and-joints cost is measured on: a laptop opening, whose lid the parts stage finds.
PARTS_SEQUENCE = dict(object_name="laptop", motion="articulate", n_frames=24)


# -- the benchmark sequence ------------------------------------------------------------------------
def cache_root() -> Path:
    """Where rendered benchmark sequences are kept (``$XDG_CACHE_HOME/artclass/bench``)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "artclass" / "bench"


def bench_sequence(*, cache_dir: Path | None = None, **spec: Any) -> Path:
    """The benchmark sequence folder, rendered with the synthetic generator on first use.

    Parameters
    ----------
    cache_dir : folder holding rendered sequences (default :func:`cache_root`)
    **spec : arguments of ``generate_sequence`` (object_name, motion, noise, n_frames, seed, width,
        height); missing ones take :data:`DEFAULT_SEQUENCE`

    Returns
    -------
    Path : ``cache_dir/<object>_<motion>_<w>x<h>_<n>f_<hash>``, where the hash covers the generator
    version and every parameter, so a new generator renders anew.
    """
    from artclass_plugins.synth import GENERATOR_VERSION, generate_sequence

    spec = {**DEFAULT_SEQUENCE, **spec}
    digest = hashlib.sha256(json.dumps(dict(spec, generator=GENERATOR_VERSION), sort_keys=True).encode())
    name = (
        f"{spec['object_name']}_{spec['motion']}_{spec['width']}x{spec['height']}_{spec['n_frames']}f_"
        f"{digest.hexdigest()[:10]}"
    )
    root = Path(cache_dir) if cache_dir else cache_root()
    out = root / name
    if (out / "meta.json").is_file():
        return out
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{name}.", dir=root))
    try:
        generate_sequence(tmp / name, **spec)
        os.replace(tmp / name, out)  # atomic: a half-rendered sequence is never taken from the cache
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


class CycledSequence(Sequence):
    """A long sequence made of a short one played back and forth (0, 1, ..., n-1, n-2, ..., 0, 1, ...).

    Memory-light: each frame is read from the base sequence when asked for (the base keeps its own
    small cache) and copied, so a long run holds no more frames than a short one. Consecutive frames
    stay consecutive in the base, so pairs (i, i + k) see the same small motions everywhere.
    """

    def __init__(self, base: Sequence, n_frames: int):
        super().__init__(
            name=f"{base.name}_x{n_frames}",
            path=base.path,
            intrinsics=base.intrinsics,
            n_frames=n_frames,
            label=base.label,
            object_name=base.object_name,
            has_masks=base.has_masks,
            accepted_labels=base.accepted_labels,
            meta=base.meta,
        )
        self.base = base

    def base_index(self, i: int) -> int:
        n = len(self.base)
        if n == 1:
            return 0
        t = i % (2 * n - 2)
        return t if t < n else 2 * n - 2 - t

    def load(self, i: int) -> Frame:
        f = self.base[self.base_index(i)]
        return Frame(
            i, f"{i:06d}", f.rgb.copy(), f.depth_m.copy(), None if f.mask is None else f.mask.copy(), f.time_s
        )

    def pair_truth(self, i: int, j: int):
        return self.base.pair_truth(self.base_index(i), self.base_index(j))


# -- measurements (each in a fresh process) ---------------------------------------------------------
def rss_mb() -> float:
    """Current resident memory of this process, MB (from /proc/self/status; 0 where unavailable)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MB (``ru_maxrss``; KB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _supports(fn, name: str) -> bool:
    return name in inspect.signature(fn).parameters


def _config(registry, spec: dict):
    from artclass_core import Config

    base = Config.paper() if spec.get("paper") else Config()
    cfg = dataclasses.replace(
        base,
        segmenter=spec["segmenter"],
        **{kind: spec[kind] for kind in ("preprocessor", "registrar", "rule") if spec.get(kind)},
    )
    overrides = dict(spec.get("params") or {})
    return cfg.with_overrides(registry, overrides) if overrides else cfg


def _open(registry, spec: dict) -> Sequence:
    from artclass_core import open_sequences

    seq = open_sequences(registry, spec["path"])[0]
    if spec.get("long_frames"):
        seq = CycledSequence(seq, spec["long_frames"])
    return seq


def _run_kwargs(pipeline, spec: dict) -> dict:
    kw = {}
    if _supports(pipeline.run, "workers"):
        kw["workers"] = spec.get("workers", 1)
    elif spec.get("workers", 1) != 1:
        raise RuntimeError("this Pipeline.run has no `workers` option")
    return kw


def start_up() -> float:
    """Load what is only loaded when first used (the PNG decoder's, the dense registrar's, the
    segmenters', the joint fit's and the parts' compiled loops: Numba and its cached machine code),
    which the timed runs leave out as start-up; returns its seconds."""
    import importlib

    t0 = time.perf_counter()
    for module in (
        "artclass_core.io",
        "artclass_plugins.dense.projective",
        "artclass_plugins.segmenters._compiled",
        "artclass_plugins.joints._compiled",
        "artclass_plugins.parts._compiled",
    ):
        try:
            warm_up = importlib.import_module(module).warm_up
        except ImportError:
            continue
        warm_up()
    return time.perf_counter() - t0


def measure_run(spec: dict) -> dict:
    """Run one configuration on one sequence and report times and memory (called in a child)."""
    from artclass_core import Pipeline, load_registry

    registry = load_registry()
    seq = _open(registry, spec)
    pipe = Pipeline(registry, _config(registry, spec))
    kw = _run_kwargs(pipe, spec)
    n_pairs = max(len(seq) - pipe.params.k, 0)
    start_up_s = start_up()
    rss_base = rss_mb()
    samples: dict[int, float] = {}
    marks = {max(1, n_pairs // 10), n_pairs // 2, n_pairs}

    def progress(stage, done, total):
        if done in marks:
            samples[done] = rss_mb()

    cpu0 = time.process_time()
    t0 = time.perf_counter()
    result = pipe.run(seq, progress=progress, **kw)
    wall = time.perf_counter() - t0
    cpu = time.process_time() - cpu0
    return dict(
        spec=spec,
        n_frames=len(seq),
        n_pairs=len(result.pairs),
        n_decided=sum(p.decision in DECISIONS for p in result.pairs),
        label=result.label,
        timing_s=dict(result.timing_s),
        wall_s=wall,
        cpu_s=cpu,
        start_up_s=start_up_s,
        rss_base_mb=rss_base,
        rss_samples_mb={str(k): v for k, v in sorted(samples.items())},
        peak_rss_mb=peak_rss_mb(),
        run_kwargs=kw,
        load=os.getloadavg()[0],
    )


def measure_parts(spec: dict) -> dict:
    """The cost of finding parts and joints on top of classification (called in a child): one run that
    keeps what the parts need, then the part finder on it."""
    from artclass_core import Pipeline, load_registry
    from artclass_core.config import JOINT_ESTIMATOR, PART_FINDER

    registry = load_registry()
    seq = _open(registry, spec)
    pipe = Pipeline(registry, _config(registry, spec))
    finder = registry.create("part_finder", PART_FINDER)
    estimator = registry.create("joint_estimator", JOINT_ESTIMATOR)
    start_up_s = start_up()
    t0, c0 = time.perf_counter(), time.process_time()
    result = pipe.run(seq, keep_clouds=True, **_run_kwargs(pipe, spec))
    t1, c1 = time.perf_counter(), time.process_time()
    articulation = finder.find(result, estimator=estimator)
    t2, c2 = time.perf_counter(), time.process_time()
    return dict(
        spec=spec,
        n_frames=len(seq),
        label=result.label,
        run_s=t1 - t0,
        parts_s=t2 - t1,
        run_cpu_s=c1 - c0,
        parts_cpu_s=c2 - c1,
        summary=articulation.summary(),
        start_up_s=start_up_s,
        peak_rss_mb=peak_rss_mb(),
        load=os.getloadavg()[0],
    )


def format_parts(m: dict) -> str:
    if "error" in m:
        return f"parts and joints: error: {m['error']}\n"
    return (
        f"parts and joints ({Path(m['spec']['path']).name}, {m['n_frames']} frames, "
        f"segmenter={m['spec']['segmenter']}, "
        f"workers={m['spec'].get('workers', 1)}): {m['parts_s']:.2f} s on top of the run's {m['run_s']:.2f} s "
        f"= {m['parts_s'] / m['run_s']:.1%} of the classification's wall time ({m['parts_cpu_s']:.2f} / "
        f"{m['run_cpu_s']:.2f} s = {m['parts_cpu_s'] / m['run_cpu_s']:.1%} of its CPU time; peak RSS "
        f"{m['peak_rss_mb']:.0f} MB with the clouds kept, load {m['load']:.1f}; before the run, start-up "
        f"{m['start_up_s']:.2f} s); label {m['label']}; {m['summary']}\n"
    )


def _nudged_rule_params(registry, config, factor: float = 1.1):
    """The rule's params with its first float parameter multiplied by ``factor`` (within bounds)."""
    from artclass_core import describe

    params = config.plugin_params(registry, "rule")
    for spec in describe(type(params)):
        value = getattr(params, spec.name)
        if spec.type is float and isinstance(value, float):
            new = value * factor
            low, high = spec.bounds
            if (high is not None and new > high) or (low is not None and new < low):
                continue
            return dataclasses.replace(params, **{spec.name: new}), f"{spec.name}: {value:g} -> {new:g}"
    return params, "(no float parameter to change)"


def measure_redecide(spec: dict) -> dict:
    """Time a decision-parameter change: cached re-decide (when available) and a full re-run."""
    from artclass_core import Pipeline, load_registry
    from artclass_core import pipeline as pipeline_module

    registry = load_registry()
    seq = _open(registry, spec)
    config = _config(registry, spec)
    pipe = Pipeline(registry, config)
    kw = _run_kwargs(pipe, spec)
    new_params, change = _nudged_rule_params(registry, config)
    new_config = dataclasses.replace(config, rule_params=new_params)
    # Each path is timed on a change of its own: a rule may memoise what a threshold leaves unchanged,
    # and a second path timed on the same change would find the first one's work done.
    other_params, other_change = _nudged_rule_params(registry, config, 0.9)
    other_config = dataclasses.replace(config, rule_params=other_params)
    out: dict[str, Any] = dict(spec=spec, change=change, other_change=other_change, n_frames=len(seq))
    cache_cls = getattr(pipeline_module, "StageCache", None)
    t0 = time.perf_counter()
    if cache_cls is not None:
        cache = cache_cls()
        first = pipe.run(seq, cache=cache, **kw)
    else:
        first = pipe.run(seq, **kw)
    out["first_run_s"] = time.perf_counter() - t0
    if cache_cls is not None:
        # the app's path: the same run call, with a cache that already holds clouds and registrations
        t0 = time.perf_counter()
        again = Pipeline(registry, new_config).run(seq, cache=cache, **kw)
        out["cached_rerun_s"] = time.perf_counter() - t0
        out["cache_stats"] = cache.stats()
        if hasattr(Pipeline, "redecide"):
            t0 = time.perf_counter()
            more = (
                {"workers": kw["workers"]}
                if "workers" in kw and _supports(Pipeline.redecide, "workers")
                else {}
            )
            redecided = Pipeline(registry, other_config).redecide(first, sequence=seq, cache=cache, **more)
            out["redecide_s"] = time.perf_counter() - t0
            again = Pipeline(registry, other_config).run(seq, cache=cache, **kw)
            out["redecide_equals_cached_rerun"] = [p.decision for p in redecided.pairs] == [
                p.decision for p in again.pairs
            ]
    t0 = time.perf_counter()
    full = Pipeline(registry, new_config).run(_open(registry, spec), **kw)
    out["full_rerun_s"] = time.perf_counter() - t0
    out["label_before"], out["label_after"] = first.label, full.label
    out["peak_rss_mb"] = peak_rss_mb()
    return out


_TASKS = {"run": measure_run, "redecide": measure_redecide, "parts": measure_parts}


def _child(task: str, spec: dict, conn) -> None:
    try:
        conn.send(("ok", _TASKS[task](spec)))
    except BaseException as exc:  # reported by the parent, one line
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        conn.close()


def in_child(task: str, spec: dict) -> dict:
    """Run a measurement in a fresh spawned process (so its peak memory is its own)."""
    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(task, spec, child))
    proc.start()
    child.close()
    try:
        status, value = parent.recv()
    except EOFError:
        status, value = "error", f"the measuring process died (exit code {proc.join() or proc.exitcode})"
    proc.join()
    if status != "ok":
        return dict(spec=spec, error=value)
    return value


# -- report ------------------------------------------------------------------------------------------
def stage_rows(m: dict) -> list[tuple[str, float, float | None, float | None, float | None, float | None]]:
    """(stage, seconds, frames/s, pairs/s, ms/frame, ms/pair) per stage, then ``total`` (wall)."""
    n_f, n_p = m["n_frames"], max(m["n_pairs"], 1)
    rows = []
    for stage in (*STAGES, "total"):
        s = m["wall_s"] if stage == "total" else m["timing_s"].get(stage, 0.0)
        per_frame = stage in FRAME_STAGES or stage == "total"
        per_pair = stage not in FRAME_STAGES
        rows.append(
            (
                stage,
                s,
                (n_f / s if s and per_frame else None),
                (n_p / s if s and per_pair else None),
                (1e3 * s / n_f if per_frame else None),
                (1e3 * s / n_p if per_pair else None),
            )
        )
    return rows


def _f(x, fmt="{:.1f}") -> str:
    return "-" if x is None else fmt.format(x)


def _pipeline_name(spec: dict) -> str:
    return "the paper's pipeline" if spec.get("paper") else "default pipeline"


def format_run(m: dict) -> str:
    spec = m["spec"]
    head = (
        f"{_pipeline_name(spec)}: segmenter={spec['segmenter']} workers={spec.get('workers', 1)}"
        + "".join(f" {kind}={spec[kind]}" for kind in ("preprocessor", "registrar", "rule") if spec.get(kind))
    )
    if "error" in m:
        return f"{head}\n  error: {m['error']}\n"
    lines = [
        f"{head}: {m['n_frames']} frames, {m['n_pairs']} pairs ({m['n_decided']} decided), "
        f"label {m['label']}; wall {m['wall_s']:.2f} s, CPU {m['cpu_s']:.2f} s "
        f"({m['n_pairs'] / m['cpu_s']:.1f} pairs per CPU-second, {1e3 * m['cpu_s'] / max(m['n_pairs'], 1):.1f} ms "
        f"of CPU per pair, {m['cpu_s'] / m['wall_s']:.2f} cores busy), "
        f"peak RSS {m['peak_rss_mb']:.0f} MB (after imports {m['rss_base_mb']:.0f} MB), load {m['load']:.1f}; "
        f"before the run, start-up {m.get('start_up_s', 0.0):.2f} s (loading compiled code)",
        f"  {'stage':<11}{'seconds':>9}{'frames/s':>10}{'pairs/s':>10}{'ms/frame':>10}{'ms/pair':>10}",
    ]
    for stage, s, fps, pps, mspf, mspp in stage_rows(m):
        lines.append(
            f"  {stage:<11}{s:>9.3f}{_f(fps):>10}{_f(pps):>10}{_f(mspf, '{:.2f}'):>10}"
            f"{_f(mspp, '{:.2f}'):>10}"
        )
    return "\n".join(lines) + "\n"


def format_long(m: dict) -> str:
    if "error" in m:
        return f"long sequence: error: {m['error']}\n"
    samples = ", ".join(f"after {k} pairs {v:.0f} MB" for k, v in m["rss_samples_mb"].items())
    return (
        f"long sequence ({m['n_frames']} frames, {_pipeline_name(m['spec'])}, segmenter={m['spec']['segmenter']}, "
        f"workers={m['spec'].get('workers', 1)}, "
        f"options {m['run_kwargs']}): peak RSS {m['peak_rss_mb']:.0f} MB (after imports "
        f"{m['rss_base_mb']:.0f} MB); RSS {samples}; {m['n_pairs'] / m['wall_s']:.1f} pairs/s, "
        f"wall {m['wall_s']:.1f} s, load {m['load']:.1f}\n"
    )


def format_redecide(m: dict) -> str:
    if "error" in m:
        return f"re-decide: error: {m['error']}\n"
    lines = [
        f"re-decide after a rule change ({m['n_frames']} frames, {_pipeline_name(m['spec'])}, "
        f"segmenter={m['spec']['segmenter']}, workers={m['spec'].get('workers', 1)}):"
    ]
    if "cached_rerun_s" in m:
        lines.append(
            f"  run() with a StageCache holding the clouds and registrations ({m['change']}): "
            f"{m['cached_rerun_s']:.3f} s (cache {m['cache_stats']})"
        )
    if "redecide_s" in m:
        lines.append(
            f"  Pipeline.redecide(result) ({m.get('other_change', m['change'])}): {m['redecide_s']:.3f} s "
            f"(same decisions as the cached run: {m['redecide_equals_cached_rerun']})"
        )
    if "cached_rerun_s" not in m:
        lines.append("  no StageCache in this version: a change means a full re-run")
    lines.append(
        f"  full re-run: {m['full_rerun_s']:.3f} s (first run {m['first_run_s']:.3f} s); "
        f"label {m['label_before']} -> {m['label_after']}"
    )
    return "\n".join(lines) + "\n"


def format_ratio(ours: dict, paper: dict) -> str:
    """The time per pair of a run as a share of the paper's pipeline's, on the same sequence and workers."""
    if "error" in ours or "error" in paper:
        return "time per pair against the paper's pipeline: not measured (a run failed)"
    mine, theirs = ours["wall_s"] / max(ours["n_pairs"], 1), paper["wall_s"] / max(paper["n_pairs"], 1)
    cpu = (ours["cpu_s"] / max(ours["n_pairs"], 1)) / (paper["cpu_s"] / max(paper["n_pairs"], 1))
    return (
        f"time per pair against the paper's pipeline (segmenter={ours['spec']['segmenter']}, "
        f"workers={ours['spec'].get('workers', 1)}): {1e3 * mine:.1f} ms / {1e3 * theirs:.1f} ms = "
        f"{mine / theirs:.2f} of its wall time ({cpu:.2f} of its CPU time)"
    )


def _csv(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


def run_bench(args) -> int:
    from artclass_core import load_registry

    registry = load_registry()
    out = sys.stdout
    if args.quick:
        args.segmenters, args.workers, args.long_frames = "mask", "1", 0
    if args.sequence:
        path = str(args.sequence)
    else:
        t0 = time.perf_counter()
        try:
            path = str(
                bench_sequence(
                    cache_dir=args.cache_dir,
                    width=args.width,
                    height=args.height,
                    n_frames=args.frames,
                    seed=args.seed,
                )
            )
        except ImportError as exc:
            print(
                f"artclass bench: the synthetic generator is not available ({exc}); pass --sequence PATH",
                file=sys.stderr,
            )
            return 2
        out.write(f"benchmark sequence: {path} (ready in {time.perf_counter() - t0:.1f} s)\n")
    segmenters = [s for s in _csv(args.segmenters) if s in registry.names("segmenter")]
    missing = [s for s in _csv(args.segmenters) if s not in registry.names("segmenter")]
    workers = [int(w) for w in _csv(args.workers)]
    rev = (
        os.popen(f"git -C {Path(__file__).resolve().parent} rev-parse --short HEAD 2>/dev/null")
        .read()
        .strip()
    )
    import artclass_core

    out.write(
        f"artclass bench: commit {rev or 'unknown'} (core from {Path(artclass_core.__file__).parent}), "
        f"{os.cpu_count()} CPUs, Python {sys.version.split()[0]}, load average {os.getloadavg()[0]:.1f}\n\n"
    )
    for name in missing:
        out.write(f"segmenter {name!r} is not registered: skipped\n\n")
    results: dict[str, Any] = dict(sequence=path, runs=[], commit=rev)
    base = dict(
        path=path,
        preprocessor=args.preprocessor,
        registrar=args.registrar,
        rule=args.rule,
        paper=args.paper,
        params=dict(p.split("=", 1) for p in args.param),
    )
    for seg in segmenters:
        for w in workers:
            m = in_child("run", dict(base, segmenter=seg, workers=w))
            results["runs"].append(m)
            out.write(format_run(m) + "\n")
            out.flush()
    if not args.skip_paper and not args.paper and segmenters:
        m = in_child("run", dict(path=path, paper=True, segmenter=segmenters[0], workers=workers[0]))
        results["paper"] = m
        out.write(format_run(m) + "\n")
        out.write(format_ratio(results["runs"][0], m) + "\n\n")
        out.flush()
    if not args.skip_redecide and segmenters:
        m = in_child("redecide", dict(base, segmenter=segmenters[0], workers=max(workers)))
        results["redecide"] = m
        out.write(format_redecide(m) + "\n")
        out.flush()
    if not args.skip_parts and segmenters and not args.paper:
        parts_path = path
        if not args.sequence:
            size = dict(width=args.width, height=args.height, seed=args.seed)
            parts_path = str(bench_sequence(cache_dir=args.cache_dir, **size, **PARTS_SEQUENCE))
        m = in_child("parts", dict(base, path=parts_path, segmenter=segmenters[0], workers=max(workers)))
        results["parts"] = m
        out.write(format_parts(m) + "\n")
        out.flush()
    if args.long_frames and segmenters:
        m = in_child(
            "run", dict(base, segmenter=segmenters[0], workers=max(workers), long_frames=args.long_frames)
        )
        results["long"] = m
        out.write(format_long(m))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=str))
        out.write(f"\nwrote {args.json}\n")
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sequence", help="benchmark this sequence instead of the rendered synthetic one")
    p.add_argument(
        "--frames",
        type=int,
        default=DEFAULT_SEQUENCE["n_frames"],
        help="frames of the synthetic sequence (default 60)",
    )
    p.add_argument("--width", type=int, default=DEFAULT_SEQUENCE["width"])
    p.add_argument("--height", type=int, default=DEFAULT_SEQUENCE["height"])
    p.add_argument("--seed", type=int, default=DEFAULT_SEQUENCE["seed"])
    p.add_argument(
        "--cache-dir", type=Path, help=f"where rendered sequences are kept (default {cache_root()})"
    )
    p.add_argument(
        "--segmenters", default="mask,depth_threshold", help="comma-separated (default mask,depth_threshold)"
    )
    p.add_argument("--preprocessor", help="preprocessor (default: the pipeline's default)")
    p.add_argument("--registrar", help="registrar (default: the pipeline's default)")
    p.add_argument("--rule", help="decision rule (default: the pipeline's default)")
    p.add_argument(
        "--skip-paper",
        action="store_true",
        help="do not time the paper's pipeline as written on the same sequence",
    )
    p.add_argument(
        "--paper",
        action="store_true",
        help="start from Config.paper() (the paper's pipeline as written) instead of the defaults",
    )
    p.add_argument(
        "--workers",
        default=f"1,{max(os.cpu_count() or 1, 1)}" if (os.cpu_count() or 1) > 1 else "1",
        help="comma-separated worker counts to measure (default 1 and the number of CPUs)",
    )
    p.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="set a parameter by name or paper symbol, as in `artclass classify`",
    )
    p.add_argument(
        "--long-frames",
        type=int,
        default=1000,
        help="length of the memory test sequence (0 = skip; default 1000)",
    )
    p.add_argument("--skip-redecide", action="store_true", help="skip the re-decide measurement")
    p.add_argument("--skip-parts", action="store_true", help="skip the parts-and-joints measurement")
    p.add_argument(
        "--quick",
        action="store_true",
        help="a short check: the mask segmenter, 1 worker, the paper's pipeline beside it, no long sequence",
    )
    p.add_argument("--json", metavar="FILE", help="also write every number to this JSON file")


@hookimpl
def register_commands(subparsers):
    p = subparsers.add_parser(
        "bench",
        help="measure throughput and memory (prints numbers, never fails)",
        description=__doc__.split("\n\n")[0],
    )
    add_arguments(p)
    p.set_defaults(func=run_bench)
