"""Errors the user sees: one line naming the file (or object) and the problem."""

from __future__ import annotations

from pathlib import Path


class AerecError(Exception):
    """Base class for errors reported to the user without a traceback."""


class InputError(AerecError):
    """Bad input: names the offending file and what is wrong with it."""

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)


class ReconstructionError(AerecError):
    """A stage could not produce a result from valid input (too few matches, no overlap...)."""
