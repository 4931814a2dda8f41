"""Full races without resets: every drone flies until it finishes, crashes or the time limit."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDict

from spiral.env.race_env import RaceEnv

__all__ = ["RaceResults", "race_winners", "run_races"]

Policy = Callable[[TensorDict], torch.Tensor]
"""Deterministic policy: observations of the learner drones -> actions."""


@dataclass
class RaceResults:
    """Per-drone outcome of ``world_count`` races, tensors shaped (W, D) on the CPU."""

    finished: torch.Tensor
    """Completed the lap(s) without a collision."""
    crashed: torch.Tensor
    """Collided before finishing."""
    crash_kind: torch.Tensor
    """Collision bits (see ``spiral.sim.COLLISION_KINDS``)."""
    lap_time: torch.Tensor
    """Time of the finishing gate crossing, 0 when not finished [s]."""
    gates_passed: torch.Tensor
    """Gates passed in order."""
    distance: torch.Tensor
    """Path length flown [m]."""
    present: torch.Tensor
    """Slot took part in the race."""
    trajectory: torch.Tensor | None = None
    """Positions (T, W, D, 3) when recorded."""


def run_races(env: RaceEnv, policy: Policy, *, record: bool = False) -> RaceResults:
    """Race every world of a non-resetting ``env`` once from a fresh reset, ``policy`` driving the learner slots."""
    if env.auto_reset:
        raise ValueError("run_races needs a RaceEnv built with auto_reset=False")
    obs = env.reset()
    w, d = env.world_count, env.drones_per_world
    distance = torch.zeros(env.drone_count, device=env.device)
    frames = [env.pos.clone()] if record else []
    for _ in range(env.max_episode_length):
        before = env.pos.clone()
        with torch.no_grad():
            obs, _, _, _ = env.step(policy(obs))
        distance += (env.pos - before).norm(dim=-1)
        if record:
            frames.append(env.pos.clone())
        if bool((env.finished | env.crashed | env.absent).all()):
            break

    def grid(x: torch.Tensor) -> torch.Tensor:
        return x.view(w, d).cpu()

    return RaceResults(
        finished=grid(env.finished),
        crashed=grid(env.crashed),
        crash_kind=grid(env.crash_kind),
        lap_time=grid(env.lap_time),
        gates_passed=grid(env.gates_passed),
        distance=grid(distance),
        present=grid(~env.absent),
        trajectory=torch.stack(frames).view(-1, w, d, 3).cpu() if record else None,
    )


def race_winners(res: RaceResults, teams: list[list[int]]) -> torch.Tensor:
    """Index of the winning team of each race (its first drone to finish finished first), −1 when nobody finished."""
    t = torch.where(res.finished, res.lap_time, torch.full_like(res.lap_time, float("inf")))
    best = torch.stack([t[:, slots].amin(dim=1) for slots in teams], dim=1)
    first = best.amin(dim=1)
    winner = best.argmin(dim=1)
    return torch.where(torch.isfinite(first), winner, torch.full_like(winner, -1))
