"""Evaluation protocol: identical start placements for every method, deterministic eval JSON, planner methods."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch
from typer.testing import CliRunner

from spiral.cli import app
from spiral.config.env import EVAL_REWARD, RewardCfg
from spiral.env import RaceEnv, RaceSetting, run_races
from spiral.eval.evaluate import (
    SE_IBR,
    EvalLayout,
    RaceSet,
    evaluate_methods,
    evaluate_policy,
    load_method,
    setup_race,
)
from spiral.eval.metrics import summarize_races

runner = CliRunner()


@pytest.mark.bitwise
def test_every_method_races_from_the_same_start_placements(sprint, tiny_checkpoint):
    """Start a learned policy, the planner and a cross-play pairing from identical 2v2 placements for one seed."""
    policy = load_method(tiny_checkpoint)
    starts = []
    for own, opponent in ((policy, None), (SE_IBR, None), (policy, SE_IBR), (SE_IBR, policy)):
        env, _ = setup_race(RaceSet(sprint, "2v2", 3, 7), own, opponent)
        env.reset()  # what run_races does first
        starts.append(env.pos.clone())
    for other in starts[1:]:
        assert torch.equal(starts[0], other)
    env, _ = setup_race(RaceSet(sprint, "2v2", 3, 8), policy)
    env.reset()
    assert not torch.equal(env.pos, starts[0])
    separation = torch.cdist(starts[0].view(3, 4, 3), starts[0].view(3, 4, 3))
    assert float((separation + 9 * torch.eye(4)).min()) >= sprint.start.min_separation - 1e-6


@pytest.mark.bitwise
def test_evaluation_races_end_alike_without_the_reward_terms_they_leave_out(sprint, tiny_checkpoint):
    """Evaluation envs leave the terms between drones out of their reward (``EVAL_REWARD``); with the training
    reward's terms on, the same 2v2 races end the same way, drone for drone: an outcome never reads the reward."""
    policy = load_method(tiny_checkpoint)
    env, _ = setup_race(RaceSet(sprint, "2v2", 4, 3), policy)
    assert env.cfg.reward == EVAL_REWARD and RewardCfg().proximity > 0 and RewardCfg().closing > 0
    ends = []
    for reward in (EVAL_REWARD, RewardCfg()):
        layout = EvalLayout.of_policy(policy)
        layout = dataclasses.replace(layout, env=layout.env.model_copy(update={"reward": reward}))
        env = RaceEnv(RaceSetting(sprint, layout.airframe, layout.sim), layout.env, world_count=4, drones_per_world=4,
                      learner_slots=[0, 1, 2, 3], seed=3, training=False)
        res = run_races(env, policy)
        ends.append((res.finished.clone(), res.lap_time.clone(), res.crashed.clone()))
    for first, second in zip(*ends, strict=True):
        assert torch.equal(first, second)  # exact: the same races on the same host


def test_planner_racing_a_policy_uses_the_policy_layout(sprint, tiny_checkpoint):
    """Build the planner-vs-policy env with the policy's observation layout, not the default one."""
    policy = load_method(tiny_checkpoint)
    env, _ = setup_race(RaceSet(sprint, "1v1", 1, 0), SE_IBR, policy)
    assert env.cfg.obs == EvalLayout.of_policy(policy).env.obs
    assert env.obs_dim == policy.meta["obs_layout"]["obs_dim"]
    assert env.cfg.obs != EvalLayout.default().env.obs


@pytest.mark.bitwise
def test_same_eval_command_twice_writes_identical_json(sprint_yaml, tiny_checkpoint, tmp_path):
    """Write identical JSON from two runs of one cross-play command (learned policy vs SE-IBR), but for the
    planner's measured milliseconds (its number of plans is the same)."""
    outputs = []
    for i in range(2):
        out = tmp_path / f"eval{i}.json"
        result = runner.invoke(app, ["eval", "--track", str(sprint_yaml), "--method", f"tiny={tiny_checkpoint}",
                                     "--against", "se-ibr", "--scenario", "1v1", "--runs", "2", "--seed", "3",
                                     "--json", str(out)])
        assert result.exit_code == 0, result.output
        outputs.append(json.loads(out.read_text()))
    costs = [o["methods"]["tiny"].pop("planning") for o in outputs]
    assert outputs[0] == outputs[1] and costs[0]["plans"] == costs[1]["plans"] > 0
    data = outputs[0]
    assert data["against"] == {"name": "se-ibr", "checkpoint": "se-ibr"}
    assert (data["sides"], data["races"]) == ("both", 4)  # 2 placements, each raced from both sides
    entry = data["methods"]["tiny"]
    assert entry["drones"] == 4 and entry["opponent"]["drones"] == 4
    assert entry["win_rate"] + entry["loss_rate"] + entry["draws"] == pytest.approx(1.0)


