"""What a drone observes: named observation terms, the history buffer, and the layout of named slices.

A drone's observation vector is its enabled terms of :data:`OBS_TERMS` concatenated in that order: ``ego`` (12:
position, velocity, roll/pitch/yaw, body rates), ``presence`` (2: whether the 2 nearest drones exist), then the
optional ``gate_normals`` (6), ``pid_integral`` (3), ``opponent_velocity`` (6), ``teammates`` (2),
``closest_approach`` (8) (each switched on in ``ObsCfg``), and ``history`` (K entries of
16, oldest first: :data:`HISTORY_FIELDS`). :meth:`ObservationBuilder.slices` says where each term sits; checkpoints
store it, and the order and values never change for a given ``ObsCfg`` (trained policies depend on them).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDict

from spiral.config.env import EnvCfg, ObsCfg

__all__ = [
    "HISTORY_FEATURES",
    "HISTORY_FIELDS",
    "OBS_TERMS",
    "Neighbours",
    "ObsSource",
    "ObsState",
    "ObsTerm",
    "ObservationBuilder",
    "Observer",
    "history_entry",
    "nearest_others",
    "neighbours",
    "other_drone_columns",
    "relative_to_others",
]

HISTORY_FEATURES = 16
"""Per history entry: 2 nearest drones' relative positions (6), next 2 gates' relative positions (6), action (4)."""

HISTORY_FIELDS: dict[str, tuple[int, int]] = {"opponents": (0, 6), "gates": (6, 12), "action": (12, 16)}
"""Where each field sits in one history entry: name -> (start, stop)."""


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


@dataclass(frozen=True)
class Neighbours:
    """What each drone looks at: its 2 nearest drones still racing and its next 2 gates."""

    idx: torch.Tensor
    """Slots of the nearest drones in their world (W, D, 2); 0 where absent."""
    mask: torch.Tensor
    """Whether each of them exists (W, D, 2)."""
    gates: torch.Tensor
    """Rows of the next gate and the one after in the env's gate arrays (N, 2) (track-major over its tracks)."""

    def relative(self, x: torch.Tensor) -> torch.Tensor:
        """Per-drone vectors ``x`` (N, 3) of the nearest drones minus the drone's own, zero where absent: (W, D, 2,
        3)."""
        return relative_to_others(x, self.idx, self.mask)


