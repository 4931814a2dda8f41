"""Pool opponents: their settings, batched inference, mirror worlds, per-episode offsets and blind opponents."""

from __future__ import annotations

import copy

import pytest
import torch
from pydantic import ValidationError
from tensordict import TensorDict

from spiral.config import ObsCfg, SelfPlayCfg, SimCfg, StageSpec
from spiral.core.checkpoint import FrozenPolicy
from spiral.core.host_syncs import HostSyncCounter
from spiral.env import RaceSetting
from spiral.selfplay import Matchmaker, OpponentDraws, PoolOpponents, StageSources, run_stage
from spiral.train import StageStart, StageTrainer, load_policy
from tests.selfplay.helpers import CF2X, COMMON, SOLO


def test_opponent_offsets_apply_to_both_branches_and_must_lie_in_the_action_range():
    """Offsets apply to pool and frozen opponents alike (0.1 by default, the shipped recipe's; 0: off); a negative or
    beyond-action offset names the field."""
    assert SelfPlayCfg(mode="frozen", opponent_offset=0.2).opponent_offset == pytest.approx(0.2)
    assert SelfPlayCfg().opponent_offset == pytest.approx(0.1)
    assert SelfPlayCfg(opponent_offset=0).opponent_offset == pytest.approx(0.0)
    for bad in (-0.1, 1.5):
        with pytest.raises(ValidationError, match="opponent_offset"):
            SelfPlayCfg(opponent_offset=bad)


def test_opponent_blind_is_a_probability_and_the_shipped_recipes_by_default():
    """Blind opponents in 30% of the episodes by default (the shipped recipe's SPIRAL stages); 0: off."""
    assert SelfPlayCfg().opponent_blind == pytest.approx(0.3)
    assert SelfPlayCfg(opponent_blind=0).opponent_blind == pytest.approx(0.0)
    for bad in (-0.1, 1.5):
        with pytest.raises(ValidationError, match="opponent_blind"):
            SelfPlayCfg(opponent_blind=bad)


@pytest.fixture(scope="module")
def solo_policy(line2, tmp_path_factory) -> FrozenPolicy:
    """The best of a one-iteration solo stage on line2: the frozen pool member the opponent tests race."""
    root = tmp_path_factory.mktemp("solo")
    solo = StageSpec.model_validate({"name": "solo", "iterations": 1, **SOLO})
    run_stage(RaceSetting(line2, CF2X, SimCfg()), solo, root / "a", sources=StageSources(pool_dir=root / "p"),
              progress=False)
    return load_policy(root / "a" / "best.pt")


def test_batched_opponents_match_one_by_one_inference(line2, tmp_path):
    """Give the same actions when worlds sharing a member are batched as when each row is run alone."""
    solo = StageSpec.model_validate({"name": "solo", "iterations": 1, **SOLO})
    run_stage(RaceSetting(line2, CF2X, SimCfg()), solo, tmp_path / "a", sources=StageSources(pool_dir=tmp_path / "p"),
              progress=False, seed=1)
    run_stage(RaceSetting(line2, CF2X, SimCfg()), solo, tmp_path / "b", sources=StageSources(pool_dir=tmp_path / "p"),
              progress=False, seed=2)
    policies = [load_policy(tmp_path / "a" / "best.pt"), load_policy(tmp_path / "b" / "best.pt")]
    gen = torch.Generator().manual_seed(0)
    opponents = PoolOpponents(policies, Matchmaker(2, latest=1, p_latest=0.5), world_count=6, per_world=2,
                              generator=gen)
    dim = policies[0].obs_layout["obs_dim"]
    obs = torch.randn(12, dim)
    batched = opponents(TensorDict({"policy": obs, "critic": obs}, batch_size=[12]))
    member = opponents.assignment.repeat_interleave(2)
    for row in range(12):
        single = TensorDict({"policy": obs[row:row + 1], "critic": obs[row:row + 1]}, batch_size=[1])
        assert torch.allclose(batched[row], policies[int(member[row])](single)[0], atol=1e-6)


