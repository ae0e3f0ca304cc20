"""The ``artclass sweep`` command: every labelled sequence under a folder for every setting of a
parameter grid, into one table (:func:`artclass_core.sweep.sweep`) and its figure
(:func:`artclass_plugins.figures.sweep_figure`, written next to the table as HTML)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from artclass_core import hookimpl
from artclass_core.cli import _labelled_sequences, _overrides, _pipeline_options, _progress, _workers
from artclass_core.config import PLUGIN_KINDS
from artclass_core.plugins import load_registry
from artclass_core.sweep import grid_settings, parse_grid, summary, sweep, swept_names
from artclass_core.types import DECISIONS

from .figures import sweep_figure


def _cmd_sweep(args) -> int:
    registry = load_registry()
    grid = parse_grid(args.grid)
    out = Path(args.out)
    sequences = _labelled_sequences(registry, args)
    settings = grid_settings(
        registry,
        grid,
        params=_overrides(registry, args),
        **{kind: getattr(args, kind) for kind in PLUGIN_KINDS},
    )
    lost: list[str] = []
    try:
        table = sweep(
            registry,
            sequences,
            settings,
            out=out,
            scheduler=args.scheduler,
            workers=_workers(args),
            force=args.force,
            reader=args.reader,
            progress=_progress(sys.stderr.isatty()),
            lost=lost,
        )
    except KeyboardInterrupt:
        print(
            f"artclass: interrupted; the finished rows are in {out}: run the same command again to resume",
            file=sys.stderr,
        )
        raise
    html = out.with_suffix(".html")
    sweep_figure(table).write_html(html, include_plotlyjs=True, full_html=True)  # no internet needed
    summ = summary(table)
    if args.json:
        print(
            json.dumps(
                dict(table=str(out), figure=str(html), summary=summ.to_dict("records"), lost=lost),
                default=str,
            )
        )
    else:
        print(
            summ.drop(columns=swept_names(table), errors="ignore").to_string(
                index=False,
                na_rep="–",
                formatters={
                    "accuracy": "{:.1%}".format,
                    "pair_accuracy": "{:.1%}".format,
                    "seconds": "{:.1f}".format,
                    **{d: "{:.3f}".format for d in DECISIONS},
                },
            )
        )
        failed = table["error"].notna().sum()
        print(f"\n{len(table)} rows ({failed} failed, see the error column) in {out}; figure: {html}")
    for item in lost:
        print(f"artclass: lost by the cluster, not recorded: {item}", file=sys.stderr)
    if lost:
        print("artclass: run the same command again to run the lost sequences", file=sys.stderr)
    return 1 if lost else 0


@hookimpl
def register_commands(subparsers):
    p = subparsers.add_parser(
        "sweep",
        help="evaluate every labelled sequence under a folder for every setting of a grid, into one table",
    )
    p.add_argument("root", help="folder searched for labelled sequences (recursively)")
    p.add_argument(
        "--grid",
        action="append",
        default=[],
        required=True,
        metavar="NAME=V1,V2,...",
        help="a parameter (by name or paper symbol) or a plugin kind and the values to try; repeatable: "
        "every combination runs",
    )
    _pipeline_options(p, cluster=True)
    p.add_argument(
        "--out",
        default="sweep.parquet",
        metavar="TABLE",
        help="the results table, .parquet or .csv, written as it grows; the figure goes next to it as "
        ".html (default: %(default)s)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="run again the rows already in the table (by default they are kept and skipped)",
    )
    p.set_defaults(func=_cmd_sweep)
