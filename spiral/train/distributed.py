"""Data-parallel training over several processes (one per GPU, on one or more nodes) launched by ``torchrun``.

torchrun starts the processes and sets ``RANK``, ``LOCAL_RANK`` and ``WORLD_SIZE``. :func:`init_distributed` joins
the process group (NCCL on CUDA; gloo on CPU, for tests) and pins the process to ``cuda:LOCAL_RANK``; the Warp
simulator and torch then run on that device because :class:`~spiral.train.StageTrainer` gets it as ``device``.
Inside a process group the trainer

- seeds rank r with ``seed + r`` (its own start placements and exploration noise),
- builds rsl-rl's runner with the multi-GPU config on (``alg.is_multi_gpu``: ``PPO.update`` averages gradients
  over the ranks and the observation normaliser merges its statistics), see :class:`GroupRunner`,
- starts every rank from rank 0's training state (:func:`share_training_state`: weights, optimiser, normaliser,
  iteration) and broadcasts the parameters when training starts, as rsl-rl's ``learn()`` does,
- lets only rank 0 evaluate, select, write checkpoints, logs and progress.

Without a process group nothing changes. Commands: ``docs/scaling.md``.
"""

from __future__ import annotations

import io
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist
from rsl_rl.algorithms import PPO
from rsl_rl.runners import OnPolicyRunner

from spiral.core.errors import UsageError

__all__ = [
    "DistInfo",
    "GroupRunner",
    "StageCancelledError",
    "cancel_workers",
    "current",
    "env_info",
    "init_distributed",
    "rank_device",
    "share_training_state",
    "shutdown",
]


class StageCancelledError(Exception):
    """Rank 0 did not train the stage (it was complete), so the other ranks stop too."""


@dataclass(frozen=True)
class DistInfo:
    """Where this process sits in a data-parallel run."""

    rank: int = 0
    """Global rank (0 .. world_size − 1); rank 0 writes every file."""
    local_rank: int = 0
    """Rank on this node; the process uses ``cuda:<local_rank>``."""
    world_size: int = 1
    """Number of processes."""

    @property
    def enabled(self) -> bool:
        """Whether more than one process trains."""
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        """Whether this process writes checkpoints, logs and progress."""
        return self.rank == 0

    def seed(self, base: int) -> int:
        """This rank's seed: ``base + rank``."""
        return base + self.rank


def env_info(environ: Mapping[str, str] | None = None) -> DistInfo | None:
    """The rank torchrun assigned (``RANK``, ``LOCAL_RANK``, ``WORLD_SIZE``), or None outside torchrun.

    Raises:
        ValueError: when the variables are malformed or inconsistent.
    """
    env = os.environ if environ is None else environ
    names = ("RANK", "LOCAL_RANK", "WORLD_SIZE")
    if not any(n in env for n in names):
        return None
    try:
        rank, local_rank, world_size = (int(env[n]) for n in names)
    except (KeyError, ValueError) as exc:
        raise UsageError(f"torchrun variables {', '.join(f'{n}={env.get(n)!r}' for n in names)}: "
                         f"expected three integers") from exc
    if world_size < 1 or not 0 <= rank < world_size or not 0 <= local_rank < world_size:
        raise UsageError(f"torchrun variables RANK={rank}, LOCAL_RANK={local_rank}, WORLD_SIZE={world_size} "
                         "are inconsistent")
    return DistInfo(rank, local_rank, world_size)


def rank_device(device: str | None, info: DistInfo) -> str:
    """This rank's device: ``cuda:LOCAL_RANK`` for ``None``, ``cuda`` or that same ``cuda:N``; ``cpu`` stays ``cpu``.

    Raises:
        ValueError: for another device string, or a ``cuda:N`` that is not this rank's GPU.
    """
    if device in (None, "cuda"):
        return f"cuda:{info.local_rank}"
    if device == "cpu":
        return "cpu"
    m = re.fullmatch(r"cuda:(\d+)", device)
    if m is None:
        raise UsageError(f"--device: expected cpu, cuda or cuda:N, got {device!r}")
    if int(m.group(1)) != info.local_rank:
        raise UsageError(f"--device {device} on local rank {info.local_rank}: with --distributed each process uses "
                         f"cuda:LOCAL_RANK (pass --device cuda, or none)")
    return device


