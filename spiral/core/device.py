"""Which compute device a run asks for, checked before anything is built on it, and the torch threads it computes
with."""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterator

from spiral.core.errors import UsageError

__all__ = ["canonical_device", "check_device", "torch_threads"]


def canonical_device(device: str) -> str:
    """``device``'s canonical name, ``cpu`` or ``cuda:N`` (``cuda`` is ``cuda:0``), whether or not this machine has
    it: the name a run's fingerprints and manifests record.

    Raises:
        UsageError: a malformed name.
    """
    match = re.fullmatch(r"cpu|cuda(?::(\d+))?", device)
    if match is None:
        raise UsageError(f"device {device!r}: expected cpu, cuda or cuda:N")
    return "cpu" if device == "cpu" else f"cuda:{int(match.group(1) or 0)}"


def check_device(device: str) -> str:
    """Check that ``device`` names a device this machine has, and return its canonical name.

    Args:
        device: ``cpu``, ``cuda`` (the first GPU) or ``cuda:N``.

    Returns:
        ``cpu`` or ``cuda:N``. A CPU device never loads the CUDA driver.

    Raises:
        ValueError: one line naming the device and what is wrong: a malformed name, no CUDA on this machine, or an
            index past its GPUs.
    """
    device = canonical_device(device)
    if device == "cpu":
        return "cpu"
    import torch

    count = torch.cuda.device_count()
    if count == 0:
        why = "this torch build has no CUDA support" if torch.version.cuda is None else "no CUDA driver or GPU found"
        raise UsageError(f"device {device}: CUDA is not available on this machine ({why}); use --device cpu")
    index = int(device.split(":")[1])
    if index >= count:
        raise UsageError(f"device {device}: this machine has {count} CUDA device(s), cuda:0 to cuda:{count - 1}")
    return device


@contextlib.contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """Run the body with ``count`` torch threads, and restore the count after. On the CPU, torch's reductions and
    matrix products split their work by the thread count, so it decides a result to the bit: a computation that must
    give the same numbers wherever it runs (a training step in this process, a worker or a Ray task; races beside
    other jobs) fixes it."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)
