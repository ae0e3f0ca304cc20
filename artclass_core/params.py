"""Parameter dataclasses and their metadata.

Every tunable value is declared once, as a field of a frozen dataclass, with its paper symbol, unit,
bounds, default and help text in ``dataclasses.field(metadata=...)``. The CLI, the app's sliders and
the reference docs are all built from that metadata. ``None`` means "auto": the value is derived from
the data as the paper describes (the derivation is given in ``auto``).
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field
from typing import Any, get_type_hints

from .errors import ParamError

#: The unit of a pure number (SI writes the unit of a dimensionless quantity as 1).
DIMENSIONLESS = "1"


def param(
    default: Any,
    *,
    help: str,
    symbol: str = "",
    unit: str = "",
    bounds: tuple = (None, None),
    auto: str = "",
    choices: tuple = (),
) -> Any:
    """Declare a parameter field.

    Parameters
    ----------
    default : the default value (``None`` for "auto", which then needs ``auto``)
    help : one sentence saying what the parameter does, physically
    symbol : the paper's symbol (``v``, ``r``, ``s``, ``x``, ``q_bar``, ``t_bar``, ``k``, ``w``, ``alpha``)
    unit : SI unit (``m``, ``rad``), ``frames``, ``fraction`` ..., or ``"1"`` (:data:`DIMENSIONLESS`) for a
        pure number; a numeric parameter always names one (``""`` is for strings and booleans)
    bounds : inclusive (low, high); ``None`` for an open end
    auto : how the value is derived when left as ``None``
    choices : allowed values of a string parameter
    """
    return field(
        default=default,
        metadata=dict(help=help, symbol=symbol, unit=unit, bounds=bounds, auto=auto, choices=tuple(choices)),
    )


@dataclass(frozen=True)
class Params:
    """Base of every parameter dataclass: validates bounds on construction."""

    def __post_init__(self):
        for spec in describe(type(self)):
            value = getattr(self, spec.name)
            if value is None:
                if not spec.auto:
                    raise ParamError(f"parameter {spec.name} has no value and no automatic default")
                continue
            if spec.choices and value not in spec.choices:
                raise ParamError(
                    f"parameter {spec.label} = {value!r} is not one of {', '.join(map(str, spec.choices))}"
                )
            low, high = spec.bounds
            if (low is not None and value < low) or (high is not None and value > high):
                raise ParamError(
                    f"parameter {spec.label} = {value} is out of bounds "
                    f"[{'-inf' if low is None else low}, {'inf' if high is None else high}]"
                )


@dataclass(frozen=True)
class ParamSpec:
    """Metadata of one parameter field, as the UI, CLI and docs see it."""

    name: str
    type: type
    default: Any
    help: str
    symbol: str
    unit: str
    bounds: tuple
    auto: str
    choices: tuple

    @property
    def label(self) -> str:
        return f"{self.name} ({self.symbol})" if self.symbol and self.symbol != self.name else self.name


def describe(params_cls: type) -> list[ParamSpec]:
    """The :class:`ParamSpec` of every field of a parameter dataclass, in declaration order."""
    return list(_specs(params_cls))


@functools.lru_cache(maxsize=256)
def _specs(params_cls: type) -> tuple[ParamSpec, ...]:
    """:func:`describe`, worked out once per class (every construction of a Params validates with it)."""
    hints = get_type_hints(params_cls)
    specs = []
    for f in dataclasses.fields(params_cls):
        md = f.metadata
        kind = hints[f.name]
        base = next(
            (t for t in (bool, int, float, str) if t == kind or t in getattr(kind, "__args__", ())), str
        )
        specs.append(
            ParamSpec(
                f.name,
                base,
                f.default,
                md.get("help", ""),
                md.get("symbol", ""),
                md.get("unit", ""),
                md.get("bounds", (None, None)),
                md.get("auto", ""),
                md.get("choices", ()),
            )
        )
    return tuple(specs)


def parse_value(spec: ParamSpec, text: str) -> Any:
    """Parse a command-line value (``"auto"`` gives ``None`` where the parameter has an automatic value)."""
    if spec.auto and text.strip().lower() in ("auto", "none"):
        return None
    try:
        if spec.type is bool:
            if text.lower() not in ("1", "0", "true", "false", "yes", "no", "on", "off"):
                raise ValueError
            return text.lower() in ("1", "true", "yes", "on")
        return spec.type(text)
    except ValueError:
        raise ParamError(f"parameter {spec.label}: {text!r} is not a valid {spec.type.__name__}") from None


def as_dict(params: Params) -> dict[str, Any]:
    """Plain ``{name: value}`` of a parameter dataclass (JSON-ready)."""
    return {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}


@dataclass(frozen=True)
class PipelineParams(Params):
    """Parameters of the pipeline itself, shared by every choice of plugins."""

    k: int = param(
        5,
        symbol="k",
        unit="frames",
        bounds=(1, 1000),
        help="Frame skip: frame i is compared with frame i + k.",
    )
    w: int = param(
        3,
        symbol="w",
        unit="pairs",
        bounds=(1, 1001),
        help="Window of the moving max-count filter over the pair decisions (1 = no filtering). "
        "The paper leaves w open; 3 removes isolated single-pair errors.",
    )
    video_joints: bool = param(
        True,
        help="A video is articulated only when a part tracked across its pairs moves continuously "
        "about a joint (prismatic, revolute or screw) over the whole video; false: whenever an AM "
        "pair survives the max-count filter (the paper's rule).",
    )
    slow_factor: int = param(
        2,
        unit="1",
        bounds=(1, 100),
        help="A pair (i, i + k) that shows no motion is compared again as (i, i + slow_factor k), "
        "when the sequence is that long: a slow motion, below the noise over k frames, shows "
        "over more. 1 = never (the paper's pairs).",
    )
    cell_size_m: float | None = param(
        None,
        symbol="x",
        unit="m",
        bounds=(1e-4, 10.0),
        auto="1/5 of the largest distance between points of the pair",
        help="Edge of the coarse grid cells that are registered one by one.",
    )
    alpha: float = param(
        0.3,
        symbol="alpha",
        unit="fraction",
        bounds=(0.0, 1.0),
        help="Fraction of a pair's occupied cells that must register; below it the pair is "
        "skipped as unreliable. The paper leaves alpha open.",
    )
    min_fitness: float = param(
        0.3,
        unit="fraction",
        bounds=(0.0, 1.0),
        help="A cell whose ICP fitness (share of source points with a correspondence) "
        "is below this is skipped as a low-confidence match.",
    )
    prealign: bool = param(
        True,
        help="Move the source cloud by the whole-object motion (found with the chosen "
        "registrar, coarse to fine) before the per-cell ICP, so cells of a carried "
        "object register; false = the paper's per-cell ICP from the identity.",
    )
    min_cell_points: int = param(
        8,
        unit="points",
        bounds=(3, 100000),
        help="A cell with fewer points than this in either frame is not registered.",
    )
