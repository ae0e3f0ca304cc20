"""The part finder's parameters."""

from __future__ import annotations

from dataclasses import dataclass

from artclass_core.params import Params, param


@dataclass(frozen=True)
class PartsParams(Params):
    min_overlap: float = param(
        0.25,
        unit="fraction",
        bounds=(0.05, 1.0),
        help="Two labelled regions (of two pairs, on one frame or neighbouring frames) may be "
        "one part when their intersection over union reaches this (the larger overlaps "
        "are merged first, and never two motions of one pair).",
    )
    link_sigmas: float = param(
        5.0,
        unit="sigma",
        bounds=(0.0, 100.0),
        help="Two moving regions that overlap (however little) are one part when their motions "
        "relative to the base move the regions' points alike, one scaled to the other, within this "
        "many depth-noise levels of the two pairs together (and each moves them by more than this "
        "many of its own pair's).",
    )
    min_pairs: int = param(
        2,
        unit="pairs",
        bounds=(1, 10_000),
        help="A moving part must be seen moving relative to the base in at least this many pairs.",
    )
    smoothness: float = param(
        1e-3,
        unit="1",
        bounds=(1e-9, 1.0),
        help="Weight of the smoothness term between neighbouring frames' states, relative to a "
        "pair difference: it only places the interleaved chains of pairs relative to each "
        "other.",
    )
    ambiguity_sigmas: float = param(
        3.0,
        unit="sigma",
        bounds=(0.0, 100.0),
        help="An object point takes the part whose motion puts it nearest a surface seen in the "
        "other frames when the next part's puts it farther by more than this many depth-noise "
        "levels; else the part whose motion changes its intensity least, when the next part's "
        "changes it more by over this many intensity-noise levels; otherwise the part of the "
        "nearest point that was decided.",
    )
    n_views: int = param(
        4,
        unit="frames",
        bounds=(0, 100),
        help="Each frame's part segmentation comes from the parts' motions: its points are looked up "
        "in this many other frames (those where the parts' motions move them most differently). "
        "0: each frame keeps the labels of one pair.",
    )
    min_seen: float = param(
        0.5,
        unit="fraction",
        bounds=(0.0, 1.0),
        help="A part's state is found in a frame no pair relates it in when at least this share of "
        "its points, moved there by its joint, lands on a surface seen in the frame.",
    )
    reach_sigmas: float = param(
        5.0,
        unit="sigma",
        bounds=(0.0, 100.0),
        help="A part's motion puts an object point on a surface seen in another frame when it lands "
        "within this many depth-noise levels of it (plus the spacing of the points) along the "
        "camera's ray.",
    )
