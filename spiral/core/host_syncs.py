"""Count the torch calls that would make the host wait for a GPU, whatever device the tensors are on.

On a CUDA device these calls copy a value to the host or size an output by the data, so the host stops until the GPU
has caught up: reading a value (``item``, ``tolist``, ``bool``/``int``/``float`` of a tensor, ``.cpu()``), finding
indices (``nonzero``, one-argument ``where``, ``argwhere``), outputs sized by the data (``masked_select``,
``unique``, ``bincount``, ``repeat_interleave`` by a tensor), indexing with a bool mask (``x[mask]``,
``x[mask] = v``) and uploads of host data (``torch.tensor``/``torch.as_tensor`` of a list, number or array with a
``device``: a blocking copy waits for the device's queue). On a CPU nothing waits, so a CPU test counts them to pin the
code path a CUDA run takes.
"""

from __future__ import annotations

import os
import traceback
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch.overrides import TorchFunctionMode

__all__ = ["HostSyncCounter", "is_host_sync", "put_rows"]

_PACKAGE = str(Path(__file__).resolve().parents[1]) + os.sep
"""The spiral package's folder: call sites are counted in its files by default."""
_READS = frozenset({"__bool__", "__int__", "__float__", "__index__", "item", "tolist", "cpu", "numpy"})
_SIZED_BY_DATA = frozenset({"nonzero", "argwhere", "masked_select", "unique", "unique_consecutive", "bincount"})


def _mask_index(args: tuple[Any, ...]) -> bool:
    """Whether ``x[index]`` / ``x[index] = v`` has a bool tensor among its indices."""
    index = args[1] if len(args) > 1 else None
    items = index if isinstance(index, tuple) else (index,)
    return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool and i.dim() > 0 for i in items)


def _to_host(args: tuple[Any, ...], kwargs: dict[str, Any]) -> bool:
    """Whether a ``to`` call moves a tensor from a GPU to the CPU (``x.to(env.device)`` on a CPU env waits for
    nothing, on any device)."""
    if not args or not isinstance(args[0], torch.Tensor) or args[0].device.type == "cpu":
        return False
    targets = [*args[1:], kwargs.get("device")]
    return any((isinstance(t, str) and t.startswith("cpu")) or (isinstance(t, torch.device) and t.type == "cpu")
               for t in targets)


def is_host_sync(name: str, args: tuple[Any, ...], kwargs: dict[str, Any]) -> bool:
    """Whether the torch function or tensor method ``name`` called with ``args``/``kwargs`` waits for the device."""
    if name in _READS or name in _SIZED_BY_DATA:
        return True
    if name in ("tensor", "as_tensor"):  # host data placed on a device named by the caller
        return kwargs.get("device") is not None and not (args and isinstance(args[0], torch.Tensor))
    if name in ("__getitem__", "__setitem__", "index_put_", "index_put"):
        return _mask_index(args)
    if name == "where":
        return len(args) + len(kwargs) == 1
    if name == "repeat_interleave":
        repeats = args[1] if len(args) > 1 else kwargs.get("repeats")
        return isinstance(repeats, torch.Tensor) or (len(args) == 1 and not kwargs)
    if name == "to":
        return _to_host(args, kwargs)
    return False


class HostSyncCounter(TorchFunctionMode):
    """A torch function mode that counts host synchronisations by call site (file:line of the innermost frame whose
    file ``under`` accepts, by default the spiral package's files), and lets every call through unchanged.

    >>> with HostSyncCounter() as syncs:
    ...     env.step(actions)
    >>> syncs.total, syncs.sites.most_common(3)
    """

    def __init__(self, under: Callable[[str], bool] | None = None) -> None:
        super().__init__()
        self.sites: Counter[tuple[str, str]] = Counter()
        """Count by ``(call, "path:line")``."""
        self._under = under or (lambda filename: filename.startswith(_PACKAGE))

    @property
    def total(self) -> int:
        """Host synchronisations counted so far."""
        return sum(self.sites.values())

    def __torch_function__(self, func: Any, types: Any, args: tuple[Any, ...] = (),
                           kwargs: dict[str, Any] | None = None) -> Any:
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        if is_host_sync(name, args, kwargs):
            self.sites[(name, self._site())] += 1
        return func(*args, **kwargs)

    def _site(self) -> str:
        """Where the counted call was made: the innermost frame that ``under`` accepts."""
        frames = [f for f in traceback.extract_stack()[:-2] if self._under(f.filename)]
        if not frames:
            return "?"
        f = frames[-1]
        return f"{f.filename.removeprefix(_PACKAGE)}:{f.lineno}"


def put_rows(dst: torch.Tensor, values: torch.Tensor, rows: torch.Tensor, index: torch.Tensor | None) -> None:
    """Write ``values`` into the rows of ``dst`` that the bool mask ``rows`` selects (along the first dimension).

    With ``index`` (``rows``' indices, from ``nonzero``), ``values`` holds the selected rows only, in order; without,
    it holds a value for every row and is kept where ``rows`` is set: more work, but no host synchronisation.
    """
    if index is not None:
        dst[index] = values
    else:
        dst.copy_(torch.where(rows.view(-1, *[1] * (dst.dim() - 1)), values, dst))
