"""The ``artclass`` command line. Errors the user can fix print one line and exit with status 2."""

from __future__ import annotations

import argparse
import json
import os
import sys
from functools import partial
from typing import Any

from tqdm import tqdm

from .articulation import Articulation, forget_clouds
from .config import JOINT_ESTIMATOR, PART_FINDER, PLUGIN_KINDS, Config
from .errors import ArtclassError
from .evaluate import evaluation, markdown
from .interfaces import KINDS
from .params import PipelineParams, describe
from .pipeline import Pipeline
from .plugins import Registry, load_registry
from .sequences import find_sequences, open_sequences, split_reader_values
from .sweep import DASK_HINT, grid_settings, plan_tasks, run_tasks
from .types import RunResult


class _Bars:
    """``progress(stage, done, total)`` shown as tqdm bars with an ETA, one per stage, closed when done."""

    def __init__(self):
        self._bars: dict[str, tqdm] = {}

    def __call__(self, stage: str, done: int, total: int) -> None:
        bar = self._bars.get(stage)
        if bar is None:
            bar = self._bars[stage] = tqdm(
                total=total, desc=stage, unit=stage.rstrip("s"), dynamic_ncols=True
            )
        bar.update(done - bar.n)
        if done >= total:
            self._bars.pop(stage).close()


def _progress(enabled: bool) -> _Bars | None:
    return _Bars() if enabled else None


def _pipeline_options(p: argparse.ArgumentParser, *, cluster: bool = False) -> None:
    defaults = Config()
    p.add_argument("--reader", help="dataset reader (default: the first that recognises the path)")
    for kind in PLUGIN_KINDS:
        p.add_argument(
            f"--{kind}",
            default=getattr(defaults, kind),
            help=f"{kind} plugin (default: {getattr(defaults, kind)})",
        )
    p.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="set a parameter by name or paper symbol (v, r, s, x, q_bar, t_bar, k, w, alpha); "
        "'auto' restores an automatic value; repeatable",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    cpus = os.cpu_count() or 1
    if not cluster:
        p.add_argument(
            "--workers",
            type=int,
            default=cpus,
            help="threads that process frames and pairs; the result is the same for any number "
            "(default: one per CPU, %(default)s here)",
        )
        return
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        help=f"threads that process the frames and pairs of one sequence; the result is the same for "
        f"any number (default: one per CPU, {cpus} here; 1 with --scheduler, where Dask runs "
        f"one sequence per worker thread)",
    )
    p.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run one task per sequence on a Dask cluster: the address of its scheduler "
        "(tcp://host:8786), or 'local' to start one on this machine; the data must be at the "
        f"same path on every worker (needs {DASK_HINT})",
    )


def _workers(args) -> int:
    if args.workers is not None:
        return args.workers
    return 1 if args.scheduler else os.cpu_count() or 1


def _all_overrides(args) -> dict[str, str]:
    overrides = {}
    for item in args.param:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ArtclassError(f"--param {item!r}: expected NAME=VALUE")
        overrides[key.strip()] = value.strip()
    return overrides


def _overrides(registry: Registry, args) -> dict[str, str]:
    """The ``--param`` settings of the pipeline and its plugins (the readers' are :func:`reader_values`)."""
    return split_reader_values(registry, _all_overrides(args))[1]


def reader_values(registry: Registry, args) -> dict[str, str]:
    """The ``--param`` settings that name a reader's parameter (``max_time_diff_s``, ``colour_topic`` ...)."""
    return split_reader_values(registry, _all_overrides(args))[0]


def config_from_args(registry: Registry, args: argparse.Namespace) -> Config:
    plugins = {kind: getattr(args, kind) for kind in PLUGIN_KINDS}
    return grid_settings(registry, {}, params=_overrides(registry, args), **plugins)[0].config(registry)


