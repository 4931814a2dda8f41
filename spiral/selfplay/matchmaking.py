"""Which pool member each training world races: the latest best with probability p, else sampled from the pool."""

from __future__ import annotations

from typing import Literal

import torch

__all__ = ["Matchmaker"]


class Matchmaker:
    """Draws opponents and keeps, per member, how often the learner lost to it.

    ``prioritized`` sampling weights member m by (losses_m + 1) / (races_m + 2), the learner's smoothed loss
    rate against it, so the pool's hardest members are met more often (prioritised fictitious self-play).
    """

    def __init__(self, member_count: int, *, latest: int, p_latest: float,
                 mode: Literal["uniform", "prioritized"] = "prioritized", device: torch.device | str = "cpu") -> None:
        self.latest, self.p_latest, self.mode = latest, p_latest, mode
        self.races = torch.zeros(member_count, device=device)
        self.losses = torch.zeros(member_count, device=device)

    def weights(self) -> torch.Tensor:
        """Sampling weights over members for the non-latest draws (sum to 1)."""
        w = torch.ones_like(self.races) if self.mode == "uniform" else (self.losses + 1.0) / (self.races + 2.0)
        return w / w.sum()

    def draw(self, count: int, generator: torch.Generator) -> torch.Tensor:
        """Member index for each of ``count`` worlds."""
        device = self.races.device
        u = torch.rand(count, generator=generator, device=device)
        sampled = torch.multinomial(self.weights(), count, replacement=True, generator=generator)
        return torch.where(u < self.p_latest, torch.full_like(sampled, self.latest), sampled)

    def add_member(self) -> None:
        """Count one more member (appended last), the latest best from now on."""
        self.races = torch.cat([self.races, self.races.new_zeros(1)])
        self.losses = torch.cat([self.losses, self.losses.new_zeros(1)])
        self.latest = len(self.races) - 1

    def record(self, members: torch.Tensor, learner_won: torch.Tensor, counted: torch.Tensor | None = None) -> None:
        """Count finished races against ``members`` (those where the bool mask ``counted`` is set, all when None); a
        race the learner did not win counts as a loss."""
        counted = torch.ones_like(learner_won) if counted is None else counted
        self.races.index_add_(0, members, counted.to(self.races.dtype))
        self.losses.index_add_(0, members, (counted & ~learner_won).to(self.races.dtype))
