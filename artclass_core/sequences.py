"""Finding sequences on disk through whichever reader recognises them."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from pathlib import Path

from .errors import InputError
from .params import describe, parse_value
from .plugins import Registry
from .types import Sequence


def split_reader_values(
    registry: Registry, values: Mapping[str, str]
) -> tuple[dict[str, str], dict[str, str]]:
    """``(reader values, other values)``: the ``--param NAME=VALUE`` settings that name a field of some
    reader's parameters (``max_time_diff_s``, a bag's ``colour_topic`` ...), and the rest."""
    names = {s.name for n in registry.names("reader") for s in describe(registry.get("reader", n).Params)}
    return (
        {k: v for k, v in values.items() if k in names},
        {k: v for k, v in values.items() if k not in names},
    )


def _reader(registry: Registry, name: str, values: Mapping[str, str]):
    """Reader ``name`` with those of ``values`` that name its parameters (strings, parsed by type)."""
    params = registry.get("reader", name).Params()
    changes = {s.name: parse_value(s, values[s.name]) for s in describe(type(params)) if s.name in values}
    return registry.create("reader", name, dataclasses.replace(params, **changes) if changes else params)


def _opened(found: list[Sequence], reader: str, values: Mapping[str, str]) -> list[Sequence]:
    for s in found:
        s.opened_with = (reader, tuple(sorted(values.items())))
    return found


def open_sequences(
    registry: Registry,
    path: str | Path,
    *,
    reader: str | None = None,
    reader_values: Mapping[str, str] | None = None,
) -> list[Sequence]:
    """The sequences at ``path``, from the named reader or the first reader that recognises it.

    ``PATH#NAME`` selects one sequence by name from a path that holds several (e.g. one object of a
    YCB-Video scene). ``reader_values`` set reader parameters by name (each reader takes those of its
    own). Raises :class:`InputError` when the path is missing or no reader recognises it.
    """
    text = str(path)
    path, _, wanted = text.partition("#") if "#" in text and not Path(text).exists() else (text, "", "")
    path = Path(path)
    if not path.exists():
        raise InputError("no such file or folder", path=path)
    names = [reader] if reader else registry.names("reader")
    for name in names:
        found = _opened(
            _reader(registry, name, reader_values or {}).sequences(path), name, reader_values or {}
        )
        if found:
            break
    else:
        tried = ", ".join(names)
        raise InputError(f"not a sequence that any reader recognises (tried: {tried})", path=path)
    if wanted:
        chosen = [s for s in found if s.name == wanted or s.name.endswith(wanted)]
        if not chosen:
            raise InputError(
                f"no sequence named {wanted!r}; found: {', '.join(s.name for s in found)}", path=path
            )
        return chosen
    return found


def find_sequences(
    registry: Registry,
    root: str | Path,
    *,
    reader: str | None = None,
    labelled_only: bool = True,
    reader_values: Mapping[str, str] | None = None,
) -> tuple[list[Sequence], list[InputError]]:
    """Every sequence under ``root`` that a reader recognises (a recognised folder is not descended).
    Symbolic links to folders are followed (each real folder visited once, so a link loop ends).

    With ``labelled_only`` only sequences that carry a ground-truth label are returned. Folders that a
    reader recognises but cannot read are returned as errors, so one bad folder does not stop a sweep.
    """
    root = Path(root)
    if not root.is_dir():
        raise InputError("no such folder", path=root)
    names = [reader] if reader else registry.names("reader")
    readers = {n: _reader(registry, n, reader_values or {}) for n in names}
    out: list[Sequence] = []
    errors: list[InputError] = []
    visited: set[str] = set()
    for here, dirs, _files in os.walk(root, followlinks=True):
        real = os.path.realpath(here)
        if real in visited:
            dirs.clear()
            continue
        visited.add(real)
        dirs.sort()
        for name, r in readers.items():
            try:
                found = _opened(r.sequences(Path(here)), name, reader_values or {})
            except InputError as exc:
                errors.append(exc)
                dirs.clear()
                break
            if found:
                out.extend(s for s in found if s.label or not labelled_only)
                dirs.clear()
                break
    return out, errors
