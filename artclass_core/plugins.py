"""The plugin manager: loads the ``artclass`` entry points and collects the registered classes.

``ARTCLASS_PLUGINS`` controls which entry points load, like pytest's ``-p``: a comma-separated list
of entry-point names loads only those; ``no:NAME`` entries block a name and load the rest.
A plugin that fails to import is reported in :attr:`Registry.failures`, not fatal.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from importlib.metadata import entry_points

import pluggy

from . import hookspecs
from .errors import PluginError
from .interfaces import KINDS
from .params import Params

ENTRY_POINT_GROUP = "artclass"


@dataclass
class PluginInfo:
    kind: str
    name: str
    cls: type
    source: str  # the pluggy plugin (module) that registered it, and its distribution


@dataclass
class Registry:
    """Every registered plugin class, by kind and name."""

    pm: pluggy.PluginManager
    plugins: dict[str, dict[str, PluginInfo]] = field(default_factory=lambda: {k: {} for k in KINDS})
    failures: dict[str, str] = field(default_factory=dict)  # entry point -> error

    def names(self, kind: str) -> list[str]:
        return sorted(self.plugins[kind])

    def get(self, kind: str, name: str) -> type:
        try:
            return self.plugins[kind][name].cls
        except KeyError:
            known = ", ".join(self.names(kind)) or "none"
            raise PluginError(f"unknown {kind} {name!r}; registered: {known}") from None

    def create(self, kind: str, name: str, params: Params | None = None):
        return self.get(kind, name)(params)

    def add_parser_commands(self, subparsers) -> None:
        self.pm.hook.register_commands(subparsers=subparsers)


def _allowed(name: str, setting: str | None) -> bool:
    if not setting:
        return True
    items = [s.strip() for s in setting.split(",") if s.strip()]
    if f"no:{name}" in items:
        return False
    wanted = [s for s in items if not s.startswith("no:")]
    return not wanted or name in wanted


def load_registry(*, extra_plugins: tuple = (), entry_point_setting: str | None = None) -> Registry:
    """Build a :class:`Registry` from the installed entry points plus ``extra_plugins`` (modules/objects).

    Parameters
    ----------
    extra_plugins : plugin objects registered directly (e.g. from a notebook or a test)
    entry_point_setting : overrides the ``ARTCLASS_PLUGINS`` environment variable
    """
    pm = pluggy.PluginManager(ENTRY_POINT_GROUP)
    pm.add_hookspecs(hookspecs)
    registry = Registry(pm)
    setting = os.environ.get("ARTCLASS_PLUGINS") if entry_point_setting is None else entry_point_setting
    sources: dict[str, str] = {}
    for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        if not _allowed(ep.name, setting) or pm.has_plugin(ep.name):
            continue
        try:
            pm.register(ep.load(), name=ep.name)
        except Exception as exc:  # a broken third-party plugin must not take the tool down
            registry.failures[ep.name] = f"{type(exc).__name__}: {exc}"
            continue
        sources[ep.name] = f"{ep.value} ({ep.dist.name if ep.dist else 'unknown distribution'})"
    for obj in extra_plugins:
        name = pm.register(obj)
        sources[name] = getattr(obj, "__name__", name)

    for kind, (hook, method) in KINDS.items():
        for impl in getattr(pm.hook, hook).get_hookimpls():

            def register(cls, _impl=impl, _kind=kind, _method=method):
                _check_class(cls, _kind, _method, impl_name=_impl.plugin_name)
                known = registry.plugins[_kind].get(cls.name)
                if known is not None and known.cls is not cls:
                    raise PluginError(
                        f"{_kind} name {cls.name!r} is registered twice: by {known.source} "
                        f"and by {sources.get(_impl.plugin_name, _impl.plugin_name)}"
                    )
                registry.plugins[_kind][cls.name] = PluginInfo(
                    _kind, cls.name, cls, sources.get(_impl.plugin_name, _impl.plugin_name)
                )

            impl.function(register=register)
    return registry


def _check_class(cls, kind: str, method: str, *, impl_name: str) -> None:
    where = f"{kind} {getattr(cls, '__name__', cls)!r} from plugin {impl_name!r}"
    name = getattr(cls, "name", "")
    if not (isinstance(name, str) and name and name == name.lower() and name.replace("_", "").isalnum()):
        raise PluginError(f"{where}: `name` must be a lowercase identifier, got {name!r}")
    if not isinstance(getattr(cls, "description", None), str) or not cls.description:
        raise PluginError(f"{where}: `description` must be a one-line string")
    params = getattr(cls, "Params", None)
    if not (
        isinstance(params, type)
        and issubclass(params, Params)
        and dataclasses.is_dataclass(params)
        and params.__dataclass_params__.frozen
    ):
        raise PluginError(f"{where}: `Params` must be a frozen dataclass subclassing artclass_core.Params")
    if not callable(getattr(cls, method, None)):
        raise PluginError(f"{where}: missing method `{method}`")
