"""Seeded start placements: inside the track's start box, or at random points along the track (training)."""

from __future__ import annotations

import math

import torch

from spiral.config.track import TrackSpec

__all__ = ["sample_box_starts", "sample_track_starts"]


def _separated(pos: torch.Tensor, min_sep: float) -> torch.Tensor:
    """Per world (``pos``: (W, D, 3)), whether every pair of drones is at least ``min_sep`` apart."""
    if pos.shape[1] < 2:
        return torch.ones(pos.shape[0], dtype=torch.bool, device=pos.device)
    dist = torch.cdist(pos, pos)
    dist = dist + torch.eye(pos.shape[1], device=pos.device) * 1e9
    return dist.amin(dim=(1, 2)) >= min_sep


def sample_box_starts(
    track: TrackSpec, world_count: int, drones: int, generator: torch.Generator, *, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """Positions (W, D, 3) uniform in the start box with the minimum separation, and yaws (W, D).

    Rejection sampling, redrawing only the worlds that violate the separation, so the result depends only on the
    generator's state. Raises ``ValueError`` when the box cannot hold the drones.
    """
    lo = torch.tensor(track.start.center, device=device) - torch.tensor(track.start.size, device=device) / 2
    size = torch.tensor(track.start.size, device=device)
    pos = lo + torch.rand(world_count, drones, 3, generator=generator, device=device) * size
    for _ in range(200):
        bad = ~_separated(pos, track.start.min_separation)
        if not bad.any():
            break
        redraw = lo + torch.rand(world_count, drones, 3, generator=generator, device=device) * size
        pos = torch.where(bad[:, None, None], redraw, pos)
    else:
        raise ValueError(f"start box of track {track.name!r} cannot hold {drones} drones {track.start.min_separation} m apart")
    yaw = torch.full((world_count, drones), math.radians(track.start.yaw_deg), device=device)
    return pos, yaw


def sample_track_starts(
    track: TrackSpec, world_count: int, drones: int, generator: torch.Generator, *, max_speed: float,
    device: torch.device,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Random points on the centreline segments between consecutive gates, heading for the segment's end gate.

    Returns positions (W, D, 3), velocities along the segment up to ``max_speed`` (W, D, 3), yaws (W, D) and the
    next gate (W, D). Drones of one world draw their points independently.
    """
    centers = torch.tensor(track.gate_centers(), dtype=torch.float32, device=device)
    count = centers.shape[0]
    shape = (world_count, drones)
    target = torch.randint(0, count, shape, generator=generator, device=device)
    origin = centers[(target - 1) % count]
    seg = centers[target] - origin
    u = 0.15 + 0.7 * torch.rand(*shape, 1, generator=generator, device=device)
    jitter = 0.1 * torch.randn(*shape, 3, generator=generator, device=device)
    pos = origin + u * seg + jitter
    direction = seg / seg.norm(dim=-1, keepdim=True)
    speed = max_speed * torch.rand(*shape, 1, generator=generator, device=device)
    yaw = torch.atan2(direction[..., 1], direction[..., 0])
    return pos, direction * speed, yaw, target