def test_planner_self_match_reports_its_layout(sprint):
    """Evaluate `se-ibr` alone with default settings and say so in the entry."""
    data = evaluate_methods(RaceSet(sprint, "solo", 1, 0), {"planner": "se-ibr"})
    entry = data["methods"]["planner"]
    assert entry["checkpoint"] == "se-ibr" and entry["layout"] == "defaults"
    assert entry["drones"] == 1
    assert sum(entry["crashes"].values()) + round(entry["success_ratio"]) == 1


def test_self_match_results_keep_the_scenarios_two_teams(sprint, tiny_checkpoint):
    """Every drone of a 2v2 self-match runs the learner, yet its results split slots 0-1 from 2-3 (for contacts)."""
    res = evaluate_policy(load_method(tiny_checkpoint), RaceSet(sprint, "2v2", 2, 0))
    assert res.team.tolist() == [0, 0, 1, 1]


def test_cross_play_compares_action_mappings_as_read_so_older_checkpoints_still_pair(sprint, tiny_checkpoint, tmp_path):
    """A checkpoint written before an action field existed (the key absent: its default) races one that spells the
    default out; a different mapping is refused."""
    from spiral.core.checkpoint import load_checkpoint, save_checkpoint
    from spiral.eval.evaluate import RaceSet, cross_play

    data = load_checkpoint(tiny_checkpoint)
    meta = {k: v for k, v in data.pop("spiral").items() if k not in ("format", "versions")}

    def variant(name: str, action: dict) -> object:
        path = tmp_path / f"{name}.pt"
        save_checkpoint(path, data, {**meta, "env": {**meta["env"], "action": action}})
        return load_method(path)

    action = dict(meta["env"]["action"])
    older = variant("older", {k: v for k, v in action.items() if k != "separation_team"})
    newer = variant("newer", {**action, "separation_team": "all"})
    res, winners = cross_play(older, newer, RaceSet(sprint, "1v1", 2, 0), sides="a")
    assert res.finished.shape == (2, 2) and winners.shape == (2,)
    other = variant("other", {**action, "pos_scale": 1.0})
    with pytest.raises(ValueError, match="same action mapping"):
        cross_play(older, other, RaceSet(sprint, "1v1", 2, 0), sides="a")


def test_cross_play_lets_each_team_read_its_own_observation_layout(sprint, tiny_checkpoint,
                                                                   tiny_checkpoint_other_inputs):
    """Two policies trained with different inputs race each other from both sides, each fed rows of its own width;
    mixed teams, which share one layout per env, still refuse them."""
    from spiral.eval.evaluate import RaceSet, cross_play, evaluate_mixed_teams

    a, b = load_method(tiny_checkpoint), load_method(tiny_checkpoint_other_inputs)
    assert a.obs_layout["obs_dim"] != b.obs_layout["obs_dim"]  # a policy fed the other's rows would not run
    res, winners = cross_play(a, b, RaceSet(sprint, "1v1", 2, 0), sides="both")
    assert res.finished.shape == (4, 2) and winners.shape == (4,)
    for own, opponent in ((a, b), (b, a)):
        env, _ = setup_race(RaceSet(sprint, "1v1", 2, 0), own, opponent)
        assert env.obs_dim == own.obs_layout["obs_dim"] and env.opponent_observer is not None
        assert env.opponent_observer.rows(env.opponent_idx)["policy"].shape[1] == opponent.obs_layout["obs_dim"]
    with pytest.raises(ValueError, match="same obs_layout"):
        evaluate_mixed_teams(sprint, {"a": tiny_checkpoint, "b": tiny_checkpoint_other_inputs}, runs=2, seed=0)


def test_actions_beyond_the_clamped_range_are_counted_per_axis_over_racing_steps(sprint, tiny_checkpoint):
    """A policy commanding (2, 0.5, −0.2, −1.5) on every step is beyond ±1 on x and yaw in each step it races and on
    y and z in none; the steps stop counting when a drone's race ends, and the summary gives the shares 1, 0, 0, 1."""
    env, _ = setup_race(RaceSet(sprint, "1v1", 3, 0), load_method(tiny_checkpoint))
    command = torch.tensor([2.0, 0.5, -0.2, -1.5])
    res = run_races(env, lambda obs: command.expand(obs.shape[0], 4))
    assert res.racing_steps is not None and res.beyond_steps is not None
    assert bool((res.racing_steps > 0).all())
    assert bool((res.racing_steps <= env.max_episode_length).all())
    ended = res.finished | res.crashed
    assert bool((res.racing_steps[ended] < env.max_episode_length).all())  # no counting after the race ended
    assert torch.equal(res.beyond_steps[..., 0], res.racing_steps)  # exact: integer step counts
    assert torch.equal(res.beyond_steps[..., 3], res.racing_steps)  # exact: integer step counts
    assert int(res.beyond_steps[..., 1:3].sum()) == 0
    shares = summarize_races(res)["action_beyond_range"]
    assert shares == pytest.approx({"x": 1.0, "y": 0.0, "z": 0.0, "yaw": 1.0})  # ratios of integer counts
    swapped = res.permuted([1, 0])
    assert torch.equal(swapped.beyond_steps[:, 0], res.beyond_steps[:, 1])  # exact: integer step counts, permuted
