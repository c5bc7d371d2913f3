"""Exceptions that carry the file, field or device at fault, so a user sees one clear line."""
from __future__ import annotations

from os import PathLike


class OdsplatError(Exception):
    """Base class of every error odsplat raises on purpose."""


class InputError(OdsplatError, ValueError):
    """Bad input: names the source (file, field or device) and what was expected."""

    def __init__(self, source: str | PathLike, problem: str):
        self.source = str(source)
        self.problem = problem
        super().__init__(f"{self.source}: {problem}")

    def __reduce__(self):  # raised in a worker process, it must cross back with both fields
        return type(self), (self.source, self.problem)


class SchemaError(InputError):
    """A file written by a newer, unknown or foreign schema."""


class IncompleteTakeError(InputError):
    """A take that was never finalised (its writer died); it must be recovered explicitly."""


def one_line(exc: BaseException) -> str:
    """An error in one line: odsplat's own as they are (they name their culprit), others with their type."""
    text = " ".join(str(exc).split())
    return text if isinstance(exc, OdsplatError) else f"{type(exc).__name__}: {text}" if text else type(exc).__name__
