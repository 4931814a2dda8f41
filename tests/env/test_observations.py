"""Observations: the layout of named terms, masking and neighbour order, the optional inputs, history, and opponents
with a layout of their own."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from spiral.config import EnvCfg, SimCfg
from spiral.core.checkpoint import load_policy
from spiral.env import HISTORY_FEATURES, RaceEnv, RaceSetting
from spiral.env.observations import HISTORY_FIELDS, OBS_TERMS, other_drone_columns
from tests.env.helpers import CF2X, make_env, newest, obs_with, paper_obs, place, term

ROOT = Path(__file__).resolve().parents[2]


def test_observation_dimension_matches_the_paper_layout(oval2):
    """Give 12 ego + 2 presence + K·16 history inputs for the paper layout, K = 50."""
    env = make_env(oval2, obs=paper_obs())
    assert env.obs_dim == 12 + 2 + 50 * HISTORY_FEATURES == 814
    assert env.get_observations()["policy"].shape == (2, 814)


def test_observation_slices_name_every_term_in_its_fixed_order(oval2):
    """Lay the enabled terms end to end in the registry's order, history last, with the widths the options give."""
    every = obs_with(history_len=2, gate_normals=True, pid_integral=True, opponent_velocity=True, teammates=True,
                   closest_approach=True)
    env = make_env(oval2, worlds=1, drones=2, learners=(0, 1), obs=every)
    slices = env.obs_builder.slices()
    assert list(slices) == list(OBS_TERMS)
    widths = {name: stop - start for name, (start, stop) in slices.items()}
    assert widths == {"ego": 12, "presence": 2, "gate_normals": 6, "pid_integral": 3, "opponent_velocity": 6,
                      "teammates": 2, "closest_approach": 8, "history": 2 * HISTORY_FEATURES}
    assert [start for start, _ in slices.values()] == [0, *[stop for _, stop in list(slices.values())[:-1]]]
    assert slices["history"][1] == env.obs_dim
    assert HISTORY_FIELDS == {"opponents": (0, 6), "gates": (6, 12), "action": (12, 16)}
    paper = make_env(oval2, obs=paper_obs()).obs_builder.slices()
    assert paper == {"ego": (0, 12), "presence": (12, 14), "history": (14, 814)}


def test_shipped_checkpoints_keep_their_stored_observation_layout(oval2):
    """Build, from each shipped policy's stored env settings, an env whose layout is the one stored with it."""
    paths = sorted((ROOT / "checkpoints").glob("*/*/best.pt"))
    assert paths
    for path in paths:
        policy = load_policy(path)
        env = RaceEnv(RaceSetting(oval2, CF2X, SimCfg()), EnvCfg.model_validate(policy.meta["env"]), world_count=1,
                      drones_per_world=2, learner_slots=(0,))
        assert env.obs_builder.layout() == policy.obs_layout, path


def test_solo_observation_masks_absent_opponents(oval2):
    """Zero the opponent slots and presence flags when a drone races alone."""
    env = make_env(oval2, obs=obs_with(history_len=1))
    obs = env.get_observations()["policy"]
    assert torch.all(env.obs_builder.select(obs, "presence") == 0)
    assert torch.all(env.obs_builder.select_history(obs, "opponents") == 0)


def test_observation_lists_nearest_present_drones_first(oval2):
    """Order the other drones by distance and drop crashed ones from a 4-drone scene."""
    env = make_env(oval2, worlds=1, drones=4, learners=(0, 1, 2, 3), obs=obs_with(history_len=1))
    place(env, [[-1.0, -1.0, 1.0], [-1.0, -0.5, 1.0], [-1.0, -1.0, 1.8], [-1.0, -2.5, 1.0]])
    others = newest(env, env.get_observations()["policy"], "opponents")[0].view(2, 3)
    assert torch.allclose(others, torch.tensor([[0.0, 0.5, 0.0], [0.0, 0.0, 0.8]]), atol=1e-6)
    env.out[1] = 1  # drone 1 leaves the race
    obs = env.get_observations()["policy"]
    others = newest(env, obs, "opponents")[0].view(2, 3)
    assert torch.allclose(others, torch.tensor([[0.0, 0.0, 0.8], [0.0, -1.5, 0.0]]), atol=1e-6)
    assert env.obs_builder.select(obs, "presence")[0].tolist() == pytest.approx([1.0, 1.0])  # 0/1 flags


