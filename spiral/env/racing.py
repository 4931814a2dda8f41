"""Full races without resets: every drone flies until it finishes, crashes or the time limit."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch

from spiral.core.errors import UsageError
from spiral.core.policy import Policy
from spiral.env.events import at_nearest, contact_partners, fault_share, overtakes
from spiral.env.race_env import RaceEnv, track_place
from spiral.sim import COLLISION_KINDS

__all__ = ["BEARINGS", "RaceResults", "concat_results", "contact_bearing", "run_races"]

BEARINGS = ("ahead", "beside", "behind")
"""Where the other drone of a drone–drone contact was, seen along the crashed drone's direction of travel (the codes
0, 1, 2 of ``RaceResults.contact_bearing``)."""


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
    crash_time: torch.Tensor | None = None
    """Race time of the crash (the simulator's, to the physics substep), 0 when not crashed [s]."""
    crash_partner: torch.Tensor | None = None
    """Slot of the drone touched in a drone–drone contact (the nearest one still racing), else −1."""
    contact_bearing: torch.Tensor | None = None
    """Where that drone was one control step before the contact, by :func:`contact_bearing` (index into
    ``BEARINGS``), else −1."""
    contact_fault: torch.Tensor | None = None
    """That drone's share of the contact by :func:`~spiral.env.events.fault_share` (1: it flew into a drone that
    did not close in, 0.5: both closed in alike or neither), else −1."""
    team: torch.Tensor | None = None
    """Team of each slot, shape (D,)."""
    split_time: torch.Tensor | None = None
    """Race time of each gate passage of the lap, in passing order, shape (W, D, passes); 0 when not passed [s]."""
    racing_steps: torch.Tensor | None = None
    """Control steps the drone raced (W, D)."""
    beyond_steps: torch.Tensor | None = None
    """Of those, the steps in which its commanded action lay beyond the range the env clamps to (|a| > 1), per
    action axis (W, D, 4)."""
    passes: torch.Tensor | None = None
    """Drones of the other team the drone passed in flight, and those that passed it (W, D, 2), places as the
    ``overtake`` reward term counts them (:func:`~spiral.env.events.overtakes`)."""
    laps: int = 1
    """Laps of the races (``split_time`` holds ``laps`` × gates + 1 passages)."""

    def permuted(self, order: list[int]) -> RaceResults:
        """The same races with the drones reordered: slot ``j`` of the result is slot ``order[j]`` of these.

        Contact partners are renamed to the new slots; ``team`` stays with the slot position (slot ``j`` keeps the
        team it had), so swapping two equal teams' slots swaps which drones fly for which team.
        """
        d = self.finished.shape[1]
        if sorted(order) != list(range(d)):
            raise ValueError(f"order: expected a permutation of 0..{d - 1}, got {order}")
        idx = torch.tensor(order)
        new_slot = torch.empty_like(idx)
        new_slot[idx] = torch.arange(d)
        changes = {f.name: getattr(self, f.name).index_select(_SLOT_DIM.get(f.name, 1), idx) for f in fields(self)
                   if f.name not in _PER_RACE_SET and getattr(self, f.name) is not None}
        if self.crash_partner is not None:
            p = changes["crash_partner"]
            changes["crash_partner"] = torch.where(p >= 0, new_slot[p.clamp(min=0)], p)
        return replace(self, **changes)


_PER_RACE_SET = ("team", "laps")
"""Fields of :class:`RaceResults` that hold for every race of a set (neither reordered by slot nor joined)."""
_SLOT_DIM = {"trajectory": 2}
"""Dimension of the slot in each per-drone field of :class:`RaceResults` where it is not 1."""


def run_races(env: RaceEnv, policy: Policy, *, record: bool = False,
              teams: list[list[int]] | None = None) -> RaceResults:
    """Race every world of a non-resetting ``env`` once from a fresh reset, ``policy`` driving the learner slots.

    ``teams`` lists the slots of each team (default: the learner slots against the opponent slots); a self-match,
    where every slot is a learner, passes the scenario's teams.
    """
    if env.training:
        raise ValueError("run_races needs a RaceEnv built with training=False")
    if len({track.laps for track in env.tracks}) > 1:
        raise UsageError(f"run_races: the env's tracks race different lap counts "
                         f"({', '.join(f'{t.name}: {t.laps}' for t in env.tracks)}); give the env one (episode.laps)")
    obs = env.reset()
    team = (env.slot_team.cpu() if teams is None else _team_of_slots(teams, env.drones_per_world)).to(env.device)
    tally = _RaceTally(env, team, record=record)
    for _ in range(env.max_episode_length):
        before, vel_before = env.pos.clone(), env.vel.clone()
        racing = env.records.racing()
        with torch.no_grad():
            obs, _, _, _ = env.step(policy(obs))
        tally.note_step(env, racing, before, vel_before)
        if not bool(env.records.racing().any()):
            break
    return tally.results(env)


class _RaceTally:
    """What :func:`run_races` counts for each drone (flat, on the env's device) while the races run."""

    def __init__(self, env: RaceEnv, team: torch.Tensor, *, record: bool) -> None:
        n, dev = env.drone_count, env.device
        self.distance = torch.zeros(n, device=dev)
        self.partner = torch.full((n,), -1, dtype=torch.long, device=dev)
        self.bearing = torch.full((n,), -1, dtype=torch.long, device=dev)
        self.fault = torch.full((n,), -1.0, device=dev)
        self.splits = torch.zeros(n, env.passes_needed, device=dev)
        self.steps = torch.zeros(n, dtype=torch.long, device=dev)
        self.beyond = torch.zeros_like(env.commanded, dtype=torch.long)
        self.passed, self.place = env.gates_passed.clone(), track_place(env)
        self.team = team
        """Team of each slot, (D,)."""
        self.passes = torch.zeros(n, 2, dtype=torch.long, device=dev)
        self.frames = [env.pos.clone()] if record else None
        """Positions after the reset and after every step, when recorded."""

    def note_step(self, env: RaceEnv, racing: torch.Tensor, before: torch.Tensor, vel_before: torch.Tensor) -> None:
        """Count the step just taken by the ``racing`` drones, which were at ``before`` with ``vel_before``."""
        self.passes, self.place = _note_passes(env, self.place, racing, self.team, self.passes)
        self.steps += racing
        self.beyond += racing[:, None] & (env.commanded.abs() > 1.0)
        self.distance += (env.pos - before).norm(dim=-1)
        self.passed, self.splits = _note_splits(env, self.passed, self.splits)
        self.partner, self.bearing, self.fault = _note_contacts(env, racing, before, vel_before, self.partner,
                                                                self.bearing, self.fault)
        if self.frames is not None:
            self.frames.append(env.pos.clone())

    def results(self, env: RaceEnv) -> RaceResults:
        """The races as they ended, shaped (W, D) on the CPU."""
        w, d = env.world_count, env.drones_per_world

        def grid(x: torch.Tensor) -> torch.Tensor:
            return x.view(w, d).cpu()

        return RaceResults(
            finished=grid(env.records.finished),
            crashed=grid(env.records.crashed),
            crash_kind=grid(env.records.crash_kind),
            lap_time=grid(env.records.lap_time),
            gates_passed=grid(env.gates_passed),
            distance=grid(self.distance),
            present=grid(~env.records.absent),
            trajectory=torch.stack(self.frames).view(-1, w, d, 3).cpu() if self.frames is not None else None,
            crash_time=grid(torch.where(env.records.crashed, env.crash_time, 0.0)),
            crash_partner=grid(self.partner),
            contact_bearing=grid(self.bearing),
            contact_fault=grid(self.fault),
            team=self.team.cpu(),
            split_time=self.splits.view(w, d, -1).cpu(),
            racing_steps=grid(self.steps),
            beyond_steps=self.beyond.view(w, d, -1).cpu(),
            passes=self.passes.view(w, d, 2).cpu(), laps=env.track.laps,
        )


def _note_splits(env: RaceEnv, passed: torch.Tensor, splits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The gates passed so far and ``splits`` (N, passes) with the race time of this step's gate passages filled in,
    given the gates ``passed`` before the step."""
    if not bool((env.gates_passed != passed).any()):
        return passed, splits
    k = torch.arange(env.passes_needed, device=env.device)
    now = (passed[:, None] <= k) & (env.gates_passed[:, None] > k)
    return env.gates_passed.clone(), torch.where(now, env.pass_time[:, None], splits)


def _note_passes(env: RaceEnv, place: tuple[torch.Tensor, torch.Tensor], racing: torch.Tensor, team: torch.Tensor,
                 passes: torch.Tensor) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
    """``passes`` (N, 2) plus the drones of other teams each ``racing`` drone passed and was passed by in this step,
    from its :func:`~spiral.env.race_env.track_place` before it (``place``; ``team`` per slot, (D,)), and the place
    after the step, which is the next step's place before it."""
    after = track_place(env)
    still = racing & ~(env.records.finished | env.records.crashed)
    gained = overtakes(place, after, still, team, world_count=env.world_count,
                       drones_per_world=env.drones_per_world).long()
    return passes + torch.stack([gained.clamp(min=0), (-gained).clamp(min=0)], dim=-1), after


def _note_contacts(env: RaceEnv, racing: torch.Tensor, before: torch.Tensor, vel_before: torch.Tensor,
                   partner: torch.Tensor, bearing: torch.Tensor, fault: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``partner``, ``bearing`` and ``fault`` with this step's drone–drone crashes of ``racing`` drones filled in:
    the other drone (the nearest one that was still racing), where it was at ``before`` / ``vel_before``, and how
    much of the contact the drone flew into."""
    contact = racing & env.records.crashed & ((env.records.crash_kind & COLLISION_KINDS["drone"]) != 0)
    if not contact.any():
        return partner, bearing, fault
    near, found, rel = contact_partners(env.pos, before, racing, world_count=env.world_count,
                                        drones_per_world=env.drones_per_world)
    noted = contact & found.flatten()
    share = fault_share(rel, vel_before, at_nearest(vel_before, near))
    return (torch.where(contact, torch.where(found, near, -1).flatten(), partner),
            torch.where(noted, contact_bearing(rel, vel_before), bearing), torch.where(noted, share, fault))


def concat_results(parts: list[RaceResults]) -> RaceResults:
    """The races of ``parts`` one after another (same drones per race and teams; trajectories are not joined)."""
    if not parts:
        raise ValueError("concat_results needs at least one RaceResults")
    first = parts[0]
    if any(p.trajectory is not None for p in parts):
        raise ValueError("concat_results: recorded trajectories differ in length and are not joined")
    if any(p.finished.shape[1] != first.finished.shape[1] for p in parts):
        raise ValueError("concat_results: the parts race different numbers of drones")
    if any(p.laps != first.laps for p in parts):
        raise ValueError("concat_results: the parts race different numbers of laps")
    if any((p.team is None) != (first.team is None) or (p.team is not None and not torch.equal(p.team, first.team))
           for p in parts):
        raise ValueError("concat_results: the parts have different teams")

    joined = {}
    for f in fields(RaceResults):
        values = [getattr(p, f.name) for p in parts]
        if f.name not in _PER_RACE_SET:
            joined[f.name] = None if any(v is None for v in values) else torch.cat(values)
    return replace(first, **joined)


def contact_bearing(rel: torch.Tensor, vel: torch.Tensor) -> torch.Tensor:
    """Where another drone at offset ``rel`` (N, 3) lies for a drone flying at ``vel`` (N, 3): 0 ahead (within 45°
    of the direction of travel), 2 behind (within 45° of the opposite), 1 beside (the rest, and any drone next to
    one that stands still)."""
    speed = vel.norm(dim=-1, keepdim=True)
    heading = vel / speed.clamp(min=1e-9)
    along = (rel * heading).sum(-1)
    across = (rel - along[:, None] * heading).norm(dim=-1)
    moving = speed.squeeze(-1) > 1e-6
    code = torch.ones_like(along, dtype=torch.long)
    code = torch.where(moving & (along > across), 0, code)
    return torch.where(moving & (along < -across), 2, code)


def _team_of_slots(teams: list[list[int]], drones: int) -> torch.Tensor:
    team = torch.zeros(drones, dtype=torch.long)
    for i, slots in enumerate(teams):
        team[slots] = i
    return team

