"""Synthetic RGB-D sequences of handled objects, with ground truth.

Renders articulated (one joint or a chain of joints), rigid and static scenes,
optionally handled by a hand or a gripper, on the CPU with Open3D's
``RaycastingScene``, adds structured-light sensor noise (with flying pixels and
1 mm depth steps) and writes artclass's native sequence folder (``meta.json``,
``truth.json``, ``rgb/``, ``depth/``, ``mask/``, ``hand/``, ``parts/``).
Everything is reproducible from a seed. With ``wild=True`` (the ``benchmark-wild``
preset) the seed also draws the sensor (structured light with a depth bias field,
or time of flight), the camera and the intrinsics stated for it, the colour-depth
offset, the lighting, the speeds, and the hands or grippers (``wild.py``).

Public API
----------
generate_sequence(out_dir, *, object_name, motion, noise, n_frames, seed, ..., wild=False)
generate_set(out_root, *, preset, seed=0, overwrite=False)
plan_sequence(...)  -- the same sequence in memory, frame by frame
OBJECTS, MOTIONS, NOISE_LEVELS, SENSOR_KINDS, PRESETS

The command ``artclass sample`` lives in ``artclass_plugins.synth.commands``
(registered by the core as an entry point); this package does not import the core.
"""

from .generate import (
    GENERATOR_VERSION,
    HANDS,
    TEXTURES,
    SynthFrame,
    SynthSequence,
    generate_sequence,
    plan_sequence,
)
from .motion import MOTIONS, MotionSpec
from .objects import OBJECTS, Joint, ObjectSpec, T_object_from_child, part_poses
from .presets import PRESETS, SequencePlan, generate_set, preset_plans, read_index
from .render import NOISE_LEVELS, Intrinsics, NoiseLevel
from .sensors import SENSOR_KINDS

__version__ = GENERATOR_VERSION

__all__ = [
    "GENERATOR_VERSION",
    "HANDS",
    "Intrinsics",
    "Joint",
    "MOTIONS",
    "MotionSpec",
    "NOISE_LEVELS",
    "NoiseLevel",
    "OBJECTS",
    "ObjectSpec",
    "PRESETS",
    "SENSOR_KINDS",
    "SequencePlan",
    "SynthFrame",
    "SynthSequence",
    "TEXTURES",
    "T_object_from_child",
    "generate_sequence",
    "generate_set",
    "part_poses",
    "plan_sequence",
    "preset_plans",
    "read_index",
]