def test_teammate_flags_mark_the_nearest_drones_of_the_own_race_team(oval2):
    """Flag a nearest drone of the own 2v2 team (slots 0, 1 against 2, 3), whoever drives the slots (training or a
    self-match), and never a drone that left the race; the flags come after the other extras."""
    obs_cfg = obs_with(history_len=1, opponent_velocity=True, teammates=True)
    for learners in [(0, 1), (0, 2)]:
        teams = make_env(oval2, worlds=1, drones=4, learners=learners, obs=obs_cfg).race_team
        assert teams.tolist() == [0, 0, 1, 1]
    env = make_env(oval2, worlds=1, drones=4, learners=(0, 1, 2, 3), obs=obs_cfg)
    assert env.obs_dim == 12 + 2 + 6 + 2 + HISTORY_FEATURES
    # Drone 0's nearest are 2 (opponent), then 1 (team mate); drone 3's are 2 (team mate), then 0 (opponent).
    place(env, [[-1.0, -1.0, 1.0], [-1.0, -0.2, 1.0], [-1.0, -1.3, 1.0], [-1.0, -1.9, 1.0]])
    assert list(env.obs_builder.slices())[-2:] == ["teammates", "history"]
    flags = term(env, "teammates")
    torch.testing.assert_close(flags, torch.tensor([[0.0, 1.0], [1.0, 0.0], [0.0, 1.0], [1.0, 0.0]]))  # 0/1 flags
    env.out[1] = 1  # drone 1 leaves the race: drone 0 sees two opponents, drone 1 sees nothing flagged
    flags = term(env, "teammates")
    assert flags[0].tolist() == pytest.approx([0.0, 0.0])  # 0/1 flags
    assert flags[2].tolist() == pytest.approx([0.0, 1.0])


def test_the_layout_records_every_option_and_1v1_has_no_team_mate_to_flag(oval2):
    """The stored layout spells out every option, on or off (layouts are compared whole)."""
    env = make_env(oval2, worlds=1, drones=2, learners=(0,), obs=obs_with(history_len=1))
    assert env.obs_builder.layout() == {"obs_dim": env.obs_dim, **obs_with(history_len=1).model_dump()}
    assert env.obs_builder.layout()["teammates"] is False
    env = make_env(oval2, worlds=1, drones=2, learners=(0,), obs=obs_with(history_len=1, teammates=True))
    assert env.obs_builder.layout()["teammates"] is True
    assert torch.all(term(env, "teammates") == 0)


def test_closest_approach_inputs_predict_where_and_when_the_nearest_drones_pass(oval2):
    """Drone 1 0.4 m ahead and 0.1 m aside, closing at 2 m/s: they pass 0.1 m apart at t* = 0.2 s, 0.4 of the 0.5 s
    horizon; each drone sees the other's offset at that moment. A drone that moves away is at its closest now."""
    obs_cfg = obs_with(history_len=1, closest_approach=True, approach_horizon_s=0.5)
    env = make_env(oval2, worlds=1, drones=3, learners=(0, 1, 2), obs=obs_cfg)
    assert env.obs_dim == 12 + 2 + 8 + HISTORY_FEATURES
    place(env, [[-1.0, -1.0, 1.0], [-0.6, -0.9, 1.0], [-1.0, -2.0, 1.0]])
    env.vel[:] = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    approach = term(env, "closest_approach").view(3, 2, 4)
    torch.testing.assert_close(approach[0, 0], torch.tensor([0.0, 0.1, 0.0, 0.4]))
    torch.testing.assert_close(approach[1, 0], torch.tensor([0.0, -0.1, 0.0, 0.4]))
    torch.testing.assert_close(approach[0, 1], torch.tensor([0.0, -1.0, 0.0, 0.0]))  # drone 2 flies off
    env.out[1] = env.out[2] = 1
    assert not term(env, "closest_approach")[0].any()


