"""Opponent drones in training: pool policies run batched per member inside ``RaceEnv.step``."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from tensordict import TensorDict

from spiral.core.checkpoint import FrozenPolicy, load_policy
from spiral.core.host_syncs import put_rows
from spiral.selfplay.matchmaking import Matchmaker

__all__ = ["OpponentDraws", "PoolOpponents", "StageOpponents"]


@dataclass(frozen=True)
class OpponentDraws:
    """What a world's opponents draw at its reset besides their pool member, each for the episode.

    With ``p_self > 0`` the world races copies of the learner's current policy instead (mirror self-play) with that
    probability. With ``offset > 0`` every opponent adds a constant offset, drawn uniformly in [-offset, offset] per
    axis, to its position-target actions: it flies another line. With ``blind > 0`` the world's opponents fly blind
    with that probability: the observation entries in the bool mask ``unseen`` (obs_dim,), those about other drones, are
    zeroed before their policy reads them, so they race as if alone and never make room.
    """

    p_self: float = 0.0
    offset: float = 0.0
    blind: float = 0.0
    unseen: torch.Tensor | None = None

    def __post_init__(self) -> None:
        if self.blind > 0 and self.unseen is None:
            raise ValueError("blind opponents need the mask of the observation entries they do not see (unseen)")


class PoolOpponents:
    """An ``OpponentPolicy`` over several frozen policies; each world keeps its drawn member for the episode.

    Opponent rows arrive world-major (``per_world`` rows per world). All worlds that share a member go through
    that member's network in one forward pass, without gradients. ``draws`` (:class:`OpponentDraws`) says what else a
    world's opponents draw at its reset. In mirror worlds ``live`` must be set to the learner's deterministic policy
    before the first step (:class:`~spiral.train.StageTrainer` does); mirror races are not counted by the matchmaker.
    """

    def __init__(self, policies: list[FrozenPolicy], matchmaker: Matchmaker, *, world_count: int, per_world: int,
                 generator: torch.Generator, draws: OpponentDraws | None = None) -> None:
        self.policies, self.matchmaker = policies, matchmaker
        self.per_world, self.generator = per_world, generator
        self.draws = draws or OpponentDraws()
        self.unseen = None if self.draws.unseen is None else self.draws.unseen.to(matchmaker.races.device)
        """``draws.unseen`` on the matchmaker's device."""
        self.live: Callable[[TensorDict], torch.Tensor] | None = None
        """The learner's current policy, for mirror worlds."""
        self.assignment = torch.zeros(world_count, dtype=torch.long, device=matchmaker.races.device)
        """Member index of each world."""
        self.mirror = torch.zeros(world_count, dtype=torch.bool, device=matchmaker.races.device)
        """Worlds whose opponents are the learner's current policy."""
        self.action_offset = torch.zeros(world_count, per_world, 3, device=matchmaker.races.device)
        """Constant offset of each opponent's position-target actions for the episode (its yaw is untouched)."""
        self.blind_world = torch.zeros(world_count, dtype=torch.bool, device=matchmaker.races.device)
        """Worlds whose opponents do not see the other drones (``blind``)."""
        self.sync_free = matchmaker.races.device.type != "cpu"
        """Route rows to members without a host synchronisation (the default off a CPU): every member's network runs
        on every row and each row keeps its member's actions, and resets draw for every world; on a CPU, cheaper to
        find each member's rows and the reset worlds on the host."""
        self._route: _Routing | None = None
        """The rows of each member and of the live policy for the current draws (:meth:`_routing`)."""
        self._blind: tuple[tuple, torch.Tensor] | None = None
        """The blind worlds' zeroed entries for the current draws (:meth:`_blind_mask`)."""
        self.reset(torch.ones(world_count, dtype=torch.bool, device=matchmaker.races.device))

    @torch.no_grad()
    def __call__(self, obs: TensorDict) -> torch.Tensor:
        """Actions of every opponent drone."""
        if self.sync_free:
            return PoolOpponents.act_together([self], [obs])[0]
        rows = obs["policy"]
        if self.draws.blind > 0:
            rows = torch.where(self._blind_mask(), 0.0, rows)
        return self._finish(self._by_member(obs, rows))

    @staticmethod
    @torch.no_grad()
    def act_together(pools: Sequence[PoolOpponents], obs: Sequence[TensorDict]) -> list[torch.Tensor]:
        """The actions of the opponents of several pools that share one list of members (the parts of a mixed stage),
        each pool's on its ``obs``, in one pass without a host synchronisation: every member's network runs once on
        the rows of every pool, and each row keeps its own member's actions."""
        if any(p.policies is not pools[0].policies for p in pools):
            raise ValueError("act_together: the pools race different members")
        obs = [p._blinded(o) if p.draws.blind > 0 else o for p, o in zip(pools, obs, strict=True)]
        rows = torch.cat([o["policy"] for o in obs])
        member_of_row = torch.cat([p.assignment.repeat_interleave(p.per_world) for p in pools])
        actions = torch.zeros(rows.shape[0], 4, device=rows.device)
        for m, policy in enumerate(pools[0].policies):
            actions = torch.where((member_of_row == m)[:, None], policy.actions(rows), actions)
        out = []
        for pool, o, a in zip(pools, obs, actions.split([o.batch_size[0] for o in obs]), strict=True):
            if pool.draws.p_self > 0:
                a = torch.where(pool.mirror.repeat_interleave(pool.per_world)[:, None], pool._live()(o), a)
            out.append(pool._finish(a))
        return out

    def _finish(self, actions: torch.Tensor) -> torch.Tensor:
        """``actions`` with the episode's offset of each opponent applied (in place)."""
        if self.draws.offset > 0:
            actions[:, :3] += self.action_offset.view(-1, 3)
        return actions

    def _by_member(self, obs: TensorDict, rows: torch.Tensor) -> torch.Tensor:
        """Actions with each network run on its own worlds' ``rows`` (``obs``' policy rows, blinded where the world's
        opponents fly blind) only, found on the host (:meth:`_routing`)."""
        route = self._routing()
        actions = torch.zeros(rows.shape[0], 4, device=rows.device)
        if route.mirror.numel():
            mirrored = self._live()(_select_rows(obs, rows, route.mirror))
            actions.index_copy_(0, route.mirror, mirrored.to(actions.dtype))
        acted = [self.policies[m].actions(rows.index_select(0, member_rows)) for m, member_rows in route.members]
        if acted:
            actions.index_copy_(0, route.order, torch.cat(acted))
        return actions

    def _routing(self) -> _Routing:
        """Which rows each member drives and which the live policy does, found again only when the draws
        (:attr:`assignment`, :attr:`mirror`: replaced or written in place) or the members changed since the last
        call."""
        key = (self.assignment, _version(self.assignment), self.mirror, _version(self.mirror), len(self.policies))
        if self._route is None or not _same_key(self._route.key, key):
            self._route = _Routing.of(self.assignment, self.mirror, self.per_world, len(self.policies), key)
        return self._route

    def _blind_mask(self) -> torch.Tensor:
        """The entries of the opponent rows zeroed in blind worlds (rows, obs_dim), found again only when
        :attr:`blind_world` changed since the last call."""
        key = (self.blind_world, _version(self.blind_world))
        if self._blind is None or not _same_key(self._blind[0], key):
            rows = self.blind_world[:, None].expand(-1, self.per_world).reshape(-1)
            self._blind = (key, rows[:, None] & self.unseen[None])
        return self._blind[1]

    def _live(self) -> Callable[[TensorDict], torch.Tensor]:
        """The learner's current policy, for mirror worlds."""
        if self.live is None:
            raise RuntimeError("mirror worlds need the learner's policy: set PoolOpponents.live")
        return self.live

    def reset(self, worlds: torch.Tensor) -> None:
        """Draw new members (or mirror races) for the worlds in the bool mask ``worlds``: for those worlds only, or
        without a host synchronisation (:attr:`sync_free`) for every world, kept where the mask is set."""
        idx = None if self.sync_free else worlds.nonzero().squeeze(1)
        count = len(worlds) if idx is None else idx.numel()
        if count == 0:
            return
        device = self.mirror.device
        put_rows(self.assignment, self.matchmaker.draw(count, self.generator), worlds, idx)
        put_rows(self.mirror, torch.rand(count, generator=self.generator, device=device) < self.draws.p_self, worlds,
                 idx)
        if self.draws.offset > 0:
            shift = torch.rand(count, self.per_world, 3, generator=self.generator, device=device)
            put_rows(self.action_offset, (2.0 * shift - 1.0) * self.draws.offset, worlds, idx)
        if self.draws.blind > 0:
            u = torch.rand(count, generator=self.generator, device=device)
            put_rows(self.blind_world, u < self.draws.blind, worlds, idx)

    def _blinded(self, obs: TensorDict) -> TensorDict:
        """``obs`` with the unseen entries of the blind worlds' rows zeroed."""
        rows = self.blind_world[:, None].expand(-1, self.per_world).reshape(-1)
        return obs.replace(policy=torch.where(rows[:, None] & self.unseen[None], 0.0, obs["policy"]))

    def record(self, ended: torch.Tensor, learner_won: torch.Tensor) -> None:
        """Feed the outcomes of the races that ended in pool worlds (``ended``: a bool mask over worlds) to the
        matchmaker."""
        self.matchmaker.record(self.assignment, learner_won, ended & ~self.mirror)


