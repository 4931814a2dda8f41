"""Opponent drones in training: pool policies run batched per member inside ``RaceEnv.step``."""

from __future__ import annotations

import torch
from tensordict import TensorDict

from spiral.selfplay.matchmaking import Matchmaker
from spiral.train.checkpoint import FrozenPolicy

__all__ = ["PoolOpponents"]


class PoolOpponents:
    """An ``OpponentPolicy`` over several frozen policies; each world keeps its drawn member for the episode.

    Opponent rows arrive world-major (``per_world`` rows per world). All worlds that share a member go through
    that member's network in one forward pass, without gradients.
    """

    def __init__(self, policies: list[FrozenPolicy], matchmaker: Matchmaker, *, world_count: int, per_world: int,
                 generator: torch.Generator) -> None:
        self.policies, self.matchmaker = policies, matchmaker
        self.per_world, self.generator = per_world, generator
        self.assignment = matchmaker.draw(world_count, generator)
        """Member index of each world."""

    @torch.no_grad()
    def __call__(self, obs: TensorDict) -> torch.Tensor:
        """Actions of every opponent drone."""
        member_of_row = self.assignment.repeat_interleave(self.per_world)
        actions = torch.zeros(obs.batch_size[0], 4, device=member_of_row.device)
        for m in torch.unique(member_of_row).tolist():
            rows = member_of_row == m
            actions[rows] = self.policies[m](obs[rows])
        return actions

    def reset(self, worlds: torch.Tensor) -> None:
        """Draw new members for the worlds in the bool mask ``worlds``."""
        count = int(worlds.sum())
        if count:
            self.assignment[worlds] = self.matchmaker.draw(count, self.generator)

    def record(self, worlds: torch.Tensor, learner_won: torch.Tensor) -> None:
        """Feed race outcomes of ended worlds (indices) to the matchmaker."""
        self.matchmaker.record(self.assignment[worlds], learner_won)
