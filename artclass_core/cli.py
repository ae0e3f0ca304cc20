"""The ``artclass`` command line. Errors the user can fix print one line and exit with status 2."""

from __future__ import annotations

import argparse
import json
import os
import sys
from functools import partial
from typing import Any

from .errors import ArtclassError
from .evaluate import evaluate, markdown
from .params import PipelineParams, describe
from .pipeline import PLUGIN_KINDS, Config, Pipeline
from .plugins import Registry, load_registry
from .sequences import find_sequences, open_sequences
from .interfaces import KINDS


def _progress(enabled: bool):
    if not enabled:
        return None

    def show(stage: str, done: int, total: int) -> None:
        width = 30
        filled = int(width * done / max(total, 1))
        sys.stderr.write(f"\r{stage:>10} [{'#' * filled}{'.' * (width - filled)}] {done}/{total}")
        if done >= total:
            sys.stderr.write("\n")
        sys.stderr.flush()
    return show


def _pipeline_options(p: argparse.ArgumentParser) -> None:
    defaults = Config()
    p.add_argument("--reader", help="dataset reader (default: the first that recognises the path)")
    for kind in PLUGIN_KINDS:
        p.add_argument(f"--{kind}", default=getattr(defaults, kind),
                       help=f"{kind} plugin (default: {getattr(defaults, kind)})")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="set a parameter by name or paper symbol (v, r, s, x, q_bar, t_bar, k, w, alpha); "
                        "'auto' restores an automatic value; repeatable")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                   help="threads that process frames and pairs; the result is the same for any number "
                        "(default: one per CPU, %(default)s here)")


def config_from_args(registry: Registry, args: argparse.Namespace, **replace: str) -> Config:
    names = {kind: replace.get(kind, getattr(args, kind)) for kind in PLUGIN_KINDS}
    for kind, name in names.items():
        if not (kind == "segmenter" and name == "auto"):
            registry.get(kind, name)   # unknown plugin -> PluginError naming the registered ones
    overrides = {}
    for item in args.param:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ArtclassError(f"--param {item!r}: expected NAME=VALUE")
        overrides[key.strip()] = value.strip()
    return Config(**names).with_overrides(registry, overrides)


def cmd_classify(registry: Registry, args) -> int:
    config = config_from_args(registry, args)
    sequences = open_sequences(registry, args.path, reader=args.reader)
    if len(sequences) > 1:
        names = ", ".join(s.name for s in sequences)
        raise ArtclassError(f"{args.path} holds {len(sequences)} sequences ({names}); choose one with "
                            f"PATH#NAME, or run `artclass evaluate` over them")
    seq = sequences[0]
    result = Pipeline(registry, config).run(seq, progress=_progress(sys.stderr.isatty()), workers=args.workers)
    if args.json:
        print(json.dumps(result.to_dict(cells=not args.no_cells)))
        return 0
    decisions = " ".join(p.decision if p.decision != "skipped" else "-" for p in result.pairs)
    print(f"{seq.name}: {result.label}"
          + (f" (ground truth: {seq.label})" if seq.label else ""))
    print(f"  pairs (i, i+{config.pipeline.k}): {decisions}")
    print(f"  after max-count filter (w={config.pipeline.w}): {' '.join(result.filtered)}")
    print("  fractions: " + ", ".join(f"{d} {v:.2f}" for d, v in result.fractions.items()))
    skipped = [p for p in result.pairs if p.decision == "skipped"]
    if skipped:
        print(f"  skipped pairs: {len(skipped)} (e.g. {skipped[0].i}-{skipped[0].j}: {skipped[0].reason})")
    print("  plugins: " + ", ".join(f"{k}={v}" for k, v in result.plugins.items()))
    print(f"  time: {result.timing_s['total']:.2f} s")
    return 0


def cmd_evaluate(registry: Registry, args) -> int:
    sequences, errors = find_sequences(registry, args.root, reader=args.reader)
    for err in errors:
        print(f"artclass: skipping {err}", file=sys.stderr)
    if not sequences:
        raise ArtclassError(f"{args.root}: no labelled sequence found")
    configs = [config_from_args(registry, args)]
    if args.compare_rule:
        configs.append(config_from_args(registry, args, rule=args.compare_rule))
    if args.compare_paper:
        configs.append(config_from_args(registry, args, preprocessor="paper", rule="paper")
                       .with_overrides(registry, {"prealign": False}))
    evals = [evaluate(registry, sequences, c, progress=_progress(sys.stderr.isatty()), workers=args.workers)
             for c in configs]
    if args.json:
        print(json.dumps(dict(evaluations=[e.to_dict() for e in evals]), indent=1))
    else:
        print(markdown(evals))
    return 0


def _param_dicts(params_cls: type) -> list[dict[str, Any]]:
    return [dict(name=s.name, symbol=s.symbol, unit=s.unit, default=s.default, bounds=list(s.bounds), auto=s.auto,
                 help=s.help) for s in describe(params_cls)]


def _param_line(*, name, symbol, unit, default, auto, **_) -> str:
    sym = f" ({symbol})" if symbol else ""
    value = f"auto: {auto}" if default is None else repr(default)
    return f"      {name}{sym} = {value} {unit}".rstrip()


def plugin_table(registry: Registry) -> dict[str, Any]:
    """Every registered plugin with its parameters and origin (what ``artclass plugins`` prints)."""
    out: dict[str, Any] = {}
    for kind in KINDS:
        out[kind] = [dict(name=info.name, description=info.cls.description, source=info.source,
                          params=_param_dicts(info.cls.Params))
                     for info in sorted(registry.plugins[kind].values(), key=lambda i: i.name)]
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
    parser = argparse.ArgumentParser(prog="artclass", description=(
        "Tell from an RGB-D sequence whether the handled object is articulated, rigid or static."))
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("classify", help="classify one sequence")
    p.add_argument("path", help="sequence folder (PATH#NAME picks one of several)")
    _pipeline_options(p)
    p.add_argument("--no-cells", action="store_true", help="leave the per-cell details out of --json")
    p.set_defaults(func=partial(cmd_classify, registry))
    p = sub.add_parser("evaluate", help="classify every labelled sequence under a folder and report accuracy")
    p.add_argument("root")
    _pipeline_options(p)
    p.add_argument("--compare-rule", metavar="RULE", help="also evaluate this decision rule, side by side")
    p.add_argument("--compare-paper", action="store_true",
                   help="also evaluate the paper's pipeline as written (paper preprocessor and rule, no prealignment)")
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