def test_mirror_worlds_race_the_live_policy_and_stay_out_of_matchmaking(solo_policy):
    """Drive about p_self of the worlds with the learner's policy; only pool worlds feed the loss statistics."""
    gen = torch.Generator().manual_seed(0)
    mm = Matchmaker(1, latest=0, p_latest=0.5)
    opponents = PoolOpponents([solo_policy], mm, world_count=4000, per_world=1, generator=gen,
                              draws=OpponentDraws(p_self=0.3))
    assert opponents.mirror.float().mean().item() == pytest.approx(0.3, abs=0.03)
    opponents.live = lambda obs: torch.full((obs.batch_size[0], 4), 0.5)
    dim = solo_policy.obs_layout["obs_dim"]
    obs = torch.randn(4000, dim)
    actions = opponents(TensorDict({"policy": obs, "critic": obs}, batch_size=[4000]))
    mirrored = actions[opponents.mirror]  # the live constant
    torch.testing.assert_close(mirrored, torch.full_like(mirrored, 0.5))
    pooled = ~opponents.mirror
    single = TensorDict({"policy": obs[pooled], "critic": obs[pooled]}, batch_size=[int(pooled.sum())])
    assert torch.allclose(actions[pooled], solo_policy(single), atol=1e-6)
    opponents.record(torch.ones(4000, dtype=torch.bool), torch.zeros(4000, dtype=torch.bool))
    assert mm.races.item() == int(pooled.sum()) and mm.losses.item() == int(pooled.sum())


@pytest.mark.bitwise
def test_each_pool_member_acts_on_the_batch_of_its_rows_exactly_as_rsl_rls_actor_does(solo_policy):
    """Every member's network sees the rows that a mask of its worlds selects, in the same order, so the actions equal
    those of rsl-rl's own actor forward on that masked batch to the bit (training reproduces checkpoints exactly)."""
    members = [solo_policy, load_policy_copy(solo_policy, scale=0.5), load_policy_copy(solo_policy, scale=2.0)]
    gen = torch.Generator().manual_seed(3)
    opponents = PoolOpponents(members, Matchmaker(3, latest=2, p_latest=0.2), world_count=300, per_world=3,
                              generator=gen, draws=OpponentDraws(p_self=0.3))
    opponents.live = lambda obs: torch.full((obs.batch_size[0], 4), 0.25)
    dim = solo_policy.obs_layout["obs_dim"]
    obs = TensorDict({"policy": torch.randn(900, dim), "critic": torch.randn(900, dim + 3)}, batch_size=[900])
    actions = opponents(obs)
    member, mirror = opponents.assignment.repeat_interleave(3), opponents.mirror.repeat_interleave(3)
    assert (actions[mirror] == 0.25).all()
    for m, policy in enumerate(members):
        rows = (member == m) & ~mirror
        assert 0 < int(rows.sum()) < 900
        assert torch.equal(actions[rows], policy.actor(obs[rows]))


def load_policy_copy(policy: FrozenPolicy, *, scale: float) -> FrozenPolicy:
    """Another member: ``policy`` with its last layer's weights scaled."""
    clone = copy.deepcopy(policy)
    with torch.no_grad():
        clone.actor.mlp[-1].weight.mul_(scale)
    return clone


def test_mirror_copies_fly_the_learners_mean_action(line2, tmp_path):
    """Mirror opponents run the live actor: its mean action on the same rows."""
    solo = StageSpec.model_validate({"name": "solo", "iterations": 1, **SOLO})
    run_stage(RaceSetting(line2, CF2X, SimCfg()), solo, tmp_path / "a", sources=StageSources(pool_dir=tmp_path / "p"),
              progress=False)
    duel = StageSpec.model_validate({"name": "1v1", "scenario": "1v1", "iterations": 1, **COMMON,
                                     "selfplay": {"p_self": 1.0}})
    opponents = PoolOpponents([load_policy(tmp_path / "a" / "best.pt")], Matchmaker(1, latest=0, p_latest=0.5),
                              world_count=duel.worlds, per_world=1, generator=torch.Generator().manual_seed(0),
                              draws=OpponentDraws(p_self=1.0))
    trainer = StageTrainer(RaceSetting(line2, CF2X, SimCfg()), duel, tmp_path / "duel",
                           start=StageStart(tmp_path / "a" / "best.pt", {duel.scenario: opponents}), progress=False,
                           log=lambda _: None)
    actor = trainer.runner.alg.get_policy()
    obs = trainer.vec_env.get_observations()
    rows = obs["policy"].repeat(512, 1)
    batch = TensorDict({key: obs[key].repeat(512, 1) for key in ("policy", "critic")}, batch_size=[rows.shape[0]])
    opponents.assignment = torch.zeros(rows.shape[0], dtype=torch.long)
    opponents.mirror = torch.ones(rows.shape[0], dtype=torch.bool)
    with torch.no_grad():
        mean = actor(batch)
    torch.testing.assert_close(opponents(batch), mean)


