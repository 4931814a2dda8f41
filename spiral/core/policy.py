"""What drives drones: a policy maps observations to actions; an opponent policy may also hear about resets and
race outcomes. Structural types (``typing.Protocol``): any callable of the right shape is one."""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol, runtime_checkable

import torch
from tensordict import TensorDict

__all__ = ["MirrorOpponent", "OpponentPolicy", "Policy", "RecordingOpponent", "ResettingOpponent"]


class Policy(Protocol):
    """Deterministic policy: observations of the drones it drives (TensorDict with a ``policy`` group, one row per
    drone) -> actions (rows, 4) in [−1, 1]."""

    def __call__(self, obs: TensorDict) -> torch.Tensor:
        """Actions of every row of ``obs``."""
        ...


class OpponentPolicy(Protocol):
    """Drives the opponent slots of a race env: their observations (world-major rows) -> actions in [−1, 1].

    It may also implement :class:`ResettingOpponent` (new opponents at world resets), :class:`RecordingOpponent`
    (race outcomes, for matchmaking) and :class:`MirrorOpponent` (races the learner's current policy); the env and
    the trainer call those hooks when they are there.
    """

    def __call__(self, obs: TensorDict) -> torch.Tensor:
        """Actions of every opponent drone."""
        ...


@runtime_checkable
class ResettingOpponent(Protocol):
    """An opponent policy that wants to know when worlds reset (to draw new opponents)."""

    def reset(self, worlds: torch.Tensor) -> None:
        """Worlds in the bool mask ``worlds`` (W,) start new races."""
        ...


@runtime_checkable
class RecordingOpponent(Protocol):
    """An opponent policy that wants the outcome of each ended race (matchmaking statistics)."""

    def record(self, ended: torch.Tensor, learner_won: torch.Tensor) -> None:
        """The races of the worlds in the bool mask ``ended`` (W,) ended; ``learner_won`` (bool, W,) says who won
        each world's race (read where ``ended`` is set)."""
        ...


@runtime_checkable
class MirrorOpponent(Protocol):
    """An opponent policy that sometimes races the learner's own current policy (mirror self-play)."""

    live: Callable[[TensorDict], torch.Tensor] | None
    """The learner's current policy; the trainer sets it before the first step."""
