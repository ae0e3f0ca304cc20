"""The ``artclass export`` command: a sequence's parts and joints as a URDF."""

from __future__ import annotations

from pathlib import Path

from artclass_core import ArtclassError, hookimpl
from artclass_core.cli import _pipeline_options, classify_with_parts, config_from_args, open_one_sequence
from artclass_core.plugins import load_registry

from .urdf import model_from_articulation, write_urdf


def _cmd_export(args) -> int:
    registry = load_registry()
    seq = open_one_sequence(registry, args.path, reader=args.reader)
    out = Path(args.urdf).resolve()
    source = Path(seq.path).resolve()
    if out == source or source in out.parents:
        raise ArtclassError(
            f"{args.urdf}: will not write into the sequence's own folder {seq.path}; choose "
            f"another output folder"
        )
    result, articulation = classify_with_parts(
        registry, config_from_args(registry, args), seq, workers=args.workers, estimator=args.joint_estimator
    )
    if articulation is None:
        raise ArtclassError(
            f"rule {result.plugins['rule']!r} labels no points by motion, so it finds no parts: "
            f"use a rule that decides from motions (the default, dense)"
        )
    if any(len(p.points_m) < 4 for p in articulation.parts):
        raise ArtclassError(f"{seq.name}: a part has too few points for a mesh")
    path = write_urdf(model_from_articulation(articulation, name=_urdf_name(seq.name)), out)
    print(f"{seq.name}: {result.label}; {articulation.summary()}")
    print(f"wrote {path}")
    return 0


def _urdf_name(name: str) -> str:
    return "".join(c if c.isalnum() or c in "_-" else "_" for c in name)


@hookimpl
def register_commands(subparsers):
    p = subparsers.add_parser("export", help="classify one sequence and write its parts and joints as a URDF")
    p.add_argument("path", help="sequence folder (PATH#NAME picks one of several)")
    p.add_argument(
        "--urdf",
        required=True,
        metavar="OUT",
        help="folder to write OUT/<sequence>.urdf and OUT/meshes/<part>.ply into (not the sequence's own)",
    )
    p.add_argument("--joint-estimator", default="bic", help="joint estimator plugin (default: %(default)s)")
    _pipeline_options(p)
    p.set_defaults(func=_cmd_export)
