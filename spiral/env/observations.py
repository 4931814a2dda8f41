"""Observation features and the history buffer, batched over every drone of every world."""

from __future__ import annotations

import torch

from spiral.config.env import ObsCfg

__all__ = ["HISTORY_FEATURES", "ObservationBuilder", "nearest_others"]

HISTORY_FEATURES = 16
"""Per history entry: 2 nearest drones' relative positions (6), next 2 gates' relative positions (6), action (4)."""


def nearest_others(pos: torch.Tensor, present: torch.Tensor, count: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """Relative positions of each drone's ``count`` nearest present drones in its world, nearest first.

    Args:
        pos: Positions, shape (W, D, 3).
        present: Whether each drone is still racing, shape (W, D).
        count: Neighbours to return.

    Returns:
        Indices (W, D, count) of the neighbours in their world and a mask (W, D, count) of those that exist;
        absent neighbours have index 0 and mask False.
    """
    w, d, _ = pos.shape
    dist = torch.cdist(pos, pos)
    invalid = torch.eye(d, dtype=torch.bool, device=pos.device)[None] | ~present[:, None, :]
    dist = dist.masked_fill(invalid, float("inf"))
    k = min(count, d)
    near_dist, near_idx = torch.topk(dist, k, dim=-1, largest=False) if d > 0 else (dist, dist.long())
    mask = torch.isfinite(near_dist)
    if k < count:
        pad = count - k
        near_idx = torch.cat([near_idx, near_idx.new_zeros(w, d, pad)], dim=-1)
        mask = torch.cat([mask, mask.new_zeros(w, d, pad)], dim=-1)
    return near_idx.masked_fill(~mask, 0), mask


class ObservationBuilder:
    """Builds ``[ego(12), presence(2), extras, history(K·16)]`` for every drone and keeps the history buffer."""

    def __init__(self, cfg: ObsCfg, drone_count: int, *, device: torch.device) -> None:
        self.cfg = cfg
        self.length = (cfg.history_len - 1) * cfg.history_stride + 1
        self.history = torch.zeros(drone_count, self.length, HISTORY_FEATURES, device=device)
        """Feature history, oldest first; entries ``::history_stride`` are observed."""

    @property
    def extra_dim(self) -> int:
        """Inputs outside the ego state, presence flags and history."""
        c = self.cfg
        return (6 * c.gate_normals + 3 * c.pid_integral + 6 * c.opponent_velocity + 2 * c.teammates
                + 8 * c.closest_approach + 3 * c.priority)

    @property
    def obs_dim(self) -> int:
        """Length of one drone's observation vector."""
        return 12 + 2 + self.extra_dim + self.cfg.history_len * HISTORY_FEATURES

    def layout(self) -> dict:
        """Description of the observation vector, stored in checkpoints to refuse mismatched policies."""
        layout = {"obs_dim": self.obs_dim, **self.cfg.model_dump()}
        for option in ("teammates", "priority", "closest_approach"):  # layouts stored before an option existed
            if not layout[option]:                                      # stay equal
                del layout[option]
        if not self.cfg.closest_approach:
            del layout["approach_horizon_s"]
        return layout

    def push(self, features: torch.Tensor, fresh: torch.Tensor) -> None:
        """Append this step's features; drones in ``fresh`` (bool, N) start a new history filled with them."""
        if self.length > 1:
            self.history[:, :-1] = self.history[:, 1:].clone()
        self.history[:, -1] = features
        if fresh.any():
            self.history[fresh] = features[fresh, None, :].expand(-1, self.length, -1)

    def build(self, ego: torch.Tensor, presence: torch.Tensor, extras: list[torch.Tensor]) -> torch.Tensor:
        """Concatenate the observation of every drone, shape (N, obs_dim)."""
        hist = self.history[:, :: self.cfg.history_stride].flatten(1)
        return torch.cat([ego, presence, *extras, hist], dim=-1)
