"""Self-play stages: frozen opponents' settings, promotion feeding the pool, resume, the frozen opponent's checkpoint,
init snapshots and blind opponents across a stage's scenarios."""

from __future__ import annotations

import json

import pytest
import torch
from pydantic import ValidationError
from tensordict import TensorDict

from spiral.config import SelfPlayCfg, SimCfg, StageSpec
from spiral.core.checkpoint import CheckpointError
from spiral.env import RaceSetting
from spiral.selfplay import Pool, PoolOpponents, StageSources, run_stage
from spiral.train import load_policy
from tests.selfplay.helpers import CF2X, COMMON, PERMISSIVE, SOLO


def test_frozen_opponents_refuse_mirror_self_play_and_ignore_its_default():
    """PPO without self-play never races the learner itself: p_self > 0 given with frozen opponents is an error, and
    the default (the shipped recipe's 0.6, for pool mode) leaves every frozen world to the frozen policy."""
    with pytest.raises(ValidationError, match="p_self"):
        SelfPlayCfg(mode="frozen", p_self=0.5)
    assert SelfPlayCfg(mode="pool", p_self=0.5).mirror_share == pytest.approx(0.5)
    assert SelfPlayCfg().mirror_share == pytest.approx(0.6)
    assert SelfPlayCfg(mode="frozen").mirror_share == pytest.approx(0.0)
    assert SelfPlayCfg(mode="frozen", p_self=0).mirror_share == pytest.approx(0.0)


def test_only_frozen_opponents_name_the_stage_they_come_from():
    """opponent_from picks the frozen opponent; in pool mode (opponents are the pool) it is an error."""
    assert SelfPlayCfg(mode="frozen", opponent_from="solo").opponent_from == "solo"
    assert SelfPlayCfg(mode="frozen").opponent_from is None
    with pytest.raises(ValidationError, match="opponent_from"):
        SelfPlayCfg(mode="pool", opponent_from="solo")


