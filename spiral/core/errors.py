"""The error a user can fix: what they asked for (an option, an argument, a file) cannot be done as asked."""

from __future__ import annotations

__all__ = ["UsageError"]


class UsageError(ValueError):
    """A request that cannot be met as made: a wrong option or argument, a file whose contents do not fit, a tool that
    is missing. Its message names what to change; the command line prints it as one ``Error:`` line. Any other
    exception is a bug and keeps its traceback."""
