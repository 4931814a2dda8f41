"""An exponential moving average of the policy's weights: the candidate that selection races and ``best.pt`` keeps."""

from __future__ import annotations

import copy

import torch

__all__ = ["PolicyAverage"]


class PolicyAverage:
    """Keeps θ̄ ← d·θ̄ + (1 − d)·θ after every PPO update (d = ``decay``), on a copy of the actor.

    PPO's iterates swing from one evaluation to the next in multi-drone stages; their running average is a steadier
    policy. Buffers (the observation normaliser's statistics) are copied, not averaged: they are running
    statistics already. The copy never trains and is always in evaluation mode.
    """

    def __init__(self, actor: torch.nn.Module, decay: float) -> None:
        if not 0.0 < decay < 1.0:
            raise ValueError(f"decay must lie in (0, 1), got {decay}")
        self.decay = decay
        self.model = copy.deepcopy(actor).eval().requires_grad_(False)

    @torch.no_grad()
    def update(self, actor: torch.nn.Module) -> None:
        """Move the average towards ``actor``'s current weights."""
        for mean, param in zip(self.model.parameters(), actor.parameters(), strict=True):
            mean.lerp_(param.detach(), 1.0 - self.decay)
        for mean_buf, buf in zip(self.model.buffers(), actor.buffers(), strict=True):
            mean_buf.copy_(buf)

    def policy(self) -> torch.nn.Module:
        """The averaged actor, for deterministic inference (called plainly it returns the mean action)."""
        return self.model

    def state_dict(self) -> dict[str, torch.Tensor]:
        """The averaged actor's state (the layout of the actor's own)."""
        return self.model.state_dict()

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Restore an average saved with :meth:`state_dict`."""
        self.model.load_state_dict(state)
