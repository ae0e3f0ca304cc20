"""The ``artclass sample`` command (registered by the core as the entry point
``artclass_plugins.synth.commands``)."""

from __future__ import annotations

import sys
import time

from artclass_core import hookimpl

from . import PRESETS, generate_set


def _cmd_sample(args) -> int:
    t0 = time.perf_counter()
    try:
        paths = generate_set(args.out, preset=args.preset, seed=args.seed, overwrite=args.overwrite)
    except (FileExistsError, ValueError) as exc:
        print(f"artclass sample: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {len(paths)} sequences to {args.out} in {time.perf_counter() - t0:.1f} s")
    return 0


@hookimpl
def register_commands(subparsers):
    p = subparsers.add_parser(
        "sample",
        help="write synthetic RGB-D sequences with ground truth",
        description="Render a preset set of synthetic RGB-D sequences (native folder format).",
    )
    p.add_argument("out", help="output folder (one sub-folder per sequence)")
    p.add_argument(
        "--preset",
        choices=sorted(PRESETS),
        default="sample",
        help="; ".join(f"{k}: {v}" for k, v in PRESETS.items()),
    )
    p.add_argument("--seed", type=int, default=0, help="set seed (default 0)")
    p.add_argument("--overwrite", action="store_true", help="replace existing sequences of the same names")
    p.set_defaults(func=_cmd_sample)
