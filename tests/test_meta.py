"""Meta-tests: every hook is tested and documented; every parameter is fully described.

Like datasette's ``test_plugin_hooks_have_tests`` / ``test_plugin_hooks_are_documented``: adding a hook
or a parameter without its test, documentation or metadata fails here, with a message saying what is
missing.
"""

from __future__ import annotations

import re
from importlib.metadata import distribution
from pathlib import Path

import pytest

from artclass_core import PipelineParams, describe, hookspecs, load_registry
from artclass_core.params import DIMENSIONLESS

ROOT = Path(__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent
GUIDE = ROOT / "docs" / "plugin-guide.md"
PAPER_SYMBOLS = ("v", "r", "s", "x", "q_bar", "t_bar", "k", "w", "alpha")

HOOKS = sorted(name for name, fn in vars(hookspecs).items() if hasattr(fn, "artclass_spec"))


def _builtin_params() -> list[tuple[str, type]]:
    """(where, Params class) for the pipeline and every plugin the artclass distribution registers."""
    names = sorted(ep.name for ep in distribution("artclass").entry_points if ep.group == "artclass")
    registry = load_registry(entry_point_setting=",".join(names))
    assert not registry.failures, f"built-in plugins failed to load: {registry.failures}"
    out = [("pipeline", PipelineParams)]
    for kind, plugins in registry.plugins.items():
        out += [(f"{kind} {name!r}", info.cls.Params) for name, info in sorted(plugins.items())]
    return out


PARAMS = _builtin_params()
SPECS = [(where, cls, spec) for where, cls in PARAMS for spec in describe(cls)]


def test_hooks_are_found():
    assert {
        "register_readers",
        "register_segmenters",
        "register_preprocessors",
        "register_registrars",
        "register_rules",
        "register_joint_estimators",
        "register_part_finders",
        "register_commands",
    } <= set(HOOKS)


@pytest.mark.parametrize("hook", HOOKS)
def test_hook_has_a_test(hook):
    """Some test module other than this one names the hook (e.g. ``test_hook_register_rules``)."""
    users = [
        p.name
        for p in TESTS.glob("test_*.py")
        if p.name != Path(__file__).name and re.search(rf"\b{hook}\b", p.read_text())
    ]
    assert users, f"no test exercises the hook {hook}: add e.g. test_hook_{hook} under tests/"


def _guide_sections() -> dict[str, str]:
    text = GUIDE.read_text()
    parts = re.split(r"^## ", text, flags=re.M)
    return {part.splitlines()[0]: part for part in parts[1:]}


@pytest.mark.parametrize("hook", HOOKS)
def test_hook_is_documented(hook):
    """docs/plugin-guide.md has a section per hook with its signature and an example implementation."""
    sections = {title: body for title, body in _guide_sections().items() if re.search(rf"\b{hook}\b", title)}
    assert sections, f"docs/plugin-guide.md has no '## ... {hook} ...' section"
    body = next(iter(sections.values()))
    assert re.search(rf"def {hook}\(", body), f"the {hook} section shows no example `def {hook}(...)`"
    assert "@hookimpl" in body, f"the {hook} section's example lacks @hookimpl"


def test_guide_documents_no_unknown_hook():
    """A hook renamed or removed in hookspecs.py must not live on in the guide."""
    titled = {m for title in _guide_sections() for m in re.findall(r"\bregister_\w+", title)}
    assert titled <= set(HOOKS), f"guide documents hooks that do not exist: {sorted(titled - set(HOOKS))}"


def test_parameters_are_collected():
    kinds = {where.split()[0] for where, _ in PARAMS}
    assert {
        "pipeline",
        "reader",
        "segmenter",
        "preprocessor",
        "registrar",
        "rule",
        "joint_estimator",
        "part_finder",
    } <= kinds
    assert len(SPECS) >= 15


@pytest.mark.parametrize("where,cls,spec", SPECS, ids=[f"{w}.{s.name}" for w, _, s in SPECS])
def test_parameter_is_described(where, cls, spec):
    name = f"{where} {cls.__name__}.{spec.name}"
    assert len(spec.help.strip()) >= 10, (
        f"{name}: help must be a sentence saying what the parameter does, got {spec.help!r}"
    )
    if spec.type in (int, float):
        assert spec.unit, (
            f"{name}: a numeric parameter needs a unit (metres 'm', 'rad', 'frames', ...) or "
            f"the dimensionless marker {DIMENSIONLESS!r}"
        )
        low, high = spec.bounds
        assert low is not None and high is not None, (
            f"{name}: a numeric parameter needs both bounds, got {spec.bounds}"
        )
        assert low <= high, f"{name}: bounds {spec.bounds} are reversed"
        if spec.default is not None:
            assert low <= spec.default <= high, f"{name}: default {spec.default} outside {spec.bounds}"
    if spec.default is None:
        assert spec.auto, f"{name}: default None needs `auto` saying how the value is derived"
    if spec.symbol:
        assert spec.symbol in PAPER_SYMBOLS, (
            f"{name}: symbol {spec.symbol!r} is not one of the paper's {PAPER_SYMBOLS}"
        )
    if spec.choices:
        assert spec.default is None or spec.default in spec.choices, f"{name}: default not among the choices"


def test_every_paper_symbol_is_a_parameter():
    """The paper's v, r, s, x, q_bar, t_bar, k, w and alpha are each exposed by some built-in parameter."""
    declared = {spec.symbol for _, _, spec in SPECS}
    assert set(PAPER_SYMBOLS) <= declared, (
        f"paper symbols without a parameter: {set(PAPER_SYMBOLS) - declared}"
    )
