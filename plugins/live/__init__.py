"""``artclass live``: classify a RealSense camera's frames as they arrive, or play a recording.

::

    artclass live                          # the first RealSense camera (pip install 'artclass[realsense]')
    artclass live --source REC.bag         # a recording, played frame by frame
    artclass live --record DIR             # also write the frames in the folder layout, to replay them

The mask comes from a mask-free segmenter (``depth_threshold`` unless ``--segmenter`` names
another). Each decided pair prints a line with the running decision; Ctrl-C stops and prints the
summary.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from artclass_core import ArtclassError, hookimpl, load_registry
from artclass_core.cli import _pipeline_options, config_from_args, reader_values

from .running import LiveSequence, LiveUpdate, StreamEnded, classify_live
from .sources import FrameSource, RealSenseSource, SequenceSource, open_source

__all__ = [
    "FrameSource",
    "LiveSequence",
    "LiveUpdate",
    "RealSenseSource",
    "SequenceSource",
    "StreamEnded",
    "classify_live",
    "open_source",
]


def running_line(update: LiveUpdate) -> str:
    """One line per decided pair: the pair, its decision and the decision so far."""
    pair, result = update.pair, update.result
    counts = " ".join(f"{d} {sum(p.decision == d for p in result.pairs)}" for d in ("AM", "RM", "NM"))
    return f"pair {pair.i:>5} -> {pair.j:<5} {pair.decision:<7}  so far: {result.label:<11} ({counts})"


def _cmd_live(args) -> int:
    registry = load_registry()
    try:
        config = config_from_args(registry, args)
        source = open_source(
            registry,
            args.source,
            player=args.player,
            reader=args.reader,
            reader_values=reader_values(registry, args),
        )
        last = None
        try:
            for last in classify_live(
                registry,
                source,
                config,
                record=Path(args.record) if args.record else None,
                max_frames=args.max_frames,
            ):
                if not args.json:
                    print(running_line(last), flush=True)
        except KeyboardInterrupt:
            print("stopped", file=sys.stderr)
        if last is None:
            raise ArtclassError(f"{source.path}: too few frames for a pair (k = {config.pipeline.k})")
    except ArtclassError as exc:
        print(f"artclass: error: {exc}", file=sys.stderr)
        return 2
    result = last.result
    if args.json:
        print(json.dumps(result.to_dict(cells=False)))
        return 0
    print(f"{result.sequence['name']}: {result.label}  ({last.n_frames} frames, {len(result.pairs)} pairs)")
    print(f"  after max-count filter (w={config.pipeline.w}): {' '.join(result.filtered)}")
    if args.record:
        print(f"  frames recorded in {args.record} (replay: artclass classify {args.record})")
    return 0


@hookimpl
def register_commands(subparsers):
    p = subparsers.add_parser(
        "live",
        help="classify a RealSense camera's frames as they arrive, or play a recording",
        description="Classify frames as they arrive and print the running decision after every pair. "
        "Without --source, the first RealSense camera connected (pip install 'artclass[realsense]').",
    )
    p.add_argument(
        "--source",
        metavar="PATH",
        help="a recording to play instead of a camera: a RealSense or ROS bag, a sequence folder",
    )
    p.add_argument(
        "--player",
        choices=("auto", "sdk", "reader"),
        default="auto",
        help="sdk: play a RealSense recording through the RealSense SDK, as the camera sent it; reader: "
        "play any recording through artclass's readers (what classify reads); auto (default): sdk for "
        "a RealSense recording when the SDK is installed",
    )
    p.add_argument(
        "--record", metavar="DIR", help="also write the frames to DIR (a new folder), in the folder layout"
    )
    p.add_argument("--max-frames", type=int, metavar="N", help="stop after N frames")
    _pipeline_options(p)
    p.set_defaults(func=_cmd_live, segmenter="depth_threshold")
