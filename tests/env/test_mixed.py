"""Format-mixed training: the world split, which drones sit in which slots, and actions reaching the right drones."""

from __future__ import annotations

import pytest
import torch
from pydantic import ValidationError

from spiral.config import AIRFRAMES, SimCfg, StageSpec
from spiral.env.mixed import MixedRaceEnv, training_env
from spiral.env.race_env import RaceEnv
from spiral.env.setting import RaceSetting


def mixed_stage(**kw) -> StageSpec:
    return StageSpec(name="2v2", scenario="2v2", worlds=8, iterations=1, mix={"solo": 0.25, "1v1": 0.25},
                     env={"obs": {"history_len": 1}, "episode": {"track_start_prob": 0.0}}, **kw)


def test_mix_splits_the_worlds_between_scenarios_the_stages_own_first():
    stage = mixed_stage()
    assert stage.world_split() == {"2v2": 4, "solo": 2, "1v1": 2}
    assert list(StageSpec(name="s", scenario="1v1", worlds=100, iterations=1, mix={"solo": 0.001}).world_split()
                .values()) == [99, 1]


@pytest.mark.parametrize(("scenario", "mix", "field"), [
    ("solo", {"1v1": 0.2}, "mix"), ("2v2", {"2v2": 0.2}, "mix.2v2"), ("2v2", {"1v1": 1.0}, "mix.1v1"),
    ("2v2", {"1v1": 0.6, "solo": 0.5}, "mix"),
], ids=["solo-stage", "own-format", "share-of-one", "nothing-left"])
def test_mixes_that_make_no_sense_are_refused_naming_the_field(scenario, mix, field):
    with pytest.raises(ValidationError, match=field):
        StageSpec(name="s", scenario=scenario, worlds=8, iterations=1, mix=mix)


def test_env_steps_budget_counts_the_learners_of_every_format():
    """24 steps per iteration over 4·2 + 2·1 + 2·1 learner drones: 288 env steps per iteration."""
    stage = StageSpec(name="2v2", scenario="2v2", worlds=8, env_steps=2880, mix={"solo": 0.25, "1v1": 0.25})
    assert stage.iteration_budget() == 10


def test_mixed_env_puts_each_scenarios_drones_in_its_slots_and_routes_actions_to_them(line2):
    """Parts in split order: 2v2 (learners 0, 1; opponents 2, 3), solo (learner 0 alone), 1v1 (learner 0, opponent
    1). Each learner row's action reaches its own drone; opponents fly their policy; a solo world has no opponent."""
    stage = mixed_stage()
    env = training_env(RaceSetting(line2, AIRFRAMES["cf2x"], SimCfg()), stage, device="cpu", seed=0)
    assert isinstance(env, MixedRaceEnv)
    assert list(env.parts) == ["2v2", "solo", "1v1"]
    shapes = {f: (p.world_count, p.drones_per_world, p.learner_slots, p.opponent_slots) for f, p in env.parts.items()}
    assert shapes == {"2v2": (4, 4, [0, 1], [2, 3]), "solo": (2, 1, [0], []), "1v1": (2, 2, [0], [1])}
    assert env.num_envs == 12 == env.current_observations().batch_size[0]

    def opponent(obs):
        return torch.full((obs.batch_size[0], 4), -0.5)

    env.set_opponent_policies({"2v2": opponent, "1v1": opponent})
    obs = env.reset()
    assert obs["policy"].shape == (12, env.obs_dim)
    assert env.parts["solo"].records.absent.tolist() == [False, False]
    assert env.parts["1v1"].records.absent.tolist() == [False] * 4
    actions = torch.linspace(-0.9, 0.9, 12)[:, None].expand(12, 4)
    obs, rewards, dones, extras = env.step(actions)
    assert rewards.shape == dones.shape == extras["time_outs"].shape == (12,)
    rows = iter(actions.split([8, 2, 2]))
    for part in env.parts.values():
        torch.testing.assert_close(part.last_action[part.learner_idx], next(rows))
        opponent = part.last_action[part.opponent_idx]  # the opponent's constant action
        torch.testing.assert_close(opponent, torch.full_like(opponent, -0.5))


def test_mixed_env_statistics_add_up_and_report_each_scenarios_success(line2):
    env = training_env(RaceSetting(line2, AIRFRAMES["cf2x"], SimCfg()), mixed_stage(), device="cpu", seed=0)
    parts = list(env.parts.values())
    for part, (episodes, successes) in zip(parts, [(4, 3), (2, 2), (2, 0)], strict=True):
        part.stats.sums["episodes"] += episodes  # the sums the parts keep on their device
        part.stats.sums["successes"] += successes
    stats = env.pop_stats()
    assert stats["episodes"] == 8 and stats["success"] == pytest.approx(5 / 8)
    assert (stats["success/2v2"], stats["success/solo"], stats["success/1v1"]) == pytest.approx((0.75, 1.0, 0.0))
    assert env.pop_stats()["episodes"] == 0


def test_a_stage_without_mix_trains_on_one_plain_race_env(line2):
    stage = StageSpec(name="1v1", scenario="1v1", worlds=3, iterations=1, env={"obs": {"history_len": 1}})
    env = training_env(RaceSetting(line2, AIRFRAMES["cf2x"], SimCfg()), stage, device="cpu", seed=0)
    assert type(env) is RaceEnv and env.num_envs == 3


def test_a_1v1_stage_with_2v2_worlds_races_a_learner_team_of_two_against_two_opponents(line2):
    """A format with more drones than the stage's own: in the 2v2 worlds of a 1v1 stage both drones of team A are
    learner rows (slots 0, 1) and the opponents fly slots 2, 3; the 1v1 worlds come first."""
    stage = StageSpec(name="1v1", scenario="1v1", worlds=8, iterations=1, mix={"2v2": 0.25},
                      env={"obs": {"history_len": 1}, "episode": {"track_start_prob": 0.0}})
    assert stage.world_split() == {"1v1": 6, "2v2": 2}
    assert stage.iteration_budget() == 1
    env = training_env(RaceSetting(line2, AIRFRAMES["cf2x"], SimCfg()), stage, device="cpu", seed=0)
    shapes = {f: (p.world_count, p.drones_per_world, p.learner_slots, p.opponent_slots) for f, p in env.parts.items()}
    assert shapes == {"1v1": (6, 2, [0], [1]), "2v2": (2, 4, [0, 1], [2, 3])}
    assert env.num_envs == 6 + 2 * 2
    env.set_opponent_policies({f: (lambda obs: torch.full((obs.batch_size[0], 4), 0.25)) for f in env.parts})
    env.reset()
    actions = torch.linspace(-0.9, 0.9, 10)[:, None].expand(10, 4)
    env.step(actions)
    rows = iter(actions.split([6, 4]))
    for part in env.parts.values():
        torch.testing.assert_close(part.last_action[part.learner_idx], next(rows))
        opponent = part.last_action[part.opponent_idx]  # the opponent's constant action
        torch.testing.assert_close(opponent, torch.full_like(opponent, 0.25))
