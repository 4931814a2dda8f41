"""Errors raised while reading specs, and their one-line-per-problem format."""

from __future__ import annotations

from pydantic import ValidationError

__all__ = ["SpecError", "format_validation_error"]


class SpecError(Exception):
    """A spec file is missing, unreadable or invalid.

    Each entry of ``problems`` is one line ``<file>: <dotted.field.path>: <what is wrong>``.
    """

    def __init__(self, problems: list[str]) -> None:
        super().__init__("\n".join(problems))
        self.problems = problems


def format_validation_error(source: str, exc: ValidationError, *, prefix: str = "") -> list[str]:
    """One ``<source>: <dotted.path>: <message>`` line per pydantic error.

    Errors raised by model validators carry no location; their message starts with the field path itself.
    """
    lines = []
    for err in exc.errors(include_url=False):
        path = ".".join(str(p) for p in (prefix, *err["loc"]) if p != "")
        msg = err["msg"].removeprefix("Value error, ")
        lines.append(f"{source}: {path}: {msg}" if path else f"{source}: {msg}")
    return lines
