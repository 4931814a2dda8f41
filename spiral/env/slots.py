"""Who drives each slot of a race env's worlds (learner or opponent policy), as index tensors, and the teams."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from spiral.core.scenario import race_teams

__all__ = ["Slots", "per_row", "slot_map"]


@dataclass(frozen=True)
class Slots:
    """The slots of every world by who drives them; drone ``i`` is slot ``i % D`` of world ``i // D``."""

    learner_slots: list[int]
    """Slots the learner drives."""
    opponent_slots: list[int]
    """The other slots: an opponent policy drives them, or they are absent."""
    learner_idx: torch.Tensor
    """Flat drone indices of the learner slots, world-major (one PPO environment each)."""
    opponent_idx: torch.Tensor
    """Flat drone indices of the opponent slots, world-major."""
    slot_team: torch.Tensor
    """Team of each slot by who drives it (D,): 0 learners, 1 opponents."""
    race_team: torch.Tensor
    """Team of each slot in the scenario, whoever drives it (D,): :func:`~spiral.core.scenario.race_teams`."""


def slot_map(world_count: int, drones_per_world: int, learner_slots: Sequence[int], *, device: torch.device) -> Slots:
    """The :class:`Slots` of ``world_count`` worlds whose ``learner_slots`` the learner drives."""
    d = drones_per_world
    learner = list(learner_slots)
    opponent = [s for s in range(d) if s not in learner]
    base = torch.arange(world_count, device=device)[:, None] * d
    slot_team = torch.tensor([s in opponent for s in range(d)], dtype=torch.long, device=device)
    return Slots(
        learner_slots=learner, opponent_slots=opponent,
        learner_idx=(base + torch.tensor(learner, device=device)).flatten(),
        opponent_idx=(base + torch.tensor(opponent, device=device, dtype=torch.long)).flatten(),
        slot_team=slot_team, race_team=torch.tensor(race_teams(d), dtype=torch.long, device=device),
    )


def per_row(worlds: torch.Tensor, rows: int) -> torch.Tensor:
    """A per-world mask (W,) repeated for each of a world's ``rows`` rows (W·rows,), world-major."""
    return worlds[:, None].expand(-1, rows).reshape(-1)
