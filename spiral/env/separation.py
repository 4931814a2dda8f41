"""Separation filter: shifts position targets apart where two drones are about to come close."""

from __future__ import annotations

import torch

from spiral.config.env import SeparationCfg

__all__ = ["separation_offsets"]


def separation_offsets(pos: torch.Tensor, vel: torch.Tensor, racing: torch.Tensor, cfg: SeparationCfg) -> torch.Tensor:
    """Target shift of every drone away from the other racing drones of its world, shape (W, D, 3).

    For drones i and j, with r = p_i − p_j and v = v_i − v_j, the closest approach within the horizon is at
    t* = clamp(−r·v / |v|², 0, horizon); there the separation is s = r + v·t*, of length d. Drone i is shifted by
    ``gain`` · max(0, 1 − d/``distance``) · s/d, summed over j; j gets the opposite shift from the same pair. A head-on
    approach predicted to meet exactly (d ≈ 0) pushes along r instead.

    Args:
        pos: Positions, shape (W, D, 3).
        vel: Velocities, shape (W, D, 3).
        racing: Whether each drone still races, shape (W, D); others neither push nor are pushed.
        cfg: Filter settings.
    """
    r = pos[:, :, None] - pos[:, None, :]
    v = vel[:, :, None] - vel[:, None, :]
    t = (-(r * v).sum(-1) / v.square().sum(-1).clamp_min(1e-9)).clamp(0.0, cfg.horizon_s)
    s = r + v * t[..., None]
    d = s.norm(dim=-1)
    weight = cfg.gain * (1.0 - d / cfg.distance).clamp_min(0.0) * (racing[:, :, None] & racing[:, None, :])
    direction = torch.where((d > 1e-4)[..., None], s, r)  # a drone's pair with itself has r = 0: no shift
    direction = direction / direction.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    return (weight[..., None] * direction).sum(dim=2)
