"""Errors that artclass reports to the user as one line: the file (if any) and the problem."""

from __future__ import annotations

from pathlib import Path


class ArtclassError(Exception):
    """A problem the user can fix. ``str(err)`` is the one-line message shown in the CLI and the UI."""

    def __init__(self, problem: str, *, path: str | Path | None = None):
        self.problem = problem
        self.path = None if path is None else str(path)
        super().__init__(f"{self.path}: {problem}" if self.path else problem)


class InputError(ArtclassError):
    """The data is missing, unreadable or inconsistent (bad image, no intrinsics, too few frames ...)."""


class ParamError(ArtclassError):
    """A parameter name is unknown or its value is out of bounds."""


class PluginError(ArtclassError):
    """A plugin is unknown, badly formed, clashes with another or has the wrong model signature."""
