"""The step as the reward terms see it (:class:`~spiral.env.rewards.StepOutcome`), from a race env's state and the
step's race events: progress distances, headings, the nearest drones, closing in."""

from __future__ import annotations

import torch

from spiral.env.events import RaceEvents, closing_in, heading, nearest_distance
from spiral.env.rewards import StepOutcome
from spiral.env.state import RaceState

__all__ = ["step_outcome"]


def step_outcome(state: RaceState, ev: RaceEvents) -> StepOutcome:
    """The reward terms' view of the step of ``state``'s env; frozen drones make no progress."""
    racing, zero = ev.racing, torch.zeros_like(ev.dist_before)
    nearest = None
    to_gate = state.to_next_gate()
    reward, w, d = state.cfg.reward, state.world_count, state.drones_per_world
    if reward.proximity > 0:
        nearest = nearest_distance(state.pos, state.out, world_count=w, drones_per_world=d)
    return StepOutcome(
        dist_before=torch.where(racing, ev.dist_before, zero),
        dist_after=torch.where(racing, state.gate_distance(ev.gate), zero),
        gates_passed=torch.where(racing, state.step_passes, torch.zeros_like(state.step_passes)),
        crashed_now=ev.crashed_now,
        heading=heading(state.quat),
        to_gate=to_gate,
        lap_time=ev.lap_split,
        nearest=nearest,
        race_result=ev.race_result,
        closing=closing_in(state.pos, state.vel, state.out, distance=reward.closing_distance, world_count=w,
                           drones_per_world=d) if reward.closing > 0 else None,
    )