def init_distributed(device: str | None = None, *, environ: Mapping[str, str] | None = None) -> tuple[DistInfo, str]:
    """Join torchrun's process group and return this rank and its device (see :func:`rank_device`).

    Raises:
        ValueError: outside torchrun, or when this rank's GPU does not exist.
    """
    info = env_info(environ)
    if info is None:
        raise UsageError("--distributed needs torchrun, which sets RANK, LOCAL_RANK and WORLD_SIZE "
                         "(see docs/scaling.md)")
    dev = rank_device(device, info)
    cuda = dev.startswith("cuda")
    if cuda:
        if torch.cuda.device_count() <= info.local_rank:
            raise UsageError(f"local rank {info.local_rank} needs {dev}, but this node has "
                             f"{torch.cuda.device_count()} CUDA device(s)")
        torch.cuda.set_device(info.local_rank)
    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if cuda else "gloo", rank=info.rank, world_size=info.world_size,
                                device_id=torch.device(dev) if cuda else None)
    return info, dev


def current() -> DistInfo:
    """This process's place in the process group; rank 0 of 1 when there is none."""
    if not (dist.is_available() and dist.is_initialized()):
        return DistInfo()
    return DistInfo(dist.get_rank(), int(os.environ.get("LOCAL_RANK", "0")), dist.get_world_size())


def shutdown() -> None:
    """Leave the process group (no-op without one)."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


class GroupRunner(OnPolicyRunner):
    """rsl-rl's ``OnPolicyRunner`` that joins the process group :func:`init_distributed` set up.

    rsl-rl's own ``_configure_multi_gpu`` creates an NCCL group from the torchrun variables itself; here the group
    exists already (NCCL, or gloo on CPU), so this fills in the same fields (``is_distributed``, ranks,
    ``cfg["multi_gpu"]``) from it. Without a process group it is rsl-rl's runner unchanged.
    """

    def _configure_multi_gpu(self) -> None:
        if not (dist.is_available() and dist.is_initialized()):
            if int(os.getenv("WORLD_SIZE", "1")) > 1:
                raise UsageError("launched by torchrun without a process group: train with `spiral train ... "
                                 "--distributed`, or call spiral.train.distributed.init_distributed() first")
            super()._configure_multi_gpu()
            return
        info = current()
        self.gpu_world_size, self.gpu_global_rank, self.gpu_local_rank = info.world_size, info.rank, info.local_rank
        self.is_distributed = info.enabled
        self.cfg["multi_gpu"] = ({"global_rank": info.rank, "local_rank": info.local_rank,
                                  "world_size": info.world_size} if info.enabled else None)


def share_training_state(alg: PPO, start_iteration: int, best: Any, *, device: str) -> tuple[int, Any]:
    """Give every rank rank 0's training state: weights, optimiser, normaliser (loaded into ``alg``), and return
    rank 0's start iteration and best score.

    Rank 0 may have resumed from a checkpoint the others cannot see, so its state is sent, not read from disk.

    Raises:
        StageCancelledError: on ranks > 0 when rank 0 called :func:`cancel_workers` instead.
    """
    payload: list[Any] = [None]
    if current().is_main:
        buf = io.BytesIO()
        torch.save({"alg": alg.save(), "start_iteration": start_iteration, "best": best}, buf)
        payload = [buf.getvalue()]
    dist.broadcast_object_list(payload, src=0)
    if payload[0] is None:
        raise StageCancelledError("rank 0 did not train this stage")
    if current().is_main:
        return start_iteration, best
    data = torch.load(io.BytesIO(payload[0]), map_location=device, weights_only=False)
    alg.load(data["alg"], None, strict=True)
    return data["start_iteration"], data["best"]


def cancel_workers() -> None:
    """On rank 0, when it did not train: release the ranks waiting in :func:`share_training_state`."""
    dist.broadcast_object_list([None], src=0)