def test_opponent_offsets_hold_for_an_episode_and_are_redrawn_at_reset(solo_policy):
    """Each opponent's position-target actions move by one offset per episode, within bounds; yaw is untouched."""
    dim = solo_policy.obs_layout["obs_dim"]
    obs = TensorDict({"policy": torch.randn(40, dim), "critic": torch.randn(40, dim)}, batch_size=[40])
    plain = PoolOpponents([solo_policy], Matchmaker(1, latest=0, p_latest=0.5), world_count=20, per_world=2,
                          generator=torch.Generator().manual_seed(0))
    shifted = PoolOpponents([solo_policy], Matchmaker(1, latest=0, p_latest=0.5), world_count=20, per_world=2,
                            generator=torch.Generator().manual_seed(0), draws=OpponentDraws(offset=0.2))
    delta = shifted(obs) - plain(obs)
    assert torch.allclose(shifted(obs) - plain(obs), delta)  # the same offset at every step
    assert delta[:, :3].abs().max() <= 0.2 + 1e-6 and delta[:, :3].abs().max() > 0.1 and (delta[:, 3] == 0).all()
    assert len({tuple(row) for row in delta[:, :3].tolist()}) == 40  # every opponent has its own
    shifted.reset(torch.arange(20) < 10)
    moved = (shifted(obs) - plain(obs) - delta)[:, :3].abs().sum(-1) > 0
    assert moved[:20].all() and not moved[20:].any()  # only the reset worlds (rows 0-19) draw new offsets


