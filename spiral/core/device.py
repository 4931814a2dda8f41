"""Which compute device a run asks for, checked before anything is built on it."""

from __future__ import annotations

import re

from spiral.core.errors import UsageError

__all__ = ["canonical_device", "check_device"]


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
