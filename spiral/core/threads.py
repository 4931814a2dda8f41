"""Torch's CPU thread count in one process: the share of the cores a pipeline worker is given, which can change
while it runs (``spiral run --jobs``), and code that must hold a count of its own meanwhile (the report, while
planner processes take the cores)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

__all__ = ["pinned", "take_share"]

_share: int | None = None
"""The latest share this process was given (None: never given one)."""
_pins: list[int] = []
"""Thread counts held by open :func:`pinned` blocks, innermost last."""


def take_share(threads: int) -> None:
    """Use ``threads`` torch threads from now on: at once, or when the last open :func:`pinned` block ends."""
    global _share
    _share = threads
    if not _pins:
        torch.set_num_threads(threads)


@contextlib.contextmanager
def pinned(threads: int) -> Iterator[None]:
    """Run the body on ``threads`` torch threads whatever share arrives meanwhile; afterwards the latest share, or
    the count from before when none was given."""
    before = torch.get_num_threads()
    _pins.append(threads)
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        _pins.pop()
        torch.set_num_threads(_pins[-1] if _pins else _share if _share is not None else before)
