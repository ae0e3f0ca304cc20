"""Record a benchmark set's registrations once, then decide the whole set again in seconds.

    .venv/bin/python benchmarks/replay.py record ROOT RUNS [--segmenter NAME] [--param NAME=VALUE ...]
    .venv/bin/python benchmarks/replay.py decide RUNS [--param NAME=VALUE ...]

``record`` runs the default pipeline (with the given segmenter and parameters) on every labelled
sequence under ROOT and stores each run in RUNS/, one file per sequence (about 25 MB for 24 frames at
640x480), with every pair's motion evidence over k frames and over slow_factor k frames, whatever the
pair's decision. A sequence already in RUNS is not run again.

``decide`` decides every stored run again (:meth:`~artclass_core.pipeline.Pipeline.redecide`: nothing
is read or registered) with the decision rule's current code and the given decision settings, scores
it against the sequences' current truth, and prints the report ``artclass evaluate`` prints (without
the parts and joints). A change to the rule's code or to a decision setting is measured on a whole set
in seconds instead of minutes. A setting the registrations depend on (the segmenter's, the
preprocessor's or the registrar's, k, slow_factor) cannot change: record again. The files are Python
pickles: decide only runs you recorded yourself.
"""

from __future__ import annotations

import argparse
import dataclasses
import pickle
import sys
import time
from pathlib import Path

from artclass_core import ArtclassError, Config, Pipeline, find_sequences, load_registry, open_sequences
from artclass_core.evaluate import evaluation, markdown, one_line, outcome_of, score_labels


def _config(registry, segmenter: str | None, params: list[str]) -> Config:
    config = Config() if segmenter is None else dataclasses.replace(Config(), segmenter=segmenter)
    return config.with_overrides(registry, dict(p.split("=", 1) for p in params)) if params else config


def record(registry, root: str, runs: Path, segmenter: str | None, params: list[str]) -> None:
    """Run and store every labelled sequence under ``root`` not yet in ``runs``."""
    pipeline = Pipeline(registry, _config(registry, segmenter, params))
    k, far = pipeline.params.k, pipeline.params.k * pipeline.params.slow_factor
    runs.mkdir(parents=True, exist_ok=True)
    sequences, errors = find_sequences(registry, root)
    for error in errors:
        print(f"skipped: {error}")
    for seq in sequences:
        path = runs / f"{seq.name.replace('/', '_')}.pkl"
        if path.exists():
            continue
        t0 = time.perf_counter()
        run = dict(path=str(Path(seq.path).resolve()), name=seq.name, segmenter=segmenter, params=params)
        try:
            result = pipeline.run(seq, keep_clouds=True)
        except Exception as exc:  # recorded: the set's report counts the sequence as failed
            run["error"] = one_line(exc)
        else:
            frames = {f.index: f for f in result.frames}
            for p in result.pairs:  # both baselines of every pair, so that any rule can choose
                if p.other is None and p.j == p.i + k and p.decision != "skipped" and p.i + far in frames:
                    between = tuple(frames[m] for m in range(p.i + 1, p.i + far))
                    p.other = pipeline.pair_of(seq, frames[p.i], frames[p.i + far], between, {}, None)
            for f in result.frames:
                f.cloud = None  # the evidence is what re-deciding needs
            run["result"] = result
        path.write_bytes(pickle.dumps(run, protocol=pickle.HIGHEST_PROTOCOL))
        print(
            f"{seq.name}: {result.label if 'result' in run else run['error']} ({time.perf_counter() - t0:.1f} s)"
        )


def decide(registry, runs: Path, params: list[str]) -> str:
    """The evaluation report of every run stored in ``runs``, decided again under ``params``."""
    outcomes, config = [], None
    for path in sorted(runs.glob("*.pkl")):
        run = pickle.loads(path.read_bytes())
        found = [s for s in open_sequences(registry, run["path"]) if s.name == run["name"]]
        if not found:
            raise ArtclassError(f"{path}: sequence {run['name']} is no longer at {run['path']}")
        seq = found[0]
        config = _config(registry, run["segmenter"], run["params"] + params)
        o = outcome_of(seq)
        if "error" in run:
            o.error = run["error"]
        else:
            pipeline = Pipeline(registry, config)
            result = pipeline.redecide(run["result"])
            for p in result.pairs:
                p.truth = seq.pair_truth(p.i, p.j)
            score_labels(o, pipeline, seq, result)
        outcomes.append(o)
    if config is None:
        raise ArtclassError(f"{runs}: no recorded runs (record them first)")
    return markdown([evaluation(config, outcomes)])


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    rec = sub.add_parser("record", help="run and store every labelled sequence under ROOT")
    rec.add_argument("root")
    rec.add_argument("runs", type=Path)
    rec.add_argument("--segmenter")
    dec = sub.add_parser("decide", help="decide the stored runs again and report")
    for p in (rec, dec):
        p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE")
    dec.add_argument("runs", type=Path)
    args = parser.parse_args()
    registry = load_registry()
    try:
        if args.command == "record":
            record(registry, args.root, args.runs, args.segmenter, args.param)
        else:
            print(decide(registry, args.runs, args.param))
    except ArtclassError as exc:
        print(f"replay: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
