"""The step as the reward terms see it (:class:`~spiral.env.rewards.StepOutcome`), from a race env's state and the
step's race events: progress distances, headings, the nearest drones, contacts and their fault, overtakes."""

from __future__ import annotations

import torch

from spiral.env.events import (
    RaceEvents,
    closing_in,
    contact_fault,
    heading,
    nearest_distance,
    overtakes,
)
from spiral.env.rewards import StepOutcome
from spiral.env.state import RaceState
from spiral.sim.state import COLLISION_KINDS

__all__ = ["step_outcome"]


def step_outcome(state: RaceState, ev: RaceEvents) -> StepOutcome:
    """The reward terms' view of the step of ``state``'s env; frozen drones make no progress."""
    racing, zero = ev.racing, torch.zeros_like(ev.dist_before)
    nearest = None
    to_gate = state.gate_center[state.next_gate.long()] - state.pos
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
        contact_fault=_contact_fault(state, ev) if reward.contact > 0 else None,
        closing=closing_in(state.pos, state.vel, state.out, distance=reward.closing_distance, world_count=w,
                           drones_per_world=d) if reward.closing > 0 else None,
        overtakes=_overtakes(state, ev) if reward.overtake > 0 else None,
    )


def _overtakes(state: RaceState, ev: RaceEvents) -> torch.Tensor:
    """Places each drone gained on the other team in the step, in contested races (:func:`overtakes`)."""
    contested = state.contested.repeat_interleave(state.drones_per_world)
    counted = ev.racing & ~ev.crashed_now & ~ev.finished_now & contested
    return overtakes(state.place_before, state.track_place(), counted, state.race_team,
                     world_count=state.world_count, drones_per_world=state.drones_per_world)


def _contact_fault(state: RaceState, ev: RaceEvents) -> torch.Tensor:
    """Each drone's share of the fault for a drone–drone contact this step (:func:`contact_fault`)."""
    contact = ev.crashed_now & ((state.step_collision & COLLISION_KINDS["drone"]) != 0)
    if not state.sync_free and not bool(contact.any()):  # a shortcut where reading the flag costs nothing
        return torch.zeros_like(ev.dist_before)
    pos_before, vel_before = state.before
    return contact_fault(state.pos, pos_before, vel_before, ev.racing, contact, world_count=state.world_count,
                         drones_per_world=state.drones_per_world)
