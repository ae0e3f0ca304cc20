"""artclass core: data types, parameters, hook specifications and the pipeline.

Plugins import what they need from here::

    from artclass_core import hookimpl, Params, param, Registration
"""

from .errors import ArtclassError, InputError, ParamError, PluginError
from .hookspecs import hookimpl, hookspec
from .interfaces import (
    DecisionRule,
    PairRegistrar,
    Plugin,
    Preprocessor,
    Reader,
    Registrar,
    RuleDecision,
    Segmenter,
)
from .params import Params, ParamSpec, PipelineParams, describe, param
from .pipeline import Config, Pipeline, StageCache, fractions, max_count_filter, sequence_label
from .plugins import Registry, load_registry
from .sequences import find_sequences, open_sequences
from .types import (
    CellMotion,
    Cloud,
    Frame,
    FrameResult,
    Intrinsics,
    Motion,
    MotionEvidence,
    PairResult,
    Registration,
    RunResult,
    Sequence,
    View,
)

__all__ = [
    "ArtclassError",
    "InputError",
    "ParamError",
    "PluginError",
    "hookimpl",
    "hookspec",
    "DecisionRule",
    "PairRegistrar",
    "Plugin",
    "Preprocessor",
    "Reader",
    "Registrar",
    "RuleDecision",
    "Segmenter",
    "Params",
    "ParamSpec",
    "PipelineParams",
    "describe",
    "param",
    "Config",
    "Pipeline",
    "StageCache",
    "fractions",
    "max_count_filter",
    "sequence_label",
    "Registry",
    "load_registry",
    "open_sequences",
    "find_sequences",
    "CellMotion",
    "Cloud",
    "Frame",
    "FrameResult",
    "Intrinsics",
    "Motion",
    "MotionEvidence",
    "PairResult",
    "Registration",
    "RunResult",
    "Sequence",
    "View",
]
