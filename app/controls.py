"""Sidebar controls built from the parameter metadata (``artclass_core.describe``).

A parameter is declared once, in its plugin's frozen ``Params`` dataclass; this module turns its
:class:`~artclass_core.ParamSpec` (symbol, unit, bounds, default, help, auto) into a widget, so a
new plugin's parameters appear without app changes. :func:`slider_options` and
:func:`format_value` are pure; :func:`params_widgets` draws the widgets.

Widget keys: ``cfg_p:<kind>:<plugin>:<name>`` for a value, ``cfg_auto:<kind>:<plugin>:<name>`` for
its "auto" checkbox (``kind`` is ``pipeline`` for the core's :class:`~artclass_core.PipelineParams`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import streamlit as st

from artclass_core import ParamSpec, describe

KEY_PREFIXES = ("cfg_p:", "cfg_auto:", "cfg_plugin:", "cfg_advanced")
SYMBOLS = {"q_bar": "q̄", "t_bar": "t̄", "alpha": "α"}
_MANTISSAS = (1.0, 1.2, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0)
_MAX_LINEAR = 400


def _nice(v: float) -> float:
    return float(f"{v:.6g}")


def _log_series(low: float, high: float) -> list[float]:
    out = []
    for e in range(math.floor(math.log10(low)) - 1, math.ceil(math.log10(high)) + 1):
        for m in _MANTISSAS:
            v = _nice(m * 10.0**e)
            if low <= v <= high:
                out.append(v)
    return out


def widget_kind(spec: ParamSpec) -> str:
    """``checkbox``, ``selectbox``, ``text``, ``number`` (open bounds) or ``slider``."""
    if spec.type is bool:
        return "checkbox"
    if spec.type is str:
        return "selectbox" if spec.choices else "text"
    low, high = spec.bounds
    return "number" if low is None or high is None else "slider"


def slider_options(spec: ParamSpec) -> list[Any]:
    """The values a slider offers for a bounded numeric parameter, ascending, default included.

    Integers: every value up to 60 above the lower bound, then a roughly logarithmic series.
    Floats spanning two decades or more (or from 0 to far above the default): a logarithmic series
    with about 11 steps per decade (plus 0 where 0 is allowed); otherwise about 100 even steps.
    """
    low, high = spec.bounds
    if low is None or high is None:
        raise ValueError(f"{spec.name} has open bounds; it gets a number input, not a slider")
    default = spec.default
    if spec.type is int:
        if high - low <= 60:
            values = set(range(int(low), int(high) + 1))
        else:
            values = set(range(int(low), int(low) + 21)) | {
                int(round(v)) for v in _log_series(max(low, 1), high)
            }
            values |= {int(high)}
    elif low > 0 and high / low >= 50:
        values = set(_log_series(low, high)) | {_nice(low), _nice(high)}
    elif low == 0 and spec.unit != "fraction" and (not default or high / default >= 50):
        values = {0.0} | set(_log_series(high * 1e-4, high)) | {_nice(high)}
    else:
        span = high - low
        step = 10.0 ** math.floor(math.log10(span / 100)) if span > 0 else 1.0
        while span / step > _MAX_LINEAR:
            step *= 2
        values = {_nice(low + n * step) for n in range(int(round(span / step)) + 1)}
    if default is not None:
        values.add(default)
    return sorted(v for v in values if low <= v <= high)


def nearest_option(options: list[Any], value: float) -> Any:
    """The option closest to ``value`` (in ratio for positive values, else in difference)."""

    def distance(o):
        if o > 0 and value > 0:
            return abs(math.log(o / value))
        return abs(o - value) + (1e9 if (o > 0) != (value > 0) else 0)

    return min(options, key=distance)


def symbol(spec: ParamSpec) -> str:
    return SYMBOLS.get(spec.symbol, spec.symbol)


def label(spec: ParamSpec) -> str:
    """``q̄ · q_bar``, ``x · cell_size_m``, or the bare name when there is no paper symbol."""
    s = symbol(spec)
    return f"{s} · {spec.name}" if s and s != spec.name else spec.name


def format_value(spec: ParamSpec, value: Any) -> str:
    """A readable value with its unit: lengths below 1 m in millimetres, fractions as percent."""
    if value is None:
        return "auto"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return str(value)
    if spec.unit == "m":
        return f"{1000 * value:.4g} mm" if abs(value) < 1 else f"{value:.4g} m"
    unit = f" {spec.unit}" if spec.unit and spec.unit not in ("1", "fraction") else ""
    return f"{value:.4g}{unit}"


def help_text(spec: ParamSpec) -> str:
    low, high = spec.bounds
    parts = [spec.help]
    if spec.symbol:
        parts.append(f"Paper symbol: {symbol(spec)}.")
    if spec.unit:
        parts.append(f"Unit: {spec.unit}.")
    if low is not None or high is not None:
        parts.append(f"Allowed: [{'-inf' if low is None else low}, {'inf' if high is None else high}].")
    if spec.auto:
        parts.append(f"Auto: {spec.auto}.")
    return " ".join(parts)


def value_key(kind: str, plugin: str, name: str) -> str:
    return f"cfg_p:{kind}:{plugin}:{name}"


def auto_key(kind: str, plugin: str, name: str) -> str:
    return f"cfg_auto:{kind}:{plugin}:{name}"


def _initial(spec: ParamSpec, hint: float | None) -> Any:
    if spec.default is not None:
        return spec.default
    if widget_kind(spec) == "slider":
        options = slider_options(spec)
        if hint is not None:
            return nearest_option(options, hint)
        return options[len(options) // 2]
    low, high = spec.bounds
    return hint if hint is not None else (low if low is not None else 0.0)


def _auto_changed(spec: ParamSpec, vkey: str, akey: str, hint: float | None) -> None:
    """When "auto" is unticked, start the slider at the value auto last chose."""
    if not st.session_state.get(akey) and hint is not None:
        if widget_kind(spec) == "slider":
            st.session_state[vkey] = nearest_option(slider_options(spec), hint)
        elif widget_kind(spec) == "number":
            st.session_state[vkey] = spec.type(hint)


def params_widgets(
    kind: str,
    plugin: str,
    params_cls: type,
    *,
    advanced: bool = False,
    hints: Mapping[str, float] | None = None,
    disabled: bool = False,
):
    """Draw one widget per parameter of ``params_cls`` and return the Params built from them.

    Parameters
    ----------
    kind, plugin : which plugin the parameters belong to (part of the widget keys)
    params_cls : the plugin's frozen Params dataclass
    advanced : also show the parameters without a paper symbol (else they keep their values);
        a plugin none of whose parameters has a paper symbol always shows them all
    hints : values the automatic parameters resolved to in the last run, by parameter name, used
        to start a slider when its "auto" box is unticked

    Raises
    ------
    ParamError : from the Params constructor, when the combination is invalid
    """
    hints = hints or {}
    values = {}
    specs = describe(params_cls)
    # The paper's parameters first; a plugin whose parameters have no paper symbol shows them all.
    any_symbol = any(spec.symbol for spec in specs)
    for spec in specs:
        vkey, akey = value_key(kind, plugin, spec.name), auto_key(kind, plugin, spec.name)
        hint = hints.get(spec.name)
        st.session_state.setdefault(vkey, _initial(spec, hint))
        if spec.auto:
            st.session_state.setdefault(akey, spec.default is None)
        shown = advanced or bool(spec.symbol) or not any_symbol
        is_auto = bool(spec.auto) and bool(st.session_state[akey])
        if shown and spec.auto:
            st.checkbox(
                f"{label(spec)}: auto",
                key=akey,
                help=help_text(spec),
                disabled=disabled,
                on_change=_auto_changed,
                args=(spec, vkey, akey, hint),
            )
            is_auto = bool(st.session_state[akey])
            if is_auto:
                last = f" (last run: {format_value(spec, hint)})" if hint is not None else ""
                st.caption(f"{spec.auto}{last}")
        if is_auto:
            values[spec.name] = None
            continue
        if shown:
            _widget(spec, vkey, disabled=disabled, compact=bool(spec.auto))
        values[spec.name] = st.session_state[vkey]
    return params_cls(**values)


def _widget(spec: ParamSpec, key: str, *, disabled: bool, compact: bool) -> None:
    what = widget_kind(spec)
    text = label(spec)
    visibility = "collapsed" if compact else "visible"
    if what == "checkbox":
        st.checkbox(label(spec), key=key, help=help_text(spec), disabled=disabled)
    elif what == "selectbox":
        if st.session_state[key] not in spec.choices:
            st.session_state[key] = spec.default
        st.selectbox(
            text, spec.choices, key=key, help=help_text(spec), disabled=disabled, label_visibility=visibility
        )
    elif what == "text":
        st.text_input(text, key=key, help=help_text(spec), disabled=disabled, label_visibility=visibility)
    elif what == "number":
        low, high = spec.bounds
        st.number_input(
            text,
            min_value=None if low is None else spec.type(low),
            max_value=None if high is None else spec.type(high),
            key=key,
            help=help_text(spec),
            disabled=disabled,
            format="%g" if spec.type is float else "%d",
            label_visibility=visibility,
        )
    else:
        options = slider_options(spec)
        if st.session_state[key] not in options:
            st.session_state[key] = nearest_option(options, float(st.session_state[key]))
        st.select_slider(
            text,
            options=options,
            key=key,
            help=help_text(spec),
            disabled=disabled,
            format_func=lambda v, s=spec: format_value(s, v),
            label_visibility=visibility,
        )


def reset_params() -> None:
    """Forget every parameter value and "auto" choice (an ``on_click`` callback): defaults again."""
    for key in list(st.session_state):
        if isinstance(key, str) and key.startswith(("cfg_p:", "cfg_auto:")):
            del st.session_state[key]


def keep_config_state() -> None:
    """Keep the configuration widgets' values across pages (Streamlit forgets a widget's value on a
    run where it is not drawn; writing the value back keeps it). Call at the top of every run."""
    for key in list(st.session_state):
        if isinstance(key, str) and key.startswith(KEY_PREFIXES):
            st.session_state[key] = st.session_state[key]