def cmd_classify(registry: Registry, args) -> int:
    config = config_from_args(registry, args)
    seq = open_one_sequence(registry, args.path, reader=args.reader, values=reader_values(registry, args))
    result, articulation = classify_with_parts(
        registry,
        config,
        seq,
        workers=args.workers,
        part_finder=args.part_finder,
        estimator=args.joint_estimator,
    )
    if args.json:
        out = result.to_dict(cells=not args.no_cells)
        if articulation is not None:
            out.update(articulation.to_dict())
        print(json.dumps(out))
        return 0
    decisions = " ".join({"skipped": "-", "undecided": "?"}.get(p.decision, p.decision) for p in result.pairs)
    print(f"{seq.name}: {result.label}" + (f" (ground truth: {seq.label})" if seq.label else ""))
    print(f"  why: {result.reason}")
    print(f"  pairs (i, i+{config.pipeline.k}): {decisions}")
    print(f"  after max-count filter (w={config.pipeline.w}): {' '.join(result.filtered)}")
    print("  fractions: " + ", ".join(f"{d} {v:.2f}" for d, v in result.fractions.items()))
    skipped = [p for p in result.pairs if p.decision == "skipped"]
    if skipped:
        print(f"  skipped pairs: {len(skipped)} (e.g. {skipped[0].i}-{skipped[0].j}: {skipped[0].reason})")
    if articulation is not None:
        print(f"  joints: {articulation.summary()}")
    print("  plugins: " + ", ".join(f"{k}={v}" for k, v in result.plugins.items()))
    print(f"  time: {result.timing_s['total']:.2f} s")
    return 0


def open_one_sequence(registry: Registry, path: str, *, reader: str | None = None, values=None):
    """The one sequence at ``path`` (``PATH#NAME`` picks one of several); ``values`` set reader
    parameters by name."""
    sequences = open_sequences(registry, path, reader=reader, reader_values=values)
    if len(sequences) > 1:
        names = ", ".join(s.name for s in sequences)
        raise ArtclassError(
            f"{path} holds {len(sequences)} sequences ({names}); choose one with "
            f"PATH#NAME, or run `artclass evaluate` over them"
        )
    return sequences[0]


def classify_with_parts(
    registry: Registry,
    config: Config,
    sequence,
    *,
    workers: int,
    part_finder: str = PART_FINDER,
    estimator: str = JOINT_ESTIMATOR,
) -> tuple[RunResult, Articulation | None]:
    """Classify ``sequence`` and find its parts and joints with the part finder ``part_finder`` (None
    when it cannot work on the runs of the configured rule). The clouds a run keeps for the parts are
    dropped afterwards."""
    pipeline = Pipeline(registry, config)
    finder = registry.create("part_finder", part_finder)
    with_parts = finder.works_on(pipeline.rule)
    result = pipeline.run(
        sequence, progress=_progress(sys.stderr.isatty()), workers=workers, keep_clouds=with_parts
    )
    if not with_parts:
        return result, None
    articulation = finder.find(result, estimator=registry.create("joint_estimator", estimator))
    forget_clouds(result)
    return result, articulation


def _labelled_sequences(registry: Registry, args) -> list:
    sequences, errors = find_sequences(
        registry, args.root, reader=args.reader, reader_values=reader_values(registry, args)
    )
    for err in errors:
        print(f"artclass: skipping {err}", file=sys.stderr)
    if not sequences:
        raise ArtclassError(f"{args.root}: no labelled sequence found")
    return sequences


def cmd_evaluate(registry: Registry, args) -> int:
    sequences = _labelled_sequences(registry, args)
    plugins = {kind: getattr(args, kind) for kind in PLUGIN_KINDS}
    settings = grid_settings(registry, {}, params=_overrides(registry, args), **plugins)
    if args.compare_rule:
        settings += grid_settings(
            registry, {}, params=_overrides(registry, args), **{**plugins, "rule": args.compare_rule}
        )
    if args.compare_paper:
        settings += grid_settings(
            registry,
            {},
            params={**_overrides(registry, args), "prealign": "false", "slow_factor": "1"},
            **{**plugins, "preprocessor": "paper", "rule": "paper"},
        )
    outcomes: list[dict[int, Any]] = [{} for _ in settings]
    bars = _progress(sys.stderr.isatty())
    tasks = plan_tasks(registry, sequences, settings)
    lost: list[str] = []
    for n, (i, m, _row, outcome) in enumerate(
        run_tasks(
            registry,
            tasks,
            settings,
            scheduler=args.scheduler,
            workers=_workers(args),
            reader=args.reader,
            lost=lost,
        ),
        1,
    ):
        outcomes[m][i] = outcome
        if bars:
            bars("runs", n, len(sequences) * len(settings))
    if lost:
        raise ArtclassError(f"{len(lost)} sequence(s) were lost by the cluster (e.g. {lost[0]}); run again")
    evals = [evaluation(st.config(registry), [o[i] for i in sorted(o)]) for st, o in zip(settings, outcomes)]
    if args.json:
        print(json.dumps(dict(evaluations=[e.to_dict() for e in evals]), indent=1))
    else:
        print(markdown(evals))
    return 0