def test_observation_gives_next_two_gates_relative_to_the_drone(oval2):
    """Report gate 0 then gate 1 relative to the drone's position."""
    env = make_env(oval2, worlds=1, obs=obs_with(history_len=1))
    place(env, [[-1.0, -1.0, 1.0]])
    gates = newest(env, env.get_observations()["policy"], "gates")[0].view(2, 3)
    assert torch.allclose(gates, torch.tensor([[1.0, 0.0, 0.0], [1.0, 2.0, 0.0]]), atol=1e-6)


def test_history_keeps_the_last_k_entries_oldest_first(oval2):
    """Shift the history by one entry per step; the newest entry holds the last action."""
    env = make_env(oval2, worlds=1, obs=obs_with(history_len=3))
    actions = [torch.full((1, 4), v) for v in (0.1, 0.2, 0.3)]
    for a in actions:
        obs, *_ = env.step(a)
    actions = env.obs_builder.select_history(obs["policy"], "action")[0]
    expected = torch.tensor([[0.1] * 4, [0.2] * 4, [0.3] * 4])
    assert torch.allclose(actions, expected)


def test_opponents_with_their_own_layout_read_what_an_env_of_that_layout_shows_them(oval2):
    """Opponent slots driven by a policy with other inputs are observed with its layout: after the same starts and
    actions their rows equal those an env built with that layout gives the same drones, while the learner keeps the
    env's layout."""
    mine, theirs = obs_with(history_len=3), obs_with(history_len=1, gate_normals=True, opponent_velocity=True)
    widths = []

    def opponent(obs):
        widths.append(obs["policy"].shape[1])
        return torch.full((obs.batch_size[0], 4), 0.2)

    env = make_env(oval2, worlds=2, drones=2, learners=(0,), training=False, obs=mine)
    env.set_opponent_policy(opponent, obs=theirs)
    ref = make_env(oval2, worlds=2, drones=2, learners=(0, 1), training=False, obs=theirs)
    obs, _ = env.reset(), ref.reset()
    act = torch.tensor([[0.1, 0.0, 0.0, 0.0], [0.2, 0.2, 0.2, 0.2]]).repeat(2, 1)  # per world: learner, opponent
    for _ in range(3):
        obs, _, _, _ = env.step(act[0::2])
        ref.step(act)
    assert obs["policy"].shape[1] == env.obs_dim != ref.obs_dim
    assert set(widths) == {ref.obs_dim}
    seen = env.opponent_observer.rows(env.opponent_idx)["policy"]
    # another batch shape than the reference env's: float32 rounding may differ in the last bits
    torch.testing.assert_close(seen, ref.current_observations()["policy"][1::2], rtol=1e-5, atol=1e-6)


def test_hiding_the_other_drone_columns_shows_what_a_drone_alone_observes(oval2):
    """Zeroing the columns ``other_drone_columns`` marks in a drone's rows of a 3-drone world gives the rows it
    observes once the other drones have left the race: its ego state, gates, integral and actions stay."""
    every = obs_with(history_len=2, gate_normals=True, pid_integral=True, opponent_velocity=True, teammates=True,
                   closest_approach=True)
    env = make_env(oval2, worlds=1, drones=3, learners=(0, 1, 2), obs=every)
    place(env, [[-1.0, -1.0, 1.0], [-1.0, -0.6, 1.1], [-0.7, -1.0, 1.0]])
    env.vel[:3] = torch.tensor([[1.0, 0.0, 0.0], [0.5, -0.5, 0.0], [0.0, 0.0, 0.3]])
    env.get_observations()
    with_others = env.get_observations()["policy"][0]
    env.out[1:3] = 1
    env.get_observations()
    alone = env.get_observations()["policy"][0]
    hidden = other_drone_columns(every)
    assert int(hidden.sum()) == 2 + 6 + 2 + 8 + 2 * 6  # presence, velocities, mates, approach, history
    assert (with_others[hidden] != 0).sum() > 15 and not alone[hidden].any()
    torch.testing.assert_close(with_others.masked_fill(hidden, 0.0), alone)  # the same columns from the same state
