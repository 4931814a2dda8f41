"""Who won a race: the one rule every part of spiral decides it by (training rewards, matchmaking, promotion,
evaluation, the SE-IBR studies)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

__all__ = ["race_winner"]


def race_winner(finished: torch.Tensor, finish_time: torch.Tensor, teams: Sequence[Sequence[int]]) -> torch.Tensor:
    """Index of the winning team of each race, −1 when there is no winner.

    A team's time is that of its first drone to finish; the team with the earliest time wins. Drones that did not
    finish (crashed, out of time, absent) cannot win, so a finisher beats them. No one finished, or two teams
    finished at exactly the same time: no winner.

    Args:
        finished: Whether each drone finished, shape (..., D).
        finish_time: Each drone's finish time (lap time), shape (..., D); ignored where not ``finished``.
        teams: The slots of each team (an empty team never wins).
    """
    t = torch.where(finished, finish_time, math.inf)
    none = torch.full(t.shape[:-1], math.inf, dtype=t.dtype, device=t.device)
    best = torch.stack([t[..., list(slots)].amin(dim=-1) if len(slots) else none for slots in teams], dim=-1)
    first = best.amin(dim=-1)
    alone = (best == first[..., None]).sum(dim=-1) == 1
    winner = best.argmin(dim=-1)
    return torch.where(torch.isfinite(first) & alone, winner, torch.full_like(winner, -1))
