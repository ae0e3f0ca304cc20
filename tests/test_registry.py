"""The plugin registry: entry points, the allow/block list, failures, checks on registered classes."""

from __future__ import annotations

import importlib.metadata
import types
from dataclasses import dataclass

import numpy as np
import pytest

from artclass_core import (
    Config,
    DecisionRule,
    Params,
    Pipeline,
    PluginError,
    RuleDecision,
    Segmenter,
    hookimpl,
    load_registry,
    param,
)
from artclass_core import plugins as plugins_module
from artclass_core.cli import build_parser
from artclass_core.plugins import ENTRY_POINT_GROUP

from conftest import make_sequence

BUILTIN_ENTRY_POINTS = {
    "readers",
    "segmenters",
    "preprocessors",
    "registrars",
    "rules",
    "joints",
    "parts",
    "sweep",
}


def plugin_module(name: str, **hooks) -> types.ModuleType:
    """A module-like plugin object carrying the given hook implementations."""
    mod = types.ModuleType(name)
    for hook, function in hooks.items():
        setattr(mod, hook, hookimpl(function))
    return mod


def segmenter_class(name: str, *, frozen: bool = True, description: str = "a test segmenter"):
    if frozen:

        @dataclass(frozen=True)
        class P(Params):
            level: float = param(0.5, unit="1", bounds=(0.0, 1.0), help="a level")
    else:  # a dataclass cannot be a non-frozen subclass of the frozen Params: a plain mutable one

        @dataclass
        class P:
            level: float = 0.5

    class Seg(Segmenter):
        Params = P

        def segment(self, frame, *, sequence):
            return frame.depth_m > 0

    Seg.name, Seg.description = name, description
    return Seg


def registering(*classes):
    def register_all(register):
        for cls in classes:
            register(cls)

    return register_all


# -- entry points -------------------------------------------------------------------------------------


def test_builtins_come_from_entry_points():
    names = {ep.name for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}
    assert BUILTIN_ENTRY_POINTS <= names
    registry = load_registry(entry_point_setting="")
    assert not registry.failures, registry.failures
    for kind in (
        "reader",
        "segmenter",
        "preprocessor",
        "registrar",
        "rule",
        "joint_estimator",
        "part_finder",
    ):
        assert registry.names(kind), f"no {kind} registered"
        for info in registry.plugins[kind].values():
            assert info.kind == kind and info.cls.name == info.name and info.source


# -- ARTCLASS_PLUGINS -----------------------------------------------------------------------------------


def test_allow_list_loads_only_those(monkeypatch):
    monkeypatch.setenv("ARTCLASS_PLUGINS", "segmenters, rules")
    registry = load_registry()
    assert registry.names("reader") == [] and registry.names("registrar") == []
    assert "mask" in registry.names("segmenter") and "paper" in registry.names("rule")


def test_block_list_loads_the_rest(monkeypatch):
    monkeypatch.setenv("ARTCLASS_PLUGINS", "no:rules")
    registry = load_registry()
    assert registry.names("rule") == []
    assert "folder" in registry.names("reader") and "paper" in registry.names("preprocessor")
    with pytest.raises(PluginError, match="unknown rule 'paper'; registered: none"):
        registry.get("rule", "paper")


def test_setting_argument_overrides_the_environment(monkeypatch):
    monkeypatch.setenv("ARTCLASS_PLUGINS", "no:readers")
    assert load_registry(entry_point_setting="readers").names("segmenter") == []
    assert "folder" in load_registry(entry_point_setting="readers").names("reader")
    assert "folder" in load_registry(entry_point_setting="").names("reader"), "empty setting = everything"


# -- failures -----------------------------------------------------------------------------------------------


def test_a_plugin_that_fails_to_import_is_reported_not_fatal(monkeypatch):
    real = plugins_module.entry_points
    broken = importlib.metadata.EntryPoint(
        name="broken", value="artclass_no_such_module_xyz", group=ENTRY_POINT_GROUP
    )

    def with_broken(*, group):
        return [*real(group=group), broken]

    monkeypatch.setattr(plugins_module, "entry_points", with_broken)
    registry = load_registry(entry_point_setting="")
    assert set(registry.failures) == {"broken"}
    assert "ModuleNotFoundError" in registry.failures["broken"]
    assert "artclass_no_such_module_xyz" in registry.failures["broken"]
    assert "folder" in registry.names("reader"), "the other plugins still load"
    # and a blocked broken plugin is not even imported
    assert load_registry(entry_point_setting="no:broken").failures == {}


def test_cli_lists_the_failure(monkeypatch, capsys):
    from artclass_core.cli import main

    real = plugins_module.entry_points
    broken = importlib.metadata.EntryPoint(
        name="broken", value="artclass_no_such_module_xyz", group=ENTRY_POINT_GROUP
    )
    monkeypatch.setattr(plugins_module, "entry_points", lambda *, group: [*real(group=group), broken])
    assert main(["plugins"]) == 0
    assert "failed to load plugin 'broken'" in capsys.readouterr().out


