"""Seeded start placements: inside the track's start box, or at random points along the track (training)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from spiral.config.env import EpisodeCfg
from spiral.config.track import TrackSpec

__all__ = ["Starts", "draw_starts", "sample_box_starts", "sample_track_starts"]


def _place_sequentially(
    lo: torch.Tensor, size: torch.Tensor, pos: torch.Tensor, todo: torch.Tensor, drones: int, min_sep: float,
    generator: torch.Generator, candidates: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Place the drones of the worlds in ``todo`` one by one; return positions and the worlds that got stuck."""
    w = pos.shape[0]
    new = pos.clone()
    stuck = torch.zeros(w, dtype=torch.bool, device=pos.device)
    for j in range(drones):
        cand = lo + torch.rand(w, candidates, 3, generator=generator, device=pos.device) * size
        if j == 0:
            new[:, 0] = cand[:, 0]
            continue
        ok = torch.cdist(cand, new[:, :j]).amin(dim=-1) >= min_sep
        stuck |= ~ok.any(dim=1)
        new[:, j] = cand[torch.arange(w, device=pos.device), ok.float().argmax(dim=1)]
    return torch.where(todo[:, None, None], new, pos), stuck & todo


def sample_box_starts(
    track: TrackSpec, world_count: int, drones: int, generator: torch.Generator, *, device: torch.device,
    candidates: int = 256,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Positions (W, D, 3) uniform in the start box with the minimum separation, and yaws (W, D).

    Drones are placed one after another: each takes the first of ``candidates`` uniform draws that keeps the
    separation from the drones already placed; a world that gets stuck starts over. The result depends only on
    the generator's state. Raises ``ValueError`` when the box cannot hold the drones.
    """
    lo = torch.tensor(track.start.center, device=device) - torch.tensor(track.start.size, device=device) / 2
    size = torch.tensor(track.start.size, device=device)
    pos = torch.zeros(world_count, drones, 3, device=device)
    todo = torch.ones(world_count, dtype=torch.bool, device=device)
    for _ in range(50):  # worlds whose sequential placement got stuck start over
        pos, stuck = _place_sequentially(lo, size, pos, todo, drones, track.start.min_separation, generator,
                                         candidates)
        todo = stuck
        if not todo.any():
            break
    else:
        raise ValueError(f"start box of track {track.name!r} cannot hold {drones} drones "
                         f"{track.start.min_separation} m apart")
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


@dataclass(frozen=True)
class Starts:
    """Start states of the drones of some worlds."""

    pos: torch.Tensor
    """Positions (W, D, 3)."""
    vel: torch.Tensor
    """Velocities (W, D, 3)."""
    yaw: torch.Tensor
    """Yaws (W, D)."""
    gate: torch.Tensor
    """Next gate (W, D), int32."""
    box: torch.Tensor
    """Whether each world starts in the start box (W,), else along the track."""


def draw_starts(track: TrackSpec, episode: EpisodeCfg, world_count: int, drones: int, generator: torch.Generator, *,
                training: bool, device: torch.device) -> Starts:
    """Starts in the start box, and in training a share ``episode.track_start_prob`` of worlds along the track.

    The draws depend only on the generator's state: box placements for every world first, then track starts and
    the choice between them (training with track starts only).
    """
    pos, yaw = sample_box_starts(track, world_count, drones, generator, device=device)
    vel = torch.zeros_like(pos)
    gate = torch.zeros(world_count, drones, dtype=torch.int32, device=device)
    box = torch.ones(world_count, dtype=torch.bool, device=device)
    if training and episode.track_start_prob > 0:
        t_pos, t_vel, t_yaw, t_gate = sample_track_starts(
            track, world_count, drones, generator, max_speed=episode.track_start_speed, device=device)
        use = (torch.rand(world_count, generator=generator, device=device) < episode.track_start_prob)
        pos, vel = torch.where(use[:, None, None], t_pos, pos), torch.where(use[:, None, None], t_vel, vel)
        yaw, gate = torch.where(use[:, None], t_yaw, yaw), torch.where(use[:, None], t_gate.int(), gate)
        box = ~use
    return Starts(pos, vel, yaw, gate, box)