@dataclass
class StageOpponents:
    """The opponents of a multi-drone stage's training worlds: one list of policies and one matchmaker, shared by
    every scenario's worlds."""

    members: list[FrozenPolicy]
    matchmaker: Matchmaker
    worlds: dict[str, PoolOpponents]
    """The opponents of each part of the training worlds that has opponent slots (a ``StageStart``'s ``opponents``)."""
    best_rating: float
    """The rating of the latest best (the initial policy's in a new pool)."""
    device: str

    def add(self, path: Path) -> None:
        """Race ``path``'s policy too (a promoted learner), as the latest best."""
        self.members.append(load_policy(path, device=self.device))
        self.matchmaker.add_member()


def _version(t: torch.Tensor) -> object:
    """``t``'s version counter, which every in-place write bumps; for an inference tensor, which keeps none, a new
    object, equal to no other (so that nothing cached on it is reused)."""
    try:
        return t._version
    except RuntimeError:
        return object()


def _same_key(old: tuple, new: tuple) -> bool:
    """Whether two cache keys of tensors (by identity) and numbers (by value) are the same."""
    return all(a is b if isinstance(a, torch.Tensor) else a == b for a, b in zip(old, new, strict=True))


def _select_rows(obs: TensorDict, rows: torch.Tensor, index: torch.Tensor) -> TensorDict:
    """``obs`` at the rows ``index`` (a copy of each group's rows, in order), its ``policy`` group taken from
    ``rows``."""
    policy = rows.index_select(0, index)
    groups = {k: policy if k == "policy" else v.index_select(0, index) for k, v in obs.items()}
    return TensorDict(groups, batch_size=[index.numel()], device=obs.device)


@dataclass(frozen=True)
class _Routing:
    """The opponent rows (world-major) of the live policy (mirror worlds) and of each pool member, for one set of
    draws."""

    key: tuple
    mirror: torch.Tensor
    """Rows of mirror worlds, ascending."""
    order: torch.Tensor
    """The pooled rows, member by member, each member's ascending (a stable sort by member)."""
    members: list[tuple[int, torch.Tensor]]
    """Each member that drives rows, with its rows (a slice of :attr:`order`)."""

    @staticmethod
    def of(assignment: torch.Tensor, mirror: torch.Tensor, per_world: int, member_count: int, key: tuple
           ) -> _Routing:
        member_of_row = assignment.repeat_interleave(per_world)
        mirror_row = mirror.repeat_interleave(per_world)
        pooled = torch.nonzero(~mirror_row).squeeze(1)
        members = member_of_row[pooled]
        counts = torch.bincount(members, minlength=member_count).tolist()
        order = pooled[torch.argsort(members, stable=True)]
        driven = [(m, rows) for m, rows in enumerate(order.split(counts)) if len(rows)]
        return _Routing(key, torch.nonzero(mirror_row).squeeze(1), order, driven)