def test_short_1v1_stage_promotes_into_the_pool_and_resumes(line2, tmp_path):
    """Promote at least once with a permissive rule, add members to the pool, and resume the stage."""
    solo = StageSpec.model_validate({"name": "solo", "iterations": 1, **SOLO})
    run_stage(RaceSetting(line2, CF2X, SimCfg()), solo, tmp_path / "solo",
              sources=StageSources(pool_dir=tmp_path / "pool"), progress=False)
    duel = StageSpec.model_validate({"name": "1v1", "scenario": "1v1", "iterations": 2, "selfplay": PERMISSIVE,
                                     **COMMON})
    result = run_stage(RaceSetting(line2, CF2X, SimCfg()), duel, tmp_path / "duel",
                       sources=StageSources(pool_dir=tmp_path / "pool", init_checkpoint=tmp_path / "solo" / "best.pt"),
                       progress=False)
    pool = Pool(tmp_path / "pool")
    assert len(pool.members) == 3  # the initial policy and two promotions
    assert pool.latest_best == pool.members[-1].id
    assert result.best_path.exists()
    rows = [json.loads(x) for x in (tmp_path / "duel" / "train_log.jsonl").read_text().splitlines()]
    assert [r["h2h/promoted"] for r in rows] == pytest.approx([1.0, 1.0])  # 0/1 flags
    longer = duel.model_copy(update={"iterations": 3})
    run_stage(RaceSetting(line2, CF2X, SimCfg()), longer, tmp_path / "duel",
              sources=StageSources(pool_dir=tmp_path / "pool", init_checkpoint=tmp_path / "solo" / "best.pt"),
              progress=False)
    rows = [json.loads(x) for x in (tmp_path / "duel" / "train_log.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [0, 1, 2]
    assert len(Pool(tmp_path / "pool").members) == 4


def test_frozen_opponents_run_the_opponent_checkpoint_not_the_initial_policy(line2, tmp_path, monkeypatch):
    """PPO without self-play races the stage it names (the solo best), not the policy the stage starts from."""
    from spiral.selfplay import curriculum

    solo = StageSpec.model_validate({"name": "solo", "iterations": 1, **SOLO})
    for name, seed in (("a", 1), ("b", 2)):
        run_stage(RaceSetting(line2, CF2X, SimCfg()), solo, tmp_path / name,
                  sources=StageSources(pool_dir=tmp_path / "p"), progress=False, seed=seed)
    seen: list[list] = []

    def recording(policies, *args, **kwargs):
        seen.append(policies)
        return PoolOpponents(policies, *args, **kwargs)

    monkeypatch.setattr(curriculum, "PoolOpponents", recording)
    frozen = StageSpec.model_validate({"name": "nsp", "scenario": "1v1", "iterations": 1, **COMMON,
                                       "selfplay": {**PERMISSIVE, "mode": "frozen", "opponent_from": "b"}})
    run_stage(RaceSetting(line2, CF2X, SimCfg()), frozen, tmp_path / "nsp",
              sources=StageSources(pool_dir=tmp_path / "nsp-pool", init_checkpoint=tmp_path / "a" / "best.pt",
                                   opponent_checkpoint=tmp_path / "b" / "best.pt"), progress=False)
    (opponent,) = seen[0]
    a, b = (load_policy(tmp_path / name / "best.pt") for name in ("a", "b"))
    x = torch.randn(16, b.obs_layout["obs_dim"])
    obs = TensorDict({"policy": x, "critic": x}, batch_size=[16])
    torch.testing.assert_close(opponent(obs), b(obs))  # the same checkpoint on the same rows
    assert not torch.allclose(opponent(obs), a(obs))
    assert not (tmp_path / "nsp-pool").exists()
    other = StageSpec.model_validate({**SOLO, "name": "solo", "iterations": 1,
                                      "env": {"obs": {**COMMON["env"]["obs"], "history_len": 2}}})
    run_stage(RaceSetting(line2, CF2X, SimCfg()), other, tmp_path / "c", sources=StageSources(pool_dir=tmp_path / "p"),
              progress=False)
    with pytest.raises(CheckpointError, match=r"c/best\.pt: observation layout"):
        run_stage(RaceSetting(line2, CF2X, SimCfg()), frozen, tmp_path / "nsp2",
                  sources=StageSources(pool_dir=tmp_path / "nsp-pool", init_checkpoint=tmp_path / "a" / "best.pt",
                                       opponent_checkpoint=tmp_path / "c" / "best.pt"), progress=False)
    pooled = frozen.model_copy(update={"selfplay": frozen.selfplay.model_copy(update={"mode": "pool",
                                                                                      "opponent_from": None})})
    with pytest.raises(ValueError, match="opponent checkpoint"):
        run_stage(RaceSetting(line2, CF2X, SimCfg()), pooled, tmp_path / "pooled",
                  sources=StageSources(pool_dir=tmp_path / "p", init_checkpoint=tmp_path / "a" / "best.pt",
                                       opponent_checkpoint=tmp_path / "b" / "best.pt"), progress=False)


def test_a_stage_with_blind_opponents_hides_what_its_layout_shows_of_other_drones(line2, tmp_path, monkeypatch):
    """`selfplay.opponent_blind` reaches every format's opponents with the stage layout's other-drone columns."""
    from spiral.env.observations import other_drone_columns
    from spiral.selfplay import curriculum

    built: list[PoolOpponents] = []

    def recording(*args, **kwargs):
        built.append(PoolOpponents(*args, **kwargs))
        return built[-1]

    solo = StageSpec.model_validate({"name": "solo", "iterations": 1, **SOLO})
    run_stage(RaceSetting(line2, CF2X, SimCfg()), solo, tmp_path / "solo",
              sources=StageSources(pool_dir=tmp_path / "pool"), progress=False)
    monkeypatch.setattr(curriculum, "PoolOpponents", recording)
    duel = StageSpec.model_validate({"name": "1v1", "scenario": "1v1", "iterations": 1, "mix": {"2v2": 0.5},
                                     "selfplay": {**PERMISSIVE, "opponent_blind": 0.4}, **COMMON})
    run_stage(RaceSetting(line2, CF2X, SimCfg()), duel, tmp_path / "duel",
              sources=StageSources(pool_dir=tmp_path / "pool", init_checkpoint=tmp_path / "solo" / "best.pt"),
              progress=False)
    hidden = other_drone_columns(duel.env.obs)
    assert len(built) == 2 and {o.per_world for o in built} == {1, 2}
    assert all(o.draws.blind == pytest.approx(0.4) for o in built)
    assert all(torch.equal(o.unseen, hidden) for o in built)  # exact: boolean masks


def test_frozen_worlds_race_no_mirror_copies_whatever_p_self_says_for_pool_mode(monkeypatch):
    """The opponents a stage trains against draw mirror copies of the learner with its `p_self` in pool mode, and
    never in frozen mode, where the default p_self (the shipped recipe's, for pool mode) is ignored."""
    from spiral.selfplay import Matchmaker, curriculum

    monkeypatch.setattr(curriculum, "PoolOpponents", lambda members, matchmaker, **kwargs: kwargs["draws"])
    matchmaker = Matchmaker(1, latest=0, p_latest=0.0)
    for mode, mirror in (("pool", 0.6), ("frozen", 0.0)):
        stage = StageSpec.model_validate({"name": "d", "scenario": "1v1", "iterations": 1, **COMMON,
                                          "selfplay": {**PERMISSIVE, "mode": mode}})
        draws = curriculum._world_opponents(stage, [], matchmaker, torch.Generator())
        assert draws["1v1"].p_self == pytest.approx(mirror), mode
