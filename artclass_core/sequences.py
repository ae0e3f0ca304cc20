"""Finding sequences on disk through whichever reader recognises them."""

from __future__ import annotations

import os
from pathlib import Path

from .errors import InputError
from .plugins import Registry
from .types import Sequence


def open_sequences(registry: Registry, path: str | Path, *, reader: str | None = None) -> list[Sequence]:
    """The sequences at ``path``, from the named reader or the first reader that recognises it.

    ``PATH#NAME`` selects one sequence by name from a path that holds several (e.g. one object of a
    YCB-Video scene). Raises :class:`InputError` when the path is missing or no reader recognises it.
    """
    text = str(path)
    path, _, wanted = text.partition("#") if "#" in text and not Path(text).exists() else (text, "", "")
    path = Path(path)
    if not path.exists():
        raise InputError("no such file or folder", path=path)
    names = [reader] if reader else registry.names("reader")
    for name in names:
        found = registry.create("reader", name).sequences(path)
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
    registry: Registry, root: str | Path, *, reader: str | None = None, labelled_only: bool = True
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
    readers = [registry.create("reader", n) for n in names]
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
        for r in readers:
            try:
                found = r.sequences(Path(here))
            except InputError as exc:
                errors.append(exc)
                dirs.clear()
                break
            if found:
                out.extend(s for s in found if s.label or not labelled_only)
                dirs.clear()
                break
    return out, errors