def test_blind_opponents_read_rows_without_the_unseen_entries_for_their_episode():
    """With blind 0.5 about half the worlds' opponents (pool members and mirror copies alike) read their rows with
    the unseen entries zeroed, the others their rows as they are; a world keeps its draw until its reset, and the
    caller's rows are left untouched."""
    dim, worlds = 10, 400
    unseen = torch.zeros(dim, dtype=torch.bool)
    unseen[3:7] = True
    read: list[torch.Tensor] = []

    class Member:  # a pool member (FrozenPolicy's two entry points) that records what it reads
        def actions(self, policy_obs: torch.Tensor) -> torch.Tensor:
            read.append(policy_obs.clone())
            return torch.zeros(policy_obs.shape[0], 4)

        def __call__(self, obs: TensorDict) -> torch.Tensor:
            return self.actions(obs["policy"])

    member = Member()

    x = torch.randn(2 * worlds, dim)
    obs = TensorDict({"policy": x.clone(), "critic": x.clone()}, batch_size=[2 * worlds])
    with pytest.raises(ValueError, match="unseen"):
        PoolOpponents([member], Matchmaker(1, latest=0, p_latest=0.5), world_count=worlds, per_world=2,
                      generator=torch.Generator().manual_seed(0), draws=OpponentDraws(blind=0.5))
    opponents = PoolOpponents([member], Matchmaker(1, latest=0, p_latest=0.5), world_count=worlds, per_world=2,
                              generator=torch.Generator().manual_seed(0),
                              draws=OpponentDraws(p_self=0.5, blind=0.5, unseen=unseen))
    opponents.live = member
    opponents(obs)
    torch.testing.assert_close(obs["policy"], x)  # left untouched
    order = torch.cat([torch.nonzero(opponents.mirror.repeat_interleave(2)).squeeze(1),
                       torch.nonzero(~opponents.mirror.repeat_interleave(2)).squeeze(1)])
    seen = torch.empty_like(x)
    seen[order] = torch.cat(read)  # mirror rows first, then the member's
    blind = opponents.blind_world.repeat_interleave(2)
    assert 0.4 < opponents.blind_world.float().mean() < 0.6
    assert (opponents.blind_world & opponents.mirror).any() and (opponents.blind_world & ~opponents.mirror).any()
    assert not seen[blind][:, unseen].any()
    torch.testing.assert_close(seen[blind][:, ~unseen], x[blind][:, ~unseen])  # copied rows
    torch.testing.assert_close(seen[~blind], x[~blind])
    drawn = opponents.blind_world.clone()
    opponents(obs)
    assert torch.equal(opponents.blind_world, drawn)  # exact: booleans
    opponents.reset(torch.arange(worlds) < worlds // 2)
    assert torch.equal(opponents.blind_world[worlds // 2:], drawn[worlds // 2:])  # exact: booleans
    assert not torch.equal(opponents.blind_world[: worlds // 2], drawn[: worlds // 2])  # exact: booleans


def test_opponents_without_host_syncs_act_and_draw_as_the_routed_ones(solo_policy):
    """The sync-free path (every member on every row, draws for every world) gives each row its member's actions
    and, at a reset, redraws only the masked worlds, with no host synchronisation."""
    members = [solo_policy, load_policy_copy(solo_policy, scale=0.5), load_policy_copy(solo_policy, scale=2.0)]
    draws = OpponentDraws(p_self=0.3, offset=0.1)

    def pool(*, sync_free: bool) -> PoolOpponents:
        opponents = PoolOpponents(members, Matchmaker(3, latest=2, p_latest=0.2), world_count=200, per_world=2,
                                  generator=torch.Generator().manual_seed(5), draws=draws)
        opponents.sync_free = sync_free
        opponents.live = lambda obs: torch.full((obs.batch_size[0], 4), 0.25)
        return opponents

    routed, free = pool(sync_free=False), pool(sync_free=True)
    free.assignment, free.mirror = routed.assignment.clone(), routed.mirror.clone()
    free.action_offset = routed.action_offset.clone()
    dim = solo_policy.obs_layout["obs_dim"]
    obs = TensorDict({"policy": torch.randn(400, dim), "critic": torch.randn(400, dim)}, batch_size=[400])
    with HostSyncCounter() as syncs:
        actions = free(obs)
    assert syncs.total == 0
    torch.testing.assert_close(actions, routed(obs), atol=1e-6, rtol=1e-5)
    worlds = torch.arange(200) % 3 == 0
    before = free.assignment.clone(), free.action_offset.clone()
    with HostSyncCounter() as syncs:
        free.reset(worlds)
    assert syncs.total == 0
    torch.testing.assert_close(free.assignment[~worlds], before[0][~worlds])  # worlds not reset keep their draws
    torch.testing.assert_close(free.action_offset[~worlds], before[1][~worlds])
    assert not torch.allclose(free.action_offset[worlds], before[1][worlds])  # every reset world draws anew
    assert set(free.assignment[worlds].tolist()) == {0, 1, 2}


def test_the_parts_of_a_mixed_stage_act_their_pool_opponents_in_one_pass(solo_policy):
    """Pools sharing one list of members (a 1v1 and a 2v2 part) act together: each member's network runs once over
    both parts' rows, and every row gets the actions its own pool gives it alone (mirror rows, offsets included)."""
    calls = []
    members = counted_members(solo_policy, calls)
    matchmaker, generator = Matchmaker(2, latest=1, p_latest=0.3), torch.Generator().manual_seed(7)
    pools = [PoolOpponents(members, matchmaker, world_count=worlds, per_world=per_world, generator=generator,
                           draws=OpponentDraws(p_self=0.4, offset=0.1)) for worlds, per_world in ((30, 1), (20, 2))]
    dim = solo_policy.obs_layout["obs_dim"]
    obs = [TensorDict({"policy": torch.randn(n, dim), "critic": torch.randn(n, dim)}, batch_size=[n]) for n in (30, 40)]
    for pool in pools:
        pool.sync_free = True
        pool.live = lambda o: torch.full((o.batch_size[0], 4), 0.25)
    alone = [pool(o) for pool, o in zip(pools, obs, strict=True)]
    calls.clear()
    with HostSyncCounter() as syncs:
        together = PoolOpponents.act_together(pools, obs)
    assert syncs.total == 0 and calls == [70, 70]
    for a, b in zip(together, alone, strict=True):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-5)
    with pytest.raises(ValueError, match="different members"):
        PoolOpponents.act_together([pools[0], PoolOpponents(list(members), matchmaker, world_count=2, per_world=1,
                                                            generator=generator)], obs)


def counted_members(policy: FrozenPolicy, calls: list[int]) -> list[FrozenPolicy]:
    """Two members (``policy``'s copies, the second with its last layer halved) that append the rows of each of their
    calls to ``calls``."""
    members = [load_policy_copy(policy, scale=1.0), load_policy_copy(policy, scale=0.5)]
    for m in members:
        m.actions = (lambda act: lambda rows: calls.append(rows.shape[0]) or act(rows))(m.actions)
    return members


def test_a_mixed_env_on_the_sync_free_path_steps_its_parts_opponents_in_one_pass(line2, solo_policy):
    """A 1v1 and a 2v2 part racing one pool: each env step runs each member once over both parts' opponent rows."""
    from spiral.env.mixed import MixedRaceEnv
    from tests.env.helpers import make_env

    calls = []
    members = counted_members(solo_policy, calls)
    obs_cfg = ObsCfg(**COMMON["env"]["obs"])  # the layout solo_policy reads
    parts = {"1v1": make_env(line2, worlds=3, drones=2, learners=(0,), obs=obs_cfg),
             "2v2": make_env(line2, worlds=2, drones=4, learners=(0, 1), obs=obs_cfg)}
    mixed = MixedRaceEnv(parts)
    matchmaker, generator = Matchmaker(2, latest=1, p_latest=0.5), torch.Generator().manual_seed(1)
    for env in parts.values():
        pool = PoolOpponents(members, matchmaker, world_count=env.world_count, per_world=len(env.opponent_slots),
                             generator=generator)
        env.set_opponent_policy(pool)
        env.sync_free = pool.sync_free = True
    mixed.reset()
    calls.clear()
    with HostSyncCounter() as syncs:
        mixed.step(torch.zeros(mixed.num_envs, 4))
    assert syncs.total == 0 and calls == [3 + 2 * 2, 3 + 2 * 2]