def test_duplicate_names_fail_naming_both_plugins():
    a = plugin_module("first_plugin", register_segmenters=registering(segmenter_class("twin")))
    b = plugin_module("second_plugin", register_segmenters=registering(segmenter_class("twin")))
    with pytest.raises(PluginError) as err:
        load_registry(extra_plugins=(a, b), entry_point_setting="no:segmenters")
    message = str(err.value)
    assert "'twin'" in message and "first_plugin" in message and "second_plugin" in message


def test_duplicate_of_a_builtin_names_the_builtin():
    clash = plugin_module("clashing_plugin", register_segmenters=registering(segmenter_class("mask")))
    with pytest.raises(PluginError) as err:
        load_registry(extra_plugins=(clash,), entry_point_setting="")
    assert "clashing_plugin" in str(err.value) and "artclass_plugins.segmenters" in str(err.value)


@pytest.mark.parametrize(
    "cls, problem",
    [
        (segmenter_class("Bad Name"), "`name` must be a lowercase identifier, got 'Bad Name'"),
        (segmenter_class("UPPER"), "`name` must be a lowercase identifier"),
        (segmenter_class(""), "`name` must be a lowercase identifier"),
        (segmenter_class("ok_name", frozen=False), "`Params` must be a frozen dataclass"),
        (segmenter_class("ok_name", description=""), "`description` must be a one-line string"),
    ],
    ids=["space", "upper", "empty", "not-frozen", "no-description"],
)
def test_badly_formed_classes_are_rejected(cls, problem):
    bad = plugin_module("bad_plugin", register_segmenters=registering(cls))
    with pytest.raises(PluginError) as err:
        load_registry(extra_plugins=(bad,), entry_point_setting="no:segmenters")
    assert problem in str(err.value)
    assert "bad_plugin" in str(err.value), "the message names the plugin"


def test_missing_method_is_rejected():
    class NoMethod:
        name, description, Params = "no_method", "lacks segment()", Params

    bad = plugin_module("lazy_plugin", register_segmenters=registering(NoMethod))
    with pytest.raises(PluginError, match="missing method `segment`"):
        load_registry(extra_plugins=(bad,), entry_point_setting="")


def test_params_must_subclass_params():
    @dataclass(frozen=True)
    class Plain:
        level: float = 0.5

    cls = segmenter_class("plain_params")
    cls.Params = Plain
    bad = plugin_module("plain_plugin", register_segmenters=registering(cls))
    with pytest.raises(PluginError, match="subclassing artclass_core.Params"):
        load_registry(extra_plugins=(bad,), entry_point_setting="")


# -- extra plugins --------------------------------------------------------------------------------------------


class AlwaysRM(DecisionRule):
    name = "always_rm"
    description = "calls every pair a rigid motion (test only)"
    Params = Params

    def decide(self, cells, *, source, target):
        clusters = [0 if c.matched else None for c in cells]
        return RuleDecision("RM", clusters, ["everything"], reason="always")


def test_extra_plugin_registers_and_runs():
    extra = plugin_module("test_rules", register_rules=registering(AlwaysRM))
    registry = load_registry(extra_plugins=(extra,), entry_point_setting="")
    assert registry.get("rule", "always_rm") is AlwaysRM
    assert registry.plugins["rule"]["always_rm"].source == "test_rules"
    assert "paper" in registry.names("rule"), "the built-ins stay"
    result = Pipeline(registry, Config(rule="always_rm").with_overrides(registry, {"k": "2"})).run(
        make_sequence("hinge", n_frames=5)
    )
    decided = [p.decision for p in result.pairs if p.decision != "skipped"]
    assert decided and set(decided) == {"RM"} and result.label == "rigid"
    assert result.plugins["rule"] == "always_rm"


def test_extra_plugin_object_with_methods():
    """A plugin may be any object whose attributes are hook implementations (here a class instance)."""

    class RulePlugin:
        @hookimpl
        def register_rules(self, register):
            register(AlwaysRM)

    registry = load_registry(extra_plugins=(RulePlugin(),), entry_point_setting="no:rules")
    assert registry.names("rule") == ["always_rm"]


def test_extra_plugin_adds_a_command(capsys):
    def register_commands(subparsers):
        p = subparsers.add_parser("hello", help="say hello")
        p.set_defaults(func=lambda args: print("hello from a plugin") or 0)

    registry = load_registry(
        extra_plugins=(plugin_module("hello_plugin", register_commands=register_commands),),
        entry_point_setting="",
    )
    args = build_parser(registry).parse_args(["hello"])
    assert args.func(args) == 0
    assert capsys.readouterr().out == "hello from a plugin\n"


def test_registry_create_uses_params():
    registry = load_registry(entry_point_setting="")
    cls = registry.get("segmenter", "mask")
    plugin = registry.create("segmenter", "mask", cls.Params(erode_px=2))
    assert plugin.params.erode_px == 2
    assert registry.create("segmenter", "mask").params == cls.Params()
    mask = plugin.segment(
        make_sequence("static", n_frames=1)[0], sequence=make_sequence("static", n_frames=1)
    )
    assert mask.dtype == bool and np.count_nonzero(mask) > 0