def relative_to_others(x: torch.Tensor, idx: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-drone vectors ``x`` (N, 3, world-major) of other drones of the same world minus the drone's own, zero
    where ``mask`` is False: ``idx`` (W, D, K) are their slots (as :func:`nearest_others` returns them); shape
    (W, D, K, 3)."""
    w, d, k = idx.shape
    x_w = x.view(w, d, 3)
    other = torch.gather(x_w, 1, idx.view(w, -1, 1).expand(-1, -1, 3)).view(w, d, k, 3)
    return (other - x_w[:, :, None]) * mask[..., None]


def neighbours(pos: torch.Tensor, out: torch.Tensor, next_gate: torch.Tensor, gate_count: torch.Tensor,
               gate_base: torch.Tensor, *, world_count: int, drones_per_world: int) -> Neighbours:
    """The nearest drones still racing (``out == 0``) and the next 2 gates of every drone, whose track has
    ``gate_count`` gates (N,) from row ``gate_base`` (N,) of the gate arrays on."""
    w, d = world_count, drones_per_world
    near_idx, near_mask = nearest_others(pos.view(w, d, 3), (out == 0).view(w, d))
    gates = torch.stack([next_gate.long(), (next_gate.long() + 1) % gate_count], 1)
    return Neighbours(near_idx, near_mask, gates + gate_base[:, None])


def _rows_of(table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``table[index]`` for a table of rows (R, C) and an ``index`` of any shape: one ``index_select``, a cheaper copy
    of the same rows than advanced indexing on a CPU."""
    return table.index_select(0, index.reshape(-1)).view(*index.shape, table.shape[1])


def history_entry(pos: torch.Tensor, near: Neighbours, gate_center: torch.Tensor, last_action: torch.Tensor
                  ) -> torch.Tensor:
    """This step's history entry of every drone (N, 16): :data:`HISTORY_FIELDS` ``opponents``, ``gates``,
    ``action``."""
    rel_opp = near.relative(pos)
    rel_gates = _rows_of(gate_center, near.gates) - pos[:, None]
    return torch.cat([rel_opp.view(-1, 6), rel_gates.view(-1, 6), last_action], dim=-1)


@dataclass(frozen=True)
class ObsState:
    """What the observation terms read: every drone's state (flat, world-major) and what it looks at."""

    pos: torch.Tensor
    vel: torch.Tensor
    rpy: torch.Tensor
    omega: torch.Tensor
    integral: torch.Tensor
    """The position controller's integral state (N, 3)."""
    race_team: torch.Tensor
    """Race team of each slot (D,)."""
    gate_forward: torch.Tensor
    """Passing direction of every gate (G, 3)."""
    near: Neighbours
    history: torch.Tensor
    """Observed history entries, oldest first (N, K, 16)."""


def _ego(s: ObsState, cfg: ObsCfg) -> torch.Tensor:
    return torch.cat([s.pos, s.vel, s.rpy, s.omega], dim=-1)


def _presence(s: ObsState, cfg: ObsCfg) -> torch.Tensor:
    return s.near.mask.view(-1, 2).float()


def _gate_normals(s: ObsState, cfg: ObsCfg) -> torch.Tensor:
    return _rows_of(s.gate_forward, s.near.gates).view(-1, 6)


def _pid_integral(s: ObsState, cfg: ObsCfg) -> torch.Tensor:
    return s.integral


def _opponent_velocity(s: ObsState, cfg: ObsCfg) -> torch.Tensor:
    return s.near.relative(s.vel).view(-1, 6)


def _teammates(s: ObsState, cfg: ObsCfg) -> torch.Tensor:
    mate = s.race_team[s.near.idx] == s.race_team[None, :, None]
    return (mate & s.near.mask).view(-1, 2).float()


def _closest_approach(s: ObsState, cfg: ObsCfg) -> torch.Tensor:
    """Per nearest drone (N, 2 · 4): its position relative to the drone at their closest approach within the
    horizon, both at constant velocity, and the time of that approach over the horizon (zeros when absent)."""
    rel, rel_vel = s.near.relative(s.pos), s.near.relative(s.vel)
    horizon = cfg.approach_horizon_s
    t = (-(rel * rel_vel).sum(-1) / rel_vel.square().sum(-1).clamp_min(1e-9)).clamp(0.0, horizon)
    miss = rel + rel_vel * t[..., None]
    return torch.cat([miss, (t / horizon)[..., None]], dim=-1).view(-1, 8)


def _history(s: ObsState, cfg: ObsCfg) -> torch.Tensor:
    return s.history.flatten(1)


@dataclass(frozen=True)
class ObsTerm:
    """One observation feature: its width for an ``ObsCfg`` (0: switched off) and how it is computed."""

    width: Callable[[ObsCfg], int]
    compute: Callable[[ObsState, ObsCfg], torch.Tensor]


OBS_TERMS: dict[str, ObsTerm] = {
    "ego": ObsTerm(lambda c: 12, _ego),
    "presence": ObsTerm(lambda c: 2, _presence),
    "gate_normals": ObsTerm(lambda c: 6 * c.gate_normals, _gate_normals),
    "pid_integral": ObsTerm(lambda c: 3 * c.pid_integral, _pid_integral),
    "opponent_velocity": ObsTerm(lambda c: 6 * c.opponent_velocity, _opponent_velocity),
    "teammates": ObsTerm(lambda c: 2 * c.teammates, _teammates),
    "closest_approach": ObsTerm(lambda c: 8 * c.closest_approach, _closest_approach),
    "history": ObsTerm(lambda c: c.history_len * HISTORY_FEATURES, _history),
}
"""Observation terms by name, in the order they are concatenated (the order is part of every trained policy)."""


class ObservationBuilder:
    """Keeps every drone's history buffer and concatenates its enabled observation terms."""

    def __init__(self, cfg: ObsCfg, drone_count: int, *, device: torch.device) -> None:
        self.cfg = cfg
        self.terms = [name for name, term in OBS_TERMS.items() if term.width(cfg) > 0]
        """Names of the enabled terms, in observation order."""
        self.length = cfg.history_len
        self.history = torch.zeros(drone_count, self.length, HISTORY_FEATURES, device=device)
        """Feature history (N, K, 16), oldest first."""

    @property
    def obs_dim(self) -> int:
        """Length of one drone's observation vector."""
        return sum(OBS_TERMS[name].width(self.cfg) for name in self.terms)

    def slices(self) -> dict[str, tuple[int, int]]:
        """Where each enabled term sits in the observation vector: name -> (start, stop), in order."""
        out, start = {}, 0
        for name in self.terms:
            stop = start + OBS_TERMS[name].width(self.cfg)
            out[name], start = (start, stop), stop
        return out

    def select(self, obs: torch.Tensor, name: str) -> torch.Tensor:
        """The columns of term ``name`` in observation rows ``obs`` (..., obs_dim)."""
        start, stop = self.slices()[name]
        return obs[..., start:stop]

    def select_history(self, obs: torch.Tensor, field: str) -> torch.Tensor:
        """Field ``field`` of :data:`HISTORY_FIELDS` of every observed history entry in observation rows ``obs``
        (..., obs_dim): shape (..., K, width), oldest entry first."""
        start, stop = HISTORY_FIELDS[field]
        entries = self.select(obs, "history").unflatten(-1, (self.cfg.history_len, HISTORY_FEATURES))
        return entries[..., start:stop]

    def layout(self) -> dict:
        """Description of the observation vector, stored in checkpoints to refuse mismatched policies."""
        return {"obs_dim": self.obs_dim, **self.cfg.model_dump()}

    def push(self, features: torch.Tensor, fresh: torch.Tensor) -> None:
        """Append this step's features; drones in ``fresh`` (bool, N) start a new history filled with them."""
        shifted = torch.cat([self.history[:, 1:], features[:, None, :]], dim=1)  # one pass over the history
        self.history.copy_(torch.where(fresh[:, None, None], features[:, None, :], shifted))

    def observed_history(self) -> torch.Tensor:
        """The observed history entries (N, K, 16), oldest first."""
        return self.history

    def build(self, state: ObsState) -> torch.Tensor:
        """Concatenate the observation of every drone, shape (N, obs_dim)."""
        return torch.cat([OBS_TERMS[name].compute(state, self.cfg) for name in self.terms], dim=-1)


OTHER_DRONE_TERMS = ("presence", "opponent_velocity", "teammates", "closest_approach")
"""Terms that describe only the other drones: all zero where none is near (in a solo world)."""


def other_drone_columns(cfg: ObsCfg) -> torch.Tensor:
    """Bool mask (obs_dim,) of the observation entries about other drones: the terms of :data:`OTHER_DRONE_TERMS`,
    and the ``opponents`` field of every history entry. Zeroing them shows a
    drone what it would observe with no other drone in its world."""
    builder = ObservationBuilder(cfg, 0, device=torch.device("cpu"))
    mask = torch.zeros(builder.obs_dim, dtype=torch.bool)
    for name, (start, stop) in builder.slices().items():
        if name in OTHER_DRONE_TERMS:
            mask[start:stop] = True
        elif name == "history":
            first, last = HISTORY_FIELDS["opponents"]
            entries = mask[start:stop].view(cfg.history_len, HISTORY_FEATURES)
            entries[:, first:last] = True
    return mask


@dataclass(frozen=True)
class ObsSource:
    """The race env's tensors that observations are made of: flat over every drone, world-major (N = W · D). The
    simulator's views and the priorities change in place, so an :class:`Observer` keeps them once."""

    pos: torch.Tensor
    vel: torch.Tensor
    rpy: torch.Tensor
    omega: torch.Tensor
    integral: torch.Tensor
    out: torch.Tensor
    """Non-zero for drones out of the race (crashed, finished or absent)."""
    next_gate: torch.Tensor
    race_team: torch.Tensor
    """Race team of each slot (D,)."""
    gate_center: torch.Tensor
    """Gate centres of every track, track-major (T · G, 3)."""
    gate_forward: torch.Tensor
    gate_count: torch.Tensor
    """Gates of each drone's track (N,)."""
    gate_base: torch.Tensor
    """Row of each drone's track's first gate in ``gate_center`` (N,)."""


class Observer:
    """Records every drone's history and builds the observation rows of a race env's drones (``policy``, and
    ``critic``: the same rows)."""

    def __init__(self, cfg: EnvCfg, source: ObsSource, *, device: torch.device) -> None:
        self.source = source
        self.builder = ObservationBuilder(cfg.obs, source.pos.shape[0], device=device)

    def record(self, last_action: torch.Tensor, fresh: torch.Tensor) -> None:
        """Observe the current state: a new history entry (``fresh`` drones start a new history) and every drone's
        rows."""
        self._push(last_action, fresh)
        self._policy_rows = self._build()

    def rows(self, idx: torch.Tensor) -> TensorDict:
        """Observation rows of drones ``idx`` from the last :meth:`record`."""
        obs = self._policy_rows.index_select(0, idx)
        return TensorDict({"policy": obs, "critic": obs}, batch_size=[idx.numel()])

    def peek(self, last_action: torch.Tensor) -> torch.Tensor:
        """``policy`` rows of every drone (N, obs_dim) as :meth:`record` would make them now, leaving the history as
        it is."""
        history = self.builder.history.clone()
        self._push(last_action, torch.zeros(history.shape[0], dtype=torch.bool, device=history.device))
        obs = self._build()
        self.builder.history.copy_(history)
        return obs

    def _push(self, last_action: torch.Tensor, fresh: torch.Tensor) -> None:
        v = self.source
        d = v.race_team.shape[0]
        self.near = neighbours(v.pos, v.out, v.next_gate, v.gate_count, v.gate_base,
                               world_count=v.pos.shape[0] // d, drones_per_world=d)
        self.builder.push(history_entry(v.pos, self.near, v.gate_center, last_action), fresh)

    def _build(self) -> torch.Tensor:
        v = self.source
        return self.builder.build(ObsState(
            pos=v.pos, vel=v.vel, rpy=v.rpy, omega=v.omega, integral=v.integral,
            race_team=v.race_team, gate_forward=v.gate_forward, near=self.near,
            history=self.builder.observed_history()))
