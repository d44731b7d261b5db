"""Typed errors. Bad data raises a ``PipelineError`` whose message names the file, what was expected and
what was found; ``assert`` is kept for internal invariants only."""

from __future__ import annotations

from pathlib import Path


class PipelineError(Exception):
    """Base of every error a user can cause with their data or configuration."""

    def __init__(self, path: str | Path | None, expected: str, found: str):
        self.path = None if path is None else Path(path)
        self.expected = expected
        self.found = found
        where = f"{self.path}: " if self.path is not None else ""
        super().__init__(f"{where}expected {expected}, found {found}")


class InputError(PipelineError):
    """An input file (in raw/ or written by an upstream stage) is missing, corrupt or inconsistent."""


class ConfigError(PipelineError):
    """A configuration file has an unknown key, a wrong type or an invalid value."""


class UpstreamMissingError(InputError):
    """A stage's input was not produced (or not completed) by the upstream stage."""
