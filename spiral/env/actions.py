"""How actions in [−1, 1] become PID targets: the relative or absolute mapping and the separation filter."""

from __future__ import annotations

import math

import torch

from spiral.config.env import EnvCfg, SeparationCfg
from spiral.config.track import TrackSpec
from spiral.core.scenario import race_teams
from spiral.env.separation import separation_offsets

__all__ = ["ACTION_AXES", "ActionMap"]

ACTION_AXES = ("x", "y", "z", "yaw")
"""The action's components, in order: the position target along the world's x, y, z and the yaw target."""


class ActionMap:
    """Maps every drone's 4-D action to a position and yaw target.

    ``action.mode`` relative: an offset from the drone (``pos_scale``, ``yaw_scale_deg`` at 1); absolute: a point
    of the arena's bounds and a yaw in [−π, π]. Then ``action.separation`` shifts the position targets of every
    drone, or of one race team's (``action.separation_team``; part of the flight stack).
    """

    def __init__(self, cfg: EnvCfg, track: TrackSpec, *, world_count: int, drones_per_world: int,
                 device: torch.device) -> None:
        self.cfg = cfg.action
        self.world_count, self.drones_per_world = world_count, drones_per_world
        self.lo = torch.tensor(track.bounds.min, device=device)
        self.hi = torch.tensor(track.bounds.max, device=device)
        team = self.cfg.separation_team
        self.filtered = None if team == "all" else torch.tensor(
            [t == "ab".index(team) for t in race_teams(drones_per_world)], device=device).repeat(world_count)[:, None]
        """Which drones (N, 1) the separation filter shifts; None: all."""

    def targets(self, actions: torch.Tensor, pos: torch.Tensor, vel: torch.Tensor, yaw: torch.Tensor,
                racing: torch.Tensor) -> torch.Tensor:
        """PID targets (N, 4: position, yaw) of every drone; ``racing`` (N,) drones push each other apart under the
        separation filter, the others do not."""
        a = self.cfg
        if a.mode == "relative":
            target = pos + a.pos_scale * actions[:, :3]
            yaw = yaw + math.radians(a.yaw_scale_deg) * actions[:, 3]
        else:
            target = self.lo + (actions[:, :3] + 1.0) * 0.5 * (self.hi - self.lo)
            yaw = math.pi * actions[:, 3]
        if a.separation is not None:
            shift = self._shift(pos, vel, racing, a.separation)
            target = target + (shift if self.filtered is None else shift * self.filtered)
        return torch.cat([target, yaw[:, None]], dim=-1)

    def _shift(self, pos: torch.Tensor, vel: torch.Tensor, racing: torch.Tensor, cfg: SeparationCfg) -> torch.Tensor:
        """Target shift (N, 3) of every drone away from the others by the separation rule ``cfg``."""
        w, d = self.world_count, self.drones_per_world
        return separation_offsets(pos.view(w, d, 3), vel.view(w, d, 3), racing.view(w, d), cfg).view(-1, 3)
