"""Named sets of sequences: ``sample``, ``smoke``, the benchmark at three camera resolutions, and the
randomised benchmark ``benchmark-wild``."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

from .generate import GENERATOR_VERSION, HANDS, TEXTURES, generate_sequence
from .motion import MOTIONS
from .objects import OBJECTS
from .wild import DRAWN
from .write import write_json

__all__ = ["PRESETS", "SequencePlan", "generate_set", "preset_plans"]


@dataclass(frozen=True)
class SequencePlan:
    """One sequence of a preset (its seed is derived from the set's seed)."""

    name: str
    object_name: str
    motion: str
    noise: str
    n_frames: int
    width: int
    height: int
    texture: str = "textured"
    hand: str = "none"
    wild: bool = False

    def __post_init__(self):
        if self.object_name not in OBJECTS:
            raise ValueError(f"plan {self.name!r}: unknown object {self.object_name!r}")
        if self.motion not in MOTIONS:
            raise ValueError(f"plan {self.name!r}: unknown motion {self.motion!r}")
        drawn = (DRAWN,) if self.wild else ()
        if self.texture not in TEXTURES + drawn:
            raise ValueError(f"plan {self.name!r}: unknown texture {self.texture!r}")
        if self.hand not in HANDS + drawn:
            raise ValueError(f"plan {self.name!r}: unknown hand {self.hand!r}")


def _sample() -> list[SequencePlan]:
    kw = dict(noise="low", n_frames=16, width=320, height=240)
    return [
        SequencePlan("laptop_articulate", "laptop", "articulate", **kw),
        SequencePlan("drawer_carry_articulate", "drawer", "carry_articulate", **kw),
        SequencePlan("mug_carry", "mug", "carry", **kw),
        SequencePlan("cereal_box_static", "cereal_box", "static", **kw),
    ]


_ARTICULATED = ("laptop", "drawer", "box_lid", "pliers", "globe", "microwave", "matchbox")
_CARRIED_ARTICULATING = ("laptop", "drawer", "box_lid", "pliers", "matchbox")
_RIGID = ("mug", "cereal_box", "can", "bottle", "drill", "banana")
_CARRIED_FIXED_JOINT = (("laptop", "low"), ("pliers", "high"), ("box_lid", "low"), ("matchbox", "high"))
_STATIC = (
    ("mug", "low"),
    ("drill", "high"),
    ("cereal_box", "high"),
    ("bottle", "low"),
    ("laptop", "low"),
    ("microwave", "high"),
    ("globe", "low"),
    ("drawer", "high"),
)


# Objects added with hands and kinematic chains (appended, so that the first 48 sequences keep their
# names and seeds).
_NEW_ARTICULATED = ("scissors", "monitor", "desk_lamp", "folding_ruler")
_NEW_RIGID = (("book", "low"), ("book", "high"), ("plate", "high"), ("ruler", "low"))
_NEW_STATIC = (
    ("book", "high"),
    ("plate", "low"),
    ("scissors", "high"),
    ("desk_lamp", "low"),
    ("monitor", "high"),
    ("ruler", "low"),
    ("folding_ruler", "high"),
    ("slide_case", "low"),
)
#: Who handles sequence i: HOLDER_CYCLE[i % 4] (three in four are handled); every third is plain.
HOLDER_CYCLE = ("hand", "gripper", "hand", "none")


def _benchmark(width: int = 320, height: int = 240) -> list[SequencePlan]:
    rows = []
    for obj in _ARTICULATED:
        for noise in ("low", "high"):
            rows.append((obj, "articulate", noise))
    for obj in _CARRIED_ARTICULATING:
        for noise in ("low", "high"):
            rows.append((obj, "carry_articulate", noise))
    for obj in _RIGID:
        for noise in ("low", "high"):
            rows.append((obj, "carry", noise))
    rows += [(obj, "carry", noise) for obj, noise in _CARRIED_FIXED_JOINT]
    rows += [(obj, "static", noise) for obj, noise in _STATIC]
    for obj in _NEW_ARTICULATED:
        for noise in ("low", "high"):
            rows.append((obj, "articulate", noise))
    rows += [("slide_case", "articulate", "high"), ("slide_case", "carry_articulate", "low")]
    rows += [(obj, "carry", noise) for obj, noise in _NEW_RIGID]
    rows += [(obj, "static", noise) for obj, noise in _NEW_STATIC]
    return [
        SequencePlan(
            f"{i:02d}_{obj}_{motion}_{noise}",
            obj,
            motion,
            noise,
            24,
            width,
            height,
            texture="plain" if i % 3 == 2 else "textured",
            hand=HOLDER_CYCLE[i % 4],
        )
        for i, (obj, motion, noise) in enumerate(rows)
    ]


def _smoke() -> list[SequencePlan]:
    kw = dict(noise="low", n_frames=8, width=160, height=120)
    return [
        SequencePlan("laptop_articulate", "laptop", "articulate", **kw),
        SequencePlan("drawer_carry_articulate", "drawer", "carry_articulate", **kw),
        SequencePlan("mug_carry", "mug", "carry", **kw),
        SequencePlan("box_static", "cereal_box", "static", **kw),
    ]


# The randomised benchmark: these objects and motions; sensor, camera, holders, speeds, surface and
# lighting drawn from each sequence's seed.
_WILD_ROWS = (
    [(obj, "articulate") for obj in _ARTICULATED + _NEW_ARTICULATED + ("slide_case",) for _ in range(2)]
    + [
        (obj, "carry_articulate")
        for obj in _CARRIED_ARTICULATING
        + ("scissors", "slide_case", "folding_ruler", "laptop", "pliers", "box_lid")
    ]
    + [(obj, "carry") for obj in ("cereal_box", "drill", "book", "laptop", "pliers", "box_lid", "banana")]
    + [(obj, "lift") for obj in ("kettle", "mug", "cereal_box")]
    + [(obj, "spin") for obj in ("mug", "can", "bottle", "kettle", "plate")]
    + [(obj, "slide") for obj in ("book", "plate", "ruler")]
    + [
        (obj, "static")
        for obj in (
            "mug",
            "drill",
            "cereal_box",
            "bottle",
            "laptop",
            "microwave",
            "globe",
            "drawer",
            "book",
            "plate",
            "scissors",
            "desk_lamp",
            "monitor",
            "folding_ruler",
            "slide_case",
            "kettle",
            "can",
        )
    ]
)


def _wild(width: int = 640, height: int = 480) -> list[SequencePlan]:
    return [
        SequencePlan(
            f"{i:02d}_{obj}_{motion}", obj, motion, DRAWN, 24, width, height, DRAWN, DRAWN, wild=True
        )
        for i, (obj, motion) in enumerate(_WILD_ROWS)
    ]


#: Preset name -> one-line description.
PRESETS: dict[str, str] = {
    "sample": "4 sequences, 320x240, 16 frames, low noise: what sample_data/ holds",
    "benchmark": "70 sequences, 320x240, 24 frames, 21 objects, low and high noise, three in four "
    "handled by a hand or gripper, one in three untextured: 34 articulated, 20 rigid, "
    "16 static",
    "benchmark-vga": "the benchmark at 640x480, the resolution of the Kinect / RealSense recordings "
    "of YCB-Video and RBO",
    "benchmark-rs": "the benchmark at 848x480 with a RealSense-like camera (fx = 615)",
    "smoke": "4 tiny sequences, 160x120, 8 frames, for tests",
    "benchmark-wild": "70 sequences, 640x480, 24 frames (35 articulated, 18 rigid, 17 static; 22 objects, "
    "spins, slides, lifts off a stand, flips of up to 180 degrees in 12 frames) with everything else drawn "
    "from each sequence's seed: a structured-light sensor with a depth bias field or a time-of-flight one, "
    "intrinsics stated a few percent off, colour 0-2 px off depth, lighting, and no holder, one or two hands "
    "(any sleeve, glove, skin) or grippers of any colour, grasping, resting or passing",
}
_PLANS = {
    "sample": _sample,
    "benchmark": _benchmark,
    "benchmark-vga": lambda: _benchmark(640, 480),
    "benchmark-rs": lambda: _benchmark(848, 480),
    "smoke": _smoke,
    "benchmark-wild": _wild,
}


def preset_plans(preset: str) -> list[SequencePlan]:
    """The sequences of ``preset``, in order."""
    if preset not in _PLANS:
        raise ValueError(f"preset={preset!r} is not one of {sorted(_PLANS)}")
    return _PLANS[preset]()


def generate_set(out_root: str | Path, *, preset: str, seed: int = 0, overwrite: bool = False) -> list[Path]:
    """Generate every sequence of a preset into ``out_root/<name>/``.

    Parameters
    ----------
    out_root : str or Path
        Created if missing. Files in it other than the preset's sequence
        folders and ``index.json`` are left alone.
    preset : {"sample", "smoke", "benchmark", "benchmark-vga", "benchmark-rs", "benchmark-wild"}
    seed : int
        Set seed; sequence ``i`` gets seed ``seed * 1000 + i`` (recorded in its meta.json).
    overwrite : bool
        Replace existing sequences of the same names (otherwise a non-empty
        sequence folder or an existing ``index.json`` is refused).

    Returns
    -------
    list of Path
        The sequence folders, in preset order. ``out_root/index.json`` lists them.
    """
    plans = preset_plans(preset)
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"seed={seed!r} must be a non-negative integer")
    root = Path(out_root)
    root.mkdir(parents=True, exist_ok=True)
    index_path = root / "index.json"
    if index_path.exists() and not overwrite:
        raise FileExistsError(
            f"{index_path} exists; refusing to overwrite it (pass overwrite=True or --overwrite)"
        )
    # Refuse before writing anything, not half-way through the set.
    if not overwrite:
        for plan in plans:
            d = root / plan.name
            if d.exists() and (not d.is_dir() or any(d.iterdir())):
                raise FileExistsError(
                    f"{d} is not empty; refusing to overwrite it (pass overwrite=True or --overwrite)"
                )
    out, entries = [], []
    for i, plan in enumerate(plans):
        seq_seed = seed * 1000 + i
        p = generate_sequence(
            root / plan.name,
            object_name=plan.object_name,
            motion=plan.motion,
            noise=plan.noise,
            n_frames=plan.n_frames,
            seed=seq_seed,
            width=plan.width,
            height=plan.height,
            texture=plan.texture,
            hand=plan.hand,
            wild=plan.wild,
            overwrite=overwrite,
        )
        out.append(p)
        entry = asdict(plan)
        if plan.wild:  # what was drawn
            meta = json.loads((p / "meta.json").read_text())
            entry.update(noise=meta["noise"], texture=meta["texture"], hand=meta["hand"])
        entry.update(
            seed=seq_seed, label=MOTIONS[plan.motion].label, joint_type=OBJECTS[plan.object_name].joint_type
        )
        entries.append(entry)
    write_json(
        index_path,
        {
            "preset": preset,
            "seed": seed,
            "generator": f"artclass synth {GENERATOR_VERSION}",
            "sequences": entries,
        },
    )
    return out


def read_index(out_root: str | Path) -> dict:
    """Read ``out_root/index.json`` written by ``generate_set``."""
    return json.loads((Path(out_root) / "index.json").read_text())