def _param_dicts(params_cls: type) -> list[dict[str, Any]]:
    return [
        dict(
            name=s.name,
            symbol=s.symbol,
            unit=s.unit,
            default=s.default,
            bounds=list(s.bounds),
            auto=s.auto,
            help=s.help,
        )
        for s in describe(params_cls)
    ]


def _param_line(*, name, symbol, unit, default, auto, **_) -> str:
    sym = f" ({symbol})" if symbol else ""
    value = f"auto: {auto}" if default is None else repr(default)
    return f"      {name}{sym} = {value} {unit}".rstrip()


def plugin_table(registry: Registry) -> dict[str, Any]:
    """Every registered plugin with its parameters and origin (what ``artclass plugins`` prints)."""
    out: dict[str, Any] = {}
    for kind in KINDS:
        out[kind] = [
            dict(
                name=info.name,
                description=info.cls.description,
                source=info.source,
                params=_param_dicts(info.cls.Params),
            )
            for info in sorted(registry.plugins[kind].values(), key=lambda i: i.name)
        ]
    return out


def cmd_plugins(registry: Registry, args) -> int:
    table = plugin_table(registry)
    if args.json:
        print(json.dumps(dict(plugins=table, failures=registry.failures), indent=1, default=str))
        return 0
    for kind, items in table.items():
        print(f"{kind}s:")
        for item in items:
            print(f"  {item['name']:<22} {item['description']}  [{item['source']}]")
            for s in item["params"]:
                print(_param_line(**s))
    print("pipeline:")
    for s in _param_dicts(PipelineParams):
        print(_param_line(**s))
    for name, err in registry.failures.items():
        print(f"failed to load plugin {name!r}: {err}")
    return 0


def build_parser(registry: Registry) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="artclass",
        description=(
            "Tell from an RGB-D sequence whether the handled object is articulated, rigid or static."
        ),
    )
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("classify", help="classify one sequence")
    p.add_argument("path", help="sequence folder (PATH#NAME picks one of several)")
    _pipeline_options(p)
    p.add_argument("--no-cells", action="store_true", help="leave the per-cell details out of --json")
    p.add_argument("--part-finder", default=PART_FINDER, help="part finder plugin (default: %(default)s)")
    p.add_argument(
        "--joint-estimator", default=JOINT_ESTIMATOR, help="joint estimator plugin (default: %(default)s)"
    )
    p.set_defaults(func=partial(cmd_classify, registry))
    p = sub.add_parser("evaluate", help="classify every labelled sequence under a folder and report accuracy")
    p.add_argument("root")
    _pipeline_options(p, cluster=True)
    p.add_argument("--compare-rule", metavar="RULE", help="also evaluate this decision rule, side by side")
    p.add_argument(
        "--compare-paper",
        action="store_true",
        help="also evaluate the paper's pipeline as written (paper preprocessor and rule, no prealignment)",
    )
    p.set_defaults(func=partial(cmd_evaluate, registry))
    p = sub.add_parser("plugins", help="list the registered plugins and their parameters")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=partial(cmd_plugins, registry))
    registry.add_parser_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    try:
        registry = load_registry()
        args = build_parser(registry).parse_args(argv)
        return args.func(args)
    except ArtclassError as exc:
        print(f"artclass: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
