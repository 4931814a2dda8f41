"""Measurements of a race step: progress distance to a gate, heading, the nearest other drone, a race's result."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from spiral.core.outcome import race_winner
from spiral.env.observations import nearest_others, relative_to_others

__all__ = ["RaceEvents", "at_nearest", "at_neighbours", "closing_in", "contact_partners",
           "fault_share", "gate_distance", "heading", "lap_splits", "nearest_distance", "overtakes",
           "race_result"]


@dataclass(frozen=True)
class RaceEvents:
    """What happened to every drone (N,) in one control step, as the race bookkeeping saw it."""

    racing: torch.Tensor
    """Still racing at the start of the step (neither crashed, finished nor absent)."""
    crashed_now: torch.Tensor
    """Collided during the step."""
    finished_now: torch.Tensor
    """Completed the race during the step, without a collision."""
    gate: torch.Tensor
    """The gate each drone targeted at the start of the step."""
    dist_before: torch.Tensor
    """Progress distance to that gate before the step [m]."""
    race_result: torch.Tensor | None
    """+1 / −1 per drone of the winning / losing race team where a contested race was decided this step (None
    unless the win reward needs it)."""
    lap_split: torch.Tensor | None = None
    """Duration of the lap each drone completed during the step, else 0 [s] (:func:`lap_splits`)."""


def _laps_closed(passed: torch.Tensor, gates: int | torch.Tensor) -> torch.Tensor:
    """Laps closed after ``passed`` gate passages of a race whose first passage is its start line."""
    return torch.div((passed - 1).clamp(min=0), gates, rounding_mode="floor")


def lap_splits(gates_passed: torch.Tensor, step_passes: torch.Tensor, pass_time: torch.Tensor,
               lap_start: torch.Tensor, counted: torch.Tensor, gates: int | torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """The laps ``counted`` drones completed during a step: a race's first passage crosses its start line and every
    ``gates`` passages after it (a count, or each drone's (N,)) close a lap. Returns each drone's lap duration,
    passage time less ``lap_start`` (0 for drones without a lap in the step), and the updated lap starts (the passage
    time where a lap closed) [s]. Over a one-lap race the only split is the race time."""
    closed = counted & (_laps_closed(gates_passed, gates) > _laps_closed(gates_passed - step_passes, gates))
    split = torch.where(closed, pass_time - lap_start, torch.zeros_like(pass_time))
    return split, torch.where(closed, pass_time, lap_start)


def heading(quat: torch.Tensor) -> torch.Tensor:
    """Body x axis in the world frame from (x, y, z, w) quaternions."""
    x, y, z, w = quat.unbind(-1)
    return torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], dim=-1)


def gate_distance(pos: torch.Tensor, center: torch.Tensor, forward: torch.Tensor, kappa: float) -> torch.Tensor:
    """Funnel distance sqrt(a² + κ²·l²) of every drone to its gate (``center``, ``forward`` per drone): a along the
    gate's normal, l across it.

    With κ > 1 lateral error costs more than distance along the normal, so progress pays for lining up in front of
    a gate before crossing its plane rather than for a straight line into its frame.
    """
    rel = pos - center
    along = (rel * forward).sum(-1, keepdim=True)
    lateral = rel - along * forward
    return (along.squeeze(-1) ** 2 + kappa**2 * (lateral**2).sum(-1)).sqrt()


def nearest_distance(pos: torch.Tensor, out: torch.Tensor, *, world_count: int, drones_per_world: int
                     ) -> torch.Tensor:
    """Distance of every racing drone to the nearest other drone of its world still racing (else inf)."""
    w, d = world_count, drones_per_world
    dist = torch.cdist(pos.view(w, d, 3), pos.view(w, d, 3))
    gone_w = (out != 0).view(w, d)
    gone = torch.eye(d, dtype=torch.bool, device=pos.device)[None] | gone_w[:, None, :] | gone_w[:, :, None]
    return dist.masked_fill(gone, float("inf")).amin(dim=-1).flatten()


def contact_partners(pos: torch.Tensor, pos_before: torch.Tensor, racing: torch.Tensor, *, world_count: int,
                     drones_per_world: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The other drone of each drone's contact in a step: the nearest one (at ``pos``, after the step) of those
    ``racing`` before it. Its slot (W, D, 1), whether there is one (W, D, 1), and its offset one step before (at
    ``pos_before``; (N, 3), zero where there is none)."""
    w, d = world_count, drones_per_world
    index, found = nearest_others(pos.view(w, d, 3), racing.view(w, d), count=1)
    return index, found, relative_to_others(pos_before, index, found).view(-1, 3)


def closing_in(pos: torch.Tensor, vel: torch.Tensor, out: torch.Tensor, *, distance: float, world_count: int,
               drones_per_world: int) -> torch.Tensor:
    """How fast each racing drone closes in on its nearest racing drone, times its share and the nearness (N,)
    [m/s]; 0 for the drones without a racing neighbour and for those out of the race.

    With u the unit offset to the other drone, the two close in at r = max(0, (v − v_other)·u); the drone's part of
    it is its :func:`fault_share`, and it counts in full at contact and not at all from ``distance`` away:
    r · share · max(0, 1 − d / distance). A drone that runs up on a slower one ahead takes all of it, the one
    ahead none; two drones converging alike half each.
    """
    racing = out == 0
    index, found = nearest_others(pos.view(world_count, drones_per_world, 3),
                                  racing.view(world_count, drones_per_world), count=1)
    offset = at_neighbours(pos, index) - pos[:, None]  # (N, k, 3)
    other_vel = at_neighbours(vel, index)
    rel = vel[:, None] - other_vel
    dist = offset.norm(dim=-1)
    rate = (rel * offset).sum(-1).clamp(min=0.0) / dist.clamp(min=1e-9)
    near = (1.0 - dist / distance).clamp(min=0.0)
    value = rate * fault_share(offset, vel[:, None], other_vel) * near
    counted = found.view(-1, 1) & racing[:, None]
    return torch.where(counted, value, torch.zeros_like(value)).sum(-1)


def overtakes(before: tuple[torch.Tensor, torch.Tensor], after: tuple[torch.Tensor, torch.Tensor],
              counted: torch.Tensor, race_team: torch.Tensor, *, world_count: int, drones_per_world: int
              ) -> torch.Tensor:
    """Places each drone gained on the other race team's drones in one step (N,): how many of them were ahead of it
    before the step and are not after it, less how many it had behind it and has ahead of it after.

    A place on the track is ``(gates_passed, distance to the next gate)``, before and after the step (each (N,)):
    more gates passed is ahead, then the nearer to the next gate. Only ``counted`` drones (N,; racing before and
    after the step) pass and are passed, so a drone gains nothing when the one ahead crashes or finishes.
    """
    w, d = world_count, drones_per_world
    both = counted.view(w, d)
    rivals = (race_team[:, None] != race_team[None, :])[None] & both[:, :, None] & both[:, None, :]

    def ahead_of_me(place: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
        passed, dist = (x.view(w, d) for x in place)
        ahead = (passed[:, None, :] > passed[:, :, None]) | (
            (passed[:, None, :] == passed[:, :, None]) & (dist[:, None, :] < dist[:, :, None]))
        return (ahead & rivals).sum(-1)  # (W, D): rivals ahead of drone i

    return (ahead_of_me(before) - ahead_of_me(after)).flatten().float()


def at_nearest(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Per-drone vectors ``x`` (N, 3, world-major) of each drone's nearest other drone, whose slot ``index`` (W, D, 1)
    :func:`~spiral.env.observations.nearest_others` found; (N, 3)."""
    return at_neighbours(x, index).view(-1, 3)


def at_neighbours(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Per-drone vectors ``x`` (N, 3, world-major) of each drone's k nearest other drones, whose slots ``index``
    (W, D, k) :func:`~spiral.env.observations.nearest_others` found; (N, k, 3)."""
    w, d, k = index.shape
    return torch.gather(x.view(w, d, 3), 1, index.reshape(w, d * k, 1).expand(-1, -1, 3)).view(w * d, k, 3)


def fault_share(offset: torch.Tensor, vel: torch.Tensor, other_vel: torch.Tensor) -> torch.Tensor:
    """How much of a contact each drone flew into (N,), given the ``offset`` (N, 3) to the other drone and the two
    drones' velocities ``vel`` and ``other_vel`` (N, 3), all at one moment (one step before a contact).

    With u the unit offset to the other drone and v the drone's velocity, it flew c = max(0, v·u) into the other;
    its share is c / (c + c_other), half each when neither closed in.
    """
    u = offset / offset.norm(dim=-1, keepdim=True).clamp(min=1e-9)
    closing = (vel * u).sum(-1).clamp(min=0.0)
    total = closing + (-(other_vel * u).sum(-1)).clamp(min=0.0)
    return torch.where(total > 0, closing / total.clamp(min=1e-9), torch.full_like(total, 0.5))


def race_result(finished_now: torch.Tensor, lap_time: torch.Tensor, racing: torch.Tensor, contested: torch.Tensor,
                race_team: torch.Tensor, teams: Sequence[Sequence[int]]) -> tuple[torch.Tensor, torch.Tensor]:
    """+1 / −1 per racing drone of the winning / losing race team in the ``contested`` worlds decided this step
    (N,), and which worlds were decided (W,).

    The winner (:func:`~spiral.core.outcome.race_winner`) is the team of the step's earliest finisher (lap times
    are interpolated within the step); drones already out (crashed, finished, absent) are not paid, nor anyone when
    two teams finish at exactly the same time.
    """
    w, d = contested.shape[0], race_team.shape[0]
    fin = finished_now.view(w, d)
    decided = contested & fin.any(dim=1)
    result = torch.zeros(w, d, device=contested.device)
    winner = race_winner(fin, lap_time.view(w, d), teams)  # for every world: its pay is masked, its count not read
    same_team = race_team[None, :] == winner[:, None]
    paid = decided[:, None] & (winner >= 0)[:, None] & racing.view(w, d)
    result = result + torch.where(same_team, 1.0, -1.0) * paid
    return result.flatten(), decided
