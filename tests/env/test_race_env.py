"""RaceEnv: observation layout and masking, reward terms, laps, resets and health."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from spiral.config import AIRFRAMES, EnvCfg, ObsCfg, RewardCfg, SimCfg, TrackSpec
from spiral.core.checkpoint import load_policy
from spiral.env import HISTORY_FEATURES, RaceEnv, compute_rewards, run_races
from spiral.env.events import closing_in, contact_fault, lap_splits, overtakes
from spiral.env.observations import HISTORY_FIELDS, OBS_TERMS, other_drone_columns
from spiral.env.racing import BEARINGS, contact_bearing
from spiral.env.rewards import StepOutcome
from spiral.eval.metrics import summarize_races
from spiral.sim.state import COLLISION_KINDS

CF2X = AIRFRAMES["cf2x"]
ROOT = Path(__file__).resolve().parents[2]


def make_env(track: TrackSpec, *, worlds: int = 2, drones: int = 1, learners=(0,), auto_reset: bool = True,
             obs: ObsCfg | None = None, **env_kw) -> RaceEnv:
    env_kw.setdefault("episode", {"track_start_prob": 0.0})
    cfg = EnvCfg(obs=obs or ObsCfg(history_len=3), **env_kw)
    return RaceEnv(track, CF2X, SimCfg(), cfg, world_count=worlds, drones_per_world=drones, learner_slots=learners,
                   seed=3, auto_reset=auto_reset)


def place(env: RaceEnv, positions: list[list[float]]) -> None:
    """Put the drones of world 0 at ``positions``, at rest, and rebuild the observations."""
    env.pos[: len(positions)] = torch.tensor(positions)
    env.vel.zero_()
    env.get_observations()


def term(env: RaceEnv, name: str) -> torch.Tensor:
    """Observe now and return observation term ``name`` of every learner drone."""
    return env.obs_builder.select(env.get_observations()["policy"], name)


def newest(env: RaceEnv, obs: torch.Tensor, field: str) -> torch.Tensor:
    """History field ``field`` of the newest history entry in observation rows ``obs``."""
    return env.obs_builder.select_history(obs, field)[:, -1]


def waypoint_policy(env: RaceEnv, drones: torch.Tensor | None = None):
    """Line up 0.5 m in front of the next gate, then fly 0.6 m past its centre (the learner drones by default)."""
    def act(obs):
        idx = env.learner_idx if drones is None else drones
        gate = env.next_gate.long()[idx]
        center, forward = env.gate_center[gate], env.gate_forward[gate]
        rel_gate = env.pos[idx] - center
        along = (rel_gate * forward).sum(-1, keepdim=True)
        lateral = (rel_gate - along * forward).norm(dim=-1, keepdim=True)
        lined_up = (along > -0.2) | (lateral < 0.1)
        target = torch.where(lined_up, center + 0.6 * forward, center - 0.5 * forward)
        rel = (target - env.pos[idx]) / env.cfg.action.pos_scale
        return torch.cat([rel.clamp(-1, 1), torch.zeros(len(idx), 1)], dim=-1)
    return act


def test_observation_dimension_matches_the_paper_layout(oval2):
    """Give 12 ego + 2 presence + K·16 history inputs for the paper layout, K = 50."""
    env = make_env(oval2, obs=ObsCfg(history_len=50))
    assert env.obs_dim == 12 + 2 + 50 * HISTORY_FEATURES == 814
    assert env.get_observations()["policy"].shape == (2, 814)


def test_observation_slices_name_every_term_in_its_fixed_order(oval2):
    """Lay the enabled terms end to end in the registry's order, history last, with the widths the options give."""
    every = ObsCfg(history_len=2, gate_normals=True, pid_integral=True, opponent_velocity=True, teammates=True,
                   closest_approach=True, priority=True)
    env = make_env(oval2, worlds=1, drones=2, learners=(0, 1), obs=every)
    slices = env.obs_builder.slices()
    assert list(slices) == list(OBS_TERMS)
    widths = {name: stop - start for name, (start, stop) in slices.items()}
    assert widths == {"ego": 12, "presence": 2, "gate_normals": 6, "pid_integral": 3, "opponent_velocity": 6,
                      "teammates": 2, "closest_approach": 8, "priority": 3, "history": 2 * HISTORY_FEATURES}
    assert [start for start, _ in slices.values()] == [0, *[stop for _, stop in list(slices.values())[:-1]]]
    assert slices["history"][1] == env.obs_dim
    assert HISTORY_FIELDS == {"opponents": (0, 6), "gates": (6, 12), "action": (12, 16)}
    paper = make_env(oval2, obs=ObsCfg(history_len=50)).obs_builder.slices()
    assert paper == {"ego": (0, 12), "presence": (12, 14), "history": (14, 814)}


def test_shipped_checkpoints_keep_their_stored_observation_layout(oval2):
    """Build, from each shipped policy's stored env settings, an env whose layout is the one stored with it."""
    paths = sorted((ROOT / "checkpoints").glob("*/*/best.pt"))
    assert paths
    for path in paths:
        policy = load_policy(path)
        env = RaceEnv(oval2, CF2X, SimCfg(), EnvCfg.model_validate(policy.meta["env"]), world_count=1,
                      drones_per_world=2, learner_slots=(0,))
        assert env.obs_builder.layout() == policy.obs_layout, path


def test_solo_observation_masks_absent_opponents(oval2):
    """Zero the opponent slots and presence flags when a drone races alone."""
    env = make_env(oval2, obs=ObsCfg(history_len=1))
    obs = env.get_observations()["policy"]
    assert torch.all(env.obs_builder.select(obs, "presence") == 0)
    assert torch.all(env.obs_builder.select_history(obs, "opponents") == 0)


def test_observation_lists_nearest_present_drones_first(oval2):
    """Order the other drones by distance and drop crashed ones from a 4-drone scene."""
    env = make_env(oval2, worlds=1, drones=4, learners=(0, 1, 2, 3), obs=ObsCfg(history_len=1))
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
    obs_cfg = ObsCfg(history_len=1, opponent_velocity=True, teammates=True)
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


def test_teammate_flags_leave_layouts_without_them_unchanged(oval2):
    """A layout without the option is the one stored before it existed; 1v1 has no team mate to flag."""
    env = make_env(oval2, worlds=1, drones=2, learners=(0,), obs=ObsCfg(history_len=1))
    assert "teammates" not in env.obs_builder.layout()
    env = make_env(oval2, worlds=1, drones=2, learners=(0,), obs=ObsCfg(history_len=1, teammates=True))
    assert env.obs_builder.layout()["teammates"] is True
    assert torch.all(term(env, "teammates") == 0)


def test_priority_inputs_give_the_own_priority_and_how_much_higher_the_nearest_drones_are(oval2):
    """Priorities are drawn in [0, 1) per drone at every race start; a drone observes its own, then the nearest
    and the second nearest drone's minus its own (0 for a drone that left the race), after the other extras."""
    obs_cfg = ObsCfg(history_len=1, teammates=True, priority=True)
    env = make_env(oval2, worlds=1, drones=4, learners=(0, 1, 2, 3), obs=obs_cfg)
    assert env.obs_dim == 12 + 2 + 2 + 3 + HISTORY_FEATURES
    drawn = env.priority.clone()
    assert ((drawn >= 0) & (drawn < 1)).all() and len(set(drawn.tolist())) == 4
    env.priority[:] = torch.tensor([0.5, 0.9, 0.2, 0.6])
    # Drone 0's nearest are 2, then 1; drone 3's are 2, then 0.
    place(env, [[-1.0, -1.0, 1.0], [-1.0, -0.2, 1.0], [-1.0, -1.3, 1.0], [-1.0, -1.9, 1.0]])
    prio = term(env, "priority")
    torch.testing.assert_close(prio[0], torch.tensor([0.5, -0.3, 0.4]))
    torch.testing.assert_close(prio[3], torch.tensor([0.6, -0.4, -0.1]))
    env.out[2] = 1  # drone 2 leaves the race: drone 0's nearest are 1, then 3
    torch.testing.assert_close(term(env, "priority")[0], torch.tensor([0.5, 0.4, 0.1]))
    env.reset()
    assert not torch.allclose(env.priority, torch.tensor([0.5, 0.9, 0.2, 0.6]))  # fresh draws


def test_closest_approach_inputs_predict_where_and_when_the_nearest_drones_pass(oval2):
    """Drone 1 0.4 m ahead and 0.1 m aside, closing at 2 m/s: they pass 0.1 m apart at t* = 0.2 s, 0.4 of the 0.5 s
    horizon; each drone sees the other's offset at that moment. A drone that moves away is at its closest now."""
    obs_cfg = ObsCfg(history_len=1, closest_approach=True, approach_horizon_s=0.5)
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
    env = make_env(oval2, worlds=1, obs=ObsCfg(history_len=1))
    place(env, [[-1.0, -1.0, 1.0]])
    gates = newest(env, env.get_observations()["policy"], "gates")[0].view(2, 3)
    assert torch.allclose(gates, torch.tensor([[1.0, 0.0, 0.0], [1.0, 2.0, 0.0]]), atol=1e-6)


def test_history_keeps_the_last_k_entries_oldest_first(oval2):
    """Shift the history by one entry per step; the newest entry holds the last action."""
    env = make_env(oval2, worlds=1, obs=ObsCfg(history_len=3))
    actions = [torch.full((1, 4), v) for v in (0.1, 0.2, 0.3)]
    for a in actions:
        obs, *_ = env.step(a)
    actions = env.obs_builder.select_history(obs["policy"], "action")[0]
    expected = torch.tensor([[0.1] * 4, [0.2] * 4, [0.3] * 4])
    assert torch.allclose(actions, expected)


def test_reward_terms_on_a_hand_made_transition():
    """Weight each named term and sum them."""
    cfg = RewardCfg(progress=2.0, gate=3.0, collision=10.0, alignment=1.0, alignment_threshold_deg=60.0, lap=1.0)
    outcome = StepOutcome(
        dist_before=torch.tensor([2.0, 1.0]), dist_after=torch.tensor([1.5, 1.0]),
        gates_passed=torch.tensor([1, 0]), crashed_now=torch.tensor([False, True]),
        heading=torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]),
        to_gate=torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
        lap_time=torch.tensor([5.0, 0.0]))
    total, terms = compute_rewards(outcome, cfg)
    assert terms["progress"].tolist() == pytest.approx([1.0, 0.0])
    assert terms["gate"].tolist() == pytest.approx([3.0, 0.0])
    assert terms["collision"].tolist() == pytest.approx([0.0, -10.0])
    assert terms["alignment"].tolist() == pytest.approx([0.5, 0.0])
    assert terms["lap"].tolist() == pytest.approx([20.0, 0.0])
    assert total.tolist() == pytest.approx([24.5, -10.0])


@pytest.mark.parametrize("drones", [154, 512])
@pytest.mark.bitwise
def test_a_term_at_weight_zero_leaves_every_total_bit_for_bit(drones):
    """With the contact, closing and overtake terms at weight 0 the totals equal, bit for bit, one reduction over the
    terms summed before they existed (for 154 drones a reduction over one more row would round differently)."""
    from spiral.env import rewards

    g = torch.Generator().manual_seed(0)
    outcome = StepOutcome(
        dist_before=3 * torch.rand(drones, generator=g), dist_after=3 * torch.rand(drones, generator=g),
        gates_passed=(torch.rand(drones, generator=g) < 0.1).int(), crashed_now=torch.rand(drones, generator=g) < 0.05,
        heading=torch.randn(drones, 3, generator=g), to_gate=torch.randn(drones, 3, generator=g),
        lap_time=3 + torch.rand(drones, generator=g), nearest=torch.rand(drones, generator=g),
        race_result=torch.randint(-1, 2, (drones,), generator=g).float())
    total, terms = compute_rewards(outcome, RewardCfg(proximity=0.1, win=3))
    before = torch.stack([terms[name] for name in rewards.SUMMED_AT_ONCE]).sum(0)
    assert torch.equal(total, before) and set(terms) - set(rewards.SUMMED_AT_ONCE) == {
        "contact", "closing", "overtake"}


def test_proximity_penalty_grows_linearly_inside_the_safe_distance(oval2):
    """Pay −w·(1 − d/d_safe) for the nearest racing drone: 0.2 m apart with d_safe 0.5 m costs 0.6·w per step,
    1 m apart costs nothing, and a lone drone pays nothing."""
    reward = RewardCfg(progress=0.0, gate=0.0, alignment=0.0, proximity=0.1, proximity_distance=0.5)
    env = make_env(oval2, worlds=1, drones=2, learners=(0, 1), auto_reset=False, reward=reward)
    env.reset()
    for gap, expected in ((0.2, -0.06), (1.0, 0.0)):
        place(env, [[-1.5, -1.0, 1.0], [-1.5, -1.0 + gap, 1.0]])
        hold = torch.zeros(2, 4)
        _, rewards, _, _ = env.step(hold)
        assert rewards.tolist() == pytest.approx([expected, expected], abs=2e-3)
    solo = make_env(oval2, worlds=1, auto_reset=False, reward=reward)
    _, rewards, _, _ = solo.step(torch.zeros(1, 4))
    assert float(solo.term_sums["proximity"][0]) == pytest.approx(0.0, abs=1e-12)  # clamped to 0


def test_proximity_leader_share_charges_the_drone_behind_in_full_and_the_leader_its_share(oval2):
    """In line towards gate 0 (east, at x = 0), 0.2 m apart: the drone behind (west) pays −w·0.6, the one in front
    pays the share ``proximity_leader`` of it; abreast both pay in full."""
    reward = RewardCfg(progress=0.0, gate=0.0, alignment=0.0, proximity=0.1, proximity_distance=0.5,
                       proximity_leader=0.25)
    env = make_env(oval2, worlds=1, drones=2, learners=(0, 1), auto_reset=False, reward=reward)
    env.reset()
    hold = torch.zeros(2, 4)
    place(env, [[-1.7, -1.0, 1.0], [-1.5, -1.0, 1.0]])  # drone 1 leads towards the gate
    _, rewards, _, _ = env.step(hold)
    assert rewards.tolist() == pytest.approx([-0.06, -0.015], abs=2e-3)
    place(env, [[-1.5, -1.1, 1.0], [-1.5, -0.9, 1.0]])  # abreast: neither is behind the other
    _, rewards, _, _ = env.step(hold)
    assert rewards.tolist() == pytest.approx([-0.06, -0.06], abs=2e-3)


@pytest.mark.parametrize(("v0", "v1", "expected"), [(3.0, 1.0, [-4.0, 0.0]), (2.0, -2.0, [-2.0, -2.0])])
def test_contact_penalty_charges_the_drone_that_runs_into_another_by_its_share_of_the_closing_speed(
        oval2, v0, v1, expected):
    """Two drones 0.13 m apart on one line (contact below 0.12 m): the one behind at 3 m/s runs into one ahead at
    1 m/s and pays the whole contact weight, the one ahead nothing; flying into each other alike, each pays half."""
    reward = RewardCfg(progress=0.0, gate=0.0, alignment=0.0, collision=0.0, contact=4.0)
    env = make_env(oval2, worlds=1, drones=2, learners=(0, 1), auto_reset=False, reward=reward)
    env.reset()
    place(env, [[-1.70, -1.0, 1.0], [-1.57, -1.0, 1.0]])
    env.vel[:2] = torch.tensor([[v0, 0.0, 0.0], [v1, 0.0, 0.0]])
    _, rewards, _, _ = env.step(torch.zeros(2, 4))
    assert env.crashed[:2].all() and ((env.crash_kind[:2] & COLLISION_KINDS["drone"]) != 0).all()
    assert rewards.tolist() == pytest.approx(expected)


def test_closing_in_charges_the_drone_that_runs_up_on_a_slower_one_and_shares_a_convergence():
    """Four pairs of drones (two worlds of four, each pair far from the other): a drone at 4.5 m/s 0.5 m behind one
    at 4 m/s closes in at 0.5 m/s and takes all of it, at half weight halfway into the 1 m window, the one ahead
    nothing; two drones 0.4 m apart side by side, each drifting 0.5 m/s towards the other while flying on at 4 m/s,
    close in at 1 m/s and share it; drones drifting apart, and a pair 1.5 m apart, pay nothing; so does a drone
    whose only near neighbour has left the race."""
    pos = torch.tensor([[0.0, 0.0, 1.0], [0.5, 0.0, 1.0], [5.0, 0.0, 1.0], [5.0, 0.4, 1.0],
                        [9.0, 0.0, 1.0], [9.0, 0.3, 1.0], [12.0, 0.0, 1.0], [13.5, 0.0, 1.0]])
    vel = torch.tensor([[4.5, 0.0, 0.0], [4.0, 0.0, 0.0], [4.0, 0.5, 0.0], [4.0, -0.5, 0.0],
                        [4.0, -0.5, 0.0], [4.0, 0.5, 0.0], [4.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    out = torch.zeros(8, dtype=torch.int32)
    rate = closing_in(pos, vel, out, distance=1.0, world_count=2, drones_per_world=4)
    assert rate.tolist() == pytest.approx([0.25, 0.0, 0.3, 0.3, 0.0, 0.0, 0.0, 0.0])
    out[1] = 1  # drone 1 left the race: drone 0's nearest racing drone is now 2, 5 m away
    after = closing_in(pos, vel, out, distance=1.0, world_count=2, drones_per_world=4)
    assert after[:2].tolist() == pytest.approx([0.0, 0.0], abs=1e-12)  # clamped and masked to 0


def test_closing_in_with_a_miss_distance_charges_collision_courses_only():
    """Three pairs, each drone behind faster than the one ahead: 0.5 m straight behind it, on course to hit, it
    pays as without a miss distance (0.5 m/s · 0.5 = 0.25); 0.6 m behind and 0.2 m aside it would pass 0.2 m from
    it, a third of a 0.3 m miss distance short of it: a third of what it pays without one; 0.5 m behind and 0.4 m
    aside it overtakes wide and pays nothing, where without a miss distance it pays its full closing rate."""
    pos = torch.tensor([[0.0, 0.0, 1.0], [0.5, 0.0, 1.0], [5.0, 0.0, 1.0], [5.6, 0.2, 1.0],
                        [9.0, 0.0, 1.0], [9.5, 0.4, 1.0]])
    vel = torch.tensor([[4.5, 0.0, 0.0], [4.0, 0.0, 0.0], [5.0, 0.0, 0.0], [4.0, 0.0, 0.0],
                        [5.0, 0.0, 0.0], [4.0, 0.0, 0.0]])
    out = torch.zeros(6, dtype=torch.int32)
    every = closing_in(pos, vel, out, distance=1.0, world_count=3, drones_per_world=2)
    course = closing_in(pos, vel, out, distance=1.0, world_count=3, drones_per_world=2, miss=0.3)
    rate, near = 0.6 / 0.4**0.5, 1.0 - 0.4**0.5  # the second pair's closing rate and nearness
    wide_rate, wide_near = 0.5 / 0.41**0.5, 1.0 - 0.41**0.5  # the third pair's
    assert every.tolist() == pytest.approx([0.25, 0.0, rate * near, 0.0, wide_rate * wide_near, 0.0])
    assert course.tolist() == pytest.approx([0.25, 0.0, rate * near / 3, 0.0, 0.0, 0.0])


def test_closing_in_over_three_neighbours_charges_an_opponent_behind_a_nearer_team_mate():
    """A 2v2 world: drone 0 flies at 4.5 m/s beside its team mate (0.2 m, same velocity) and 0.5 m behind an
    opponent at 4 m/s. Counting the nearest drone only it pays nothing (its team mate keeps the gap); counting its
    three nearest it pays for the opponent ahead as a 1v1 drone would (0.5 m/s · 1 · 0.5 = 0.25); its team mate, whose
    offset to the opponent is (0.5, −0.2) m, pays its own closing rate on it; the opponent and the far drone nothing."""
    pos = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.2, 1.0], [0.5, 0.0, 1.0], [5.0, 0.0, 1.0]])
    vel = torch.tensor([[4.5, 0.0, 0.0], [4.5, 0.0, 0.0], [4.0, 0.0, 0.0], [4.0, 0.0, 0.0]])
    out = torch.zeros(4, dtype=torch.int32)
    nearest = closing_in(pos, vel, out, distance=1.0, world_count=1, drones_per_world=4)
    three = closing_in(pos, vel, out, distance=1.0, world_count=1, drones_per_world=4, neighbours=3)
    d = 0.29**0.5  # team mate to opponent
    assert nearest.tolist() == pytest.approx([0.0, 0.0, 0.0, 0.0])
    assert three.tolist() == pytest.approx([0.25, (0.5 * 0.5 / d) * (1.0 - d), 0.0, 0.0])


def test_closing_penalty_is_weighted_into_the_reward(oval2):
    """Two drones 0.5 m apart on one line, the one behind 1 m/s faster: with weight 2 and a 1 m window it pays
    2 · 1 · 1 · (1 − 0.5) = 1 after the step (the gap shrinks a little), the one ahead nothing."""
    reward = RewardCfg(progress=0.0, gate=0.0, alignment=0.0, closing=2.0, closing_distance=1.0)
    env = make_env(oval2, worlds=1, drones=2, learners=(0, 1), auto_reset=False, reward=reward)
    env.reset()
    place(env, [[-1.70, -1.0, 1.0], [-1.20, -1.0, 1.0]])
    env.vel[:2] = torch.tensor([[2.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    _, rewards, _, _ = env.step(torch.zeros(2, 4))
    assert float(rewards[1]) == pytest.approx(0.0, abs=1e-12) and -1.1 < float(rewards[0]) < -0.5  # clamped to 0


def test_overtakes_count_places_changing_hands_between_teams_only():
    """Two worlds of a 2v2 layout (teams {0, 1} and {2, 3}). World 0: drone 0 passes opponent 2 on the way to the
    same gate and its team mate 1 (a team mate's place does not count); drone 3 passes its gate and stays ahead of
    everyone. World 1 races 1v1 in slots 0 and 2 (slots 1 and 3 are out): drone 6 passes drone 4."""
    team = torch.tensor([0, 0, 1, 1])
    passed_before = torch.tensor([1, 1, 1, 1, 2, 2, 2, 2], dtype=torch.int32)
    passed_after = torch.tensor([1, 1, 1, 2, 2, 2, 2, 2], dtype=torch.int32)
    dist_before = torch.tensor([2.0, 1.5, 1.8, 0.1, 1.0, 0.0, 1.2, 0.0])
    dist_after = torch.tensor([1.0, 1.2, 1.6, 3.0, 0.8, 0.0, 0.7, 0.0])
    counted = torch.tensor([True, True, True, True, True, False, True, False])
    got = overtakes((passed_before, dist_before), (passed_after, dist_after), counted, team, world_count=2,
                    drones_per_world=4)
    # drone 0: opponents 2 and 3 ahead before, only 3 after: +1; drone 2 lost its place to it: -1; drone 1 had 3
    # ahead and 2 behind, before and after: 0; drone 3 led throughout: 0. Drone 6: +1, drone 4: -1.
    assert got.tolist() == pytest.approx([1.0, 0.0, -1.0, 0.0, -1.0, 0.0, 1.0, 0.0])


def test_a_pass_in_a_start_box_race_is_paid_to_both_drones_at_the_step_it_happens(oval2):
    """Two drones of a 1v1 start-box race, side by side 0.5 m before gate 0, one flying 2 m/s faster than the other
    0.1 m ahead of it: at the step it passes, the overtake term pays it +w and the other −w; the step before and
    the steps after nothing."""
    reward = RewardCfg(progress=0.0, gate=0.0, alignment=0.0, lap=0.0, overtake=1.5)
    env = make_env(oval2, worlds=1, drones=2, learners=(0, 1), auto_reset=False, reward=reward)
    env.reset()
    assert bool(env.contested[0])
    place(env, [[-0.60, -1.15, 1.0], [-0.50, -0.85, 1.0]])
    paid = []
    for _ in range(8):
        env.vel[:2] = torch.tensor([[3.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
        before = env.pos[:2, 0].clone()
        _, rewards, _, _ = env.step(torch.tensor([[0.3, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]))
        paid.append((rewards.tolist(), bool(before[0] < before[1]), bool(env.pos[0, 0] > env.pos[1, 0])))
    passes = [i for i, (_, was_behind, now_ahead) in enumerate(paid) if was_behind and now_ahead]
    assert len(passes) == 1
    for i, (r, _, _) in enumerate(paid):
        assert r == pytest.approx([1.5, -1.5] if i == passes[0] else [0.0, 0.0], abs=1e-6)


def test_contact_fault_takes_the_closing_speed_along_the_offset_before_the_step():
    """A drone closing at 2 m/s on one that flies away from it at 1 m/s takes it all; a drone crossing at right
    angles shares with the one that flies into it by their closing speeds; drones without a contact pay nothing."""
    pos_before = torch.tensor([[0.0, 0.0, 1.0], [0.3, 0.0, 1.0], [5.0, 0.0, 1.0], [5.0, 0.3, 1.0]])
    vel_before = torch.tensor([[2.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 1.0, 0.0], [0.0, -3.0, 0.0]])
    pos = pos_before + 0.02 * vel_before
    racing = torch.ones(4, dtype=torch.bool)
    contact = torch.tensor([True, True, True, True])
    share = contact_fault(pos, pos_before, vel_before, racing, contact, world_count=2, drones_per_world=2)
    assert share.tolist() == pytest.approx([1.0, 0.0, 0.25, 0.75])
    none = contact_fault(pos, pos_before, vel_before, racing, torch.zeros(4, dtype=torch.bool), world_count=2,
                         drones_per_world=2)
    assert none.tolist() == pytest.approx([0.0] * 4, abs=1e-12)  # masked to 0


def test_opponents_with_their_own_layout_read_what_an_env_of_that_layout_shows_them(oval2):
    """Opponent slots driven by a policy with other inputs are observed with its layout: after the same starts and
    actions their rows equal those an env built with that layout gives the same drones, while the learner keeps the
    env's layout."""
    mine, theirs = ObsCfg(history_len=3), ObsCfg(history_len=1, gate_normals=True, opponent_velocity=True)
    widths = []

    def opponent(obs):
        widths.append(obs["policy"].shape[1])
        return torch.full((obs.batch_size[0], 4), 0.2)

    env = make_env(oval2, worlds=2, drones=2, learners=(0,), auto_reset=False, obs=mine)
    env.set_opponent_policy(opponent, obs=theirs)
    ref = make_env(oval2, worlds=2, drones=2, learners=(0, 1), auto_reset=False, obs=theirs)
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
    observes once the other drones have left the race: its ego state, gates, integral, own priority and actions
    stay."""
    every = ObsCfg(history_len=2, gate_normals=True, pid_integral=True, opponent_velocity=True, teammates=True,
                   closest_approach=True, priority=True)
    env = make_env(oval2, worlds=1, drones=3, learners=(0, 1, 2), obs=every)
    place(env, [[-1.0, -1.0, 1.0], [-1.0, -0.6, 1.1], [-0.7, -1.0, 1.0]])
    env.vel[:3] = torch.tensor([[1.0, 0.0, 0.0], [0.5, -0.5, 0.0], [0.0, 0.0, 0.3]])
    env.get_observations()
    with_others = env.get_observations()["policy"][0]
    env.out[1:3] = 1
    env.get_observations()
    alone = env.get_observations()["policy"][0]
    hidden = other_drone_columns(every)
    assert int(hidden.sum()) == 2 + 6 + 2 + 8 + 2 + 2 * 6  # presence, velocities, mates, approach, priority, history
    assert (with_others[hidden] != 0).sum() > 20 and not alone[hidden].any()
    torch.testing.assert_close(with_others.masked_fill(hidden, 0.0), alone)  # the same columns from the same state


def test_scripted_lap_pays_each_gate_once_and_the_lap_bonus_once(oval2):
    """Fly gate 0, gate 1, gate 0 again: three gate bonuses, one lap bonus of 100 / lap time, success."""
    env = make_env(oval2, worlds=1, auto_reset=False, reward=RewardCfg(progress=0.0, alignment=0.0))
    policy = waypoint_policy(env)
    obs = env.reset()
    steps = 0
    while not (env.finished | env.crashed).all() and steps < env.max_episode_length:
        obs, _, _, _ = env.step(policy(obs))
        steps += 1
    assert bool(env.finished[0]) and not bool(env.crashed[0])
    assert float(env.term_sums["gate"][0]) == pytest.approx(3.0 * env.cfg.reward.gate)
    lap = float(env.lap_time[0])
    assert float(env.term_sums["lap"][0]) == pytest.approx(100.0 / lap, rel=1e-5)
    assert (steps - 1) * env.dt < lap <= steps * env.dt + 1e-6


def test_lap_splits_close_a_lap_every_gates_passages_after_the_start_line():
    """Three gates a lap, two drones: the start-line passage closes nothing, the fourth passage closes lap 1 at its
    passage time, the seventh lap 2 at the time since; a drone not counted (it crashed) gets no split."""
    lap_start, times = torch.zeros(2), []
    for passed, now in ((1, 0.5), (2, 1.6), (3, 2.7), (4, 3.9), (5, 5.0), (6, 6.2), (7, 7.3)):
        split, lap_start = lap_splits(torch.tensor([passed, passed]), torch.tensor([1, 1]), torch.tensor([now, now]),
                                      lap_start, torch.tensor([True, False]), gates=3)
        times.append(split.tolist())
    assert [t[0] for t in times] == pytest.approx([0.0, 0.0, 0.0, 3.9, 0.0, 0.0, 7.3 - 3.9])
    assert [t[1] for t in times] == pytest.approx([0.0] * 7)
    assert lap_start.tolist() == pytest.approx([7.3, 0.0])
    unchanged, _ = lap_splits(torch.tensor([4]), torch.tensor([0]), torch.tensor([3.9]), torch.zeros(1),
                              torch.tensor([True]), gates=3)
    assert unchanged.tolist() == pytest.approx([0.0])  # no passage in the step: no lap closed


def test_three_lap_race_pays_the_lap_bonus_for_each_lap_by_its_own_time(oval2):
    """A scripted 3-lap race on the two-gate oval: the lap term pays 100 / T at each of the three laps, T that lap's
    time (first lap from the start, the others gate 0 to gate 0), and the three times add up to the race time."""
    env = make_env(oval2, worlds=1, auto_reset=False, reward=RewardCfg(progress=0.0, alignment=0.0),
                   episode={"track_start_prob": 0.0, "laps": 3})
    res = run_races(env, waypoint_policy(env))
    assert bool(res.finished[0, 0]) and env.passes_needed == 2 * 3 + 1
    ends = res.split_time[0, 0, [2, 4, 6]]  # passages closing laps 1, 2 and 3
    laps = torch.cat([ends[:1], ends.diff()])
    assert float(laps.sum()) == pytest.approx(float(res.lap_time[0, 0]), rel=1e-6)
    assert float(env.term_sums["lap"][0]) == pytest.approx(float((100.0 / laps).sum()), rel=1e-5)
    assert float(env.term_sums["gate"][0]) == pytest.approx(7.0 * env.cfg.reward.gate)


def test_race_results_time_every_gate_passage_and_end_with_the_lap_time(oval2):
    """Split times of a scripted lap rise gate by gate, the last one is the lap time, and the summary averages them."""
    env = make_env(oval2, worlds=2, auto_reset=False)
    res = run_races(env, waypoint_policy(env))
    assert res.finished.all()
    splits = res.split_time[:, 0]
    assert splits.shape == (2, env.passes_needed)
    assert (splits[:, 0] > 0).all() and (splits.diff(dim=1) > 0).all()
    assert torch.allclose(splits[:, -1], res.lap_time[:, 0])
    assert summarize_races(res)["split_times"] == pytest.approx(splits.mean(dim=0).tolist())


@pytest.mark.parametrize("winner", ["learner", "opponent"])
def test_race_outcome_pays_the_first_finishers_team_and_charges_the_other_once(oval2, winner):
    """One drone flies the lap while the other holds its position far from the line: at the step the flyer
    completes the lap it gets +w and the other team's racing drone −w, and nothing more afterwards."""
    reward = RewardCfg(progress=0.0, gate=0.0, alignment=0.0, lap=0.0, collision=0.0, win=5.0)
    env = make_env(oval2, worlds=1, drones=2, learners=(0,), auto_reset=False, reward=reward)
    flyer = 0 if winner == "learner" else 1
    fly = waypoint_policy(env, torch.tensor([flyer]))
    hold = torch.zeros(1, 4)
    env.set_opponent_policy(lambda obs: fly(obs) if flyer == 1 else hold)
    obs = env.reset()
    assert env.contested.all()
    place(env, [[-1.2, -1.0, 1.0], [2.5, -2.5, 1.0]] if flyer == 0 else [[2.5, -2.5, 1.0], [-1.2, -1.0, 1.0]])
    paid_at = []
    for step in range(env.max_episode_length):
        before = env.term_sums["win"].clone()
        obs, _, _, _ = env.step(fly(obs) if flyer == 0 else hold)
        if (env.term_sums["win"] != before).any():
            paid_at.append(step)
        if env.finished[flyer]:
            break
    for _ in range(5):
        env.step(hold)
    assert bool(env.finished[flyer]) and not bool(env.crashed.any())
    assert paid_at == [step]
    assert env.term_sums["win"].tolist() == pytest.approx([5.0, -5.0] if flyer == 0 else [-5.0, 5.0])
    assert not env.contested.any()


def test_race_outcome_between_two_learner_drones_pays_by_race_team(oval2):
    """A mirror world whose two drones are both learners (no opponent policy): the race is contested, and when slot
    1 finishes first it gets +w and slot 0, still racing, −w."""
    reward = RewardCfg(progress=0.0, gate=0.0, alignment=0.0, lap=0.0, collision=0.0, win=5.0)
    env = make_env(oval2, worlds=1, drones=2, learners=(0, 1), auto_reset=False, reward=reward)
    fly = waypoint_policy(env, torch.tensor([1]))
    obs = env.reset()
    assert env.contested.all()
    place(env, [[2.5, -2.5, 1.0], [-1.2, -1.0, 1.0]])
    for _ in range(env.max_episode_length):
        obs, _, _, _ = env.step(torch.cat([torch.zeros(1, 4), fly(obs)]))
        if env.finished[1]:
            break
    assert bool(env.finished[1]) and not bool(env.crashed.any())
    assert env.term_sums["win"].tolist() == pytest.approx([-5.0, 5.0])


@pytest.mark.parametrize("forfeit", [False, True])
def test_a_crash_forfeits_an_undecided_race_only_when_asked(oval2, forfeit):
    """The opponent dives into the ground while the race is undecided: with ``forfeit`` it is charged the loss
    (−w) at the crash, otherwise nothing; the hovering learner is paid nothing either way."""
    reward = RewardCfg(progress=0.0, gate=0.0, alignment=0.0, lap=0.0, collision=0.0, win=5.0, forfeit=forfeit)
    env = make_env(oval2, worlds=1, drones=2, learners=(0,), auto_reset=False, reward=reward)
    env.set_opponent_policy(lambda obs: torch.tensor([[0.0, 0.0, -1.0, 0.0]]))
    env.reset()
    for _ in range(100):
        env.step(torch.zeros(1, 4))
        if env.crashed[1]:
            break
    assert bool(env.crashed[1]) and not bool(env.crashed[0])
    assert env.term_sums["win"].tolist() == pytest.approx([0.0, -5.0 if forfeit else 0.0])
    assert bool(env.contested[0])  # nobody has finished: the race is still open for the learner


def test_only_start_box_races_against_opponents_are_contested(oval2):
    """Contest the winner of start-box races with opponents present, not of track or file starts or solo flights."""
    def contested(track_start_prob: float, opponents: bool, file_start_prob: float = 0.0) -> torch.Tensor:
        env = make_env(oval2, worlds=4, drones=2, learners=(0,),
                       episode={"track_start_prob": track_start_prob, "file_start_prob": file_start_prob})
        env.set_opponent_policy((lambda obs: torch.zeros(len(obs["policy"]), 4)) if opponents else None)
        env.reset()
        return env.contested

    assert contested(0.0, opponents=True).all()
    assert not contested(1.0, opponents=True).any()
    assert not contested(0.0, opponents=True, file_start_prob=1.0).any()
    assert not contested(0.0, opponents=False).any()
    solo = make_env(oval2, worlds=4, drones=1, learners=(0,))
    assert not solo.contested.any()


@pytest.mark.parametrize("gap", [0.15, 0.25])
def test_contact_margin_makes_drones_closer_than_it_collide_in_training_only(oval2, gap):
    """Two hovering drones 0.15 m apart (their spheres, 0.12 m, do not touch) both end their episodes with a
    drone-drone crash in a training env with a 0.05 m margin; neither does at 0.25 m, nor without the margin, nor in
    an evaluation env."""
    def ended(margin: float, *, training: bool = True) -> tuple:
        env = make_env(oval2, worlds=1, drones=2, learners=(0, 1), auto_reset=training,
                       episode={"track_start_prob": 0.0, "contact_margin": margin})
        env.reset()
        place(env, [[-1.0, -1.0, 1.0], [-1.0, -1.0 + gap, 1.0]])
        _, _, dones, extras = env.step(torch.zeros(2, 4))
        if not training:
            return tuple(env.crashed.tolist())
        return (*dones.tolist(), env.stats["crash_drone"], bool(extras["time_outs"].any()))

    assert 2 * CF2X.radius == pytest.approx(0.12)
    expected = (True, True, 2.0, False) if gap < 0.17 else (False, False, 0.0, False)
    assert ended(0.05) == pytest.approx(expected)  # flags and a count
    assert ended(0.0) == pytest.approx((False, False, 0.0, False))
    assert ended(0.05, training=False) == (False, False)


def test_crash_pays_the_penalty_once_and_ends_the_episode(oval2):
    """Dive into the ground: one collision penalty, done, then an automatic reset of that world only."""
    env = make_env(oval2, worlds=2)
    down = torch.tensor([[0.0, 0.0, -1.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    penalties, done_at = [], None
    for step in range(120):
        before = env.term_sums["collision"].clone()
        _, _, done, extras = env.step(down)
        penalties.append(float(env.term_sums["collision"][0] - before[0]) if not done[0] else None)
        if done[0]:
            done_at = step
            break
    assert done_at is not None
    assert not bool(extras["time_outs"][0])
    assert env.stats["crash_ground"] == pytest.approx(1.0)  # a count
    assert env.stats["term_collision"] == pytest.approx(-env.cfg.reward.collision)
    assert float(env.world_time()[0]) == pytest.approx(0.0, abs=1e-12) and float(env.world_time()[1]) > 0.0  # reset


def test_time_limit_is_a_time_out_not_a_termination(oval2):
    """Mark a hovering drone's episode at the time limit as a time-out and reset its world."""
    env = make_env(oval2, worlds=1, episode={"track_start_prob": 0.0, "time_limit_s": 0.5})
    hover = torch.zeros(1, 4)
    outs = [env.step(hover) for _ in range(math.ceil(0.5 / env.dt))]
    _, _, done, extras = outs[-1]
    assert bool(done[0]) and bool(extras["time_outs"][0])
    assert all(not bool(o[2][0]) for o in outs[:-1])
    assert float(env.world_time()[0]) == pytest.approx(0.0, abs=1e-12)  # zeroed by the reset


def test_nonfinite_state_resets_the_world_and_never_reaches_observations(oval2):
    """Reset a world whose state went non-finite, count it, and keep observations finite."""
    env = make_env(oval2, worlds=2)
    env.omega[0] = float("nan")
    obs, _, done, _ = env.step(torch.zeros(2, 4))
    assert bool(done[0]) and not bool(done[1])
    assert torch.isfinite(obs["policy"]).all()
    assert env.pop_stats()["health/nonfinite_resets"] == pytest.approx(1.0)  # a count


def test_absent_opponent_slots_do_not_race(oval2):
    """Park opponent slots out of the race when no opponent policy is set."""
    env = make_env(oval2, worlds=2, drones=2, learners=(0,))
    assert env.num_envs == 2
    assert env.absent.view(2, 2)[:, 1].all() and not env.absent.view(2, 2)[:, 0].any()
    res = run_races(make_env(oval2, worlds=2, drones=2, learners=(0,), auto_reset=False), lambda o: torch.zeros(2, 4))
    assert not res.present[:, 1].any()


@pytest.mark.bitwise
def test_same_seed_gives_the_same_start_placements(oval2):
    """Draw identical start positions for the same seed, different ones for another seed."""
    a, b = make_env(oval2, worlds=4, drones=4, learners=(0, 1, 2, 3)), make_env(oval2, worlds=4, drones=4,
                                                                               learners=(0, 1, 2, 3))
    assert torch.equal(a.pos, b.pos)
    d = torch.cdist(a.pos.view(4, 4, 3), a.pos.view(4, 4, 3)) + torch.eye(4) * 10
    assert float(d.min()) >= 0.25


@pytest.mark.parametrize("partner", [1, 2], ids=["teammate", "opponent"])
def test_race_results_name_the_drone_each_crashed_drone_touched(oval2, partner):
    """Fly drone 0 and one other drone into each other in a 2v2 race: each records the other as its crash partner
    and the crash time; the two hovering drones record none, and the contacts count under the right team."""
    env = make_env(oval2, worlds=1, drones=4, learners=(0, 1), auto_reset=False)
    chase = {0: partner, partner: 0}

    def act(idx: torch.Tensor) -> torch.Tensor:
        rows = [(env.pos[chase[int(i)]] - env.pos[i]) / env.cfg.action.pos_scale if int(i) in chase
                else torch.zeros(3) for i in idx]
        return torch.cat([torch.stack(rows).clamp(-1, 1), torch.zeros(len(idx), 1)], dim=-1)

    env.set_opponent_policy(lambda obs: act(env.opponent_idx))
    res = run_races(env, lambda obs: act(env.learner_idx))
    others = [s for s in range(4) if s not in chase]
    assert res.crashed[0, [0, partner]].all() and not res.crashed[0, others].any()
    assert res.crash_partner[0, 0] == partner and res.crash_partner[0, partner] == 0
    assert (res.crash_partner[0, others] == -1).all()
    assert (res.crash_time[0, [0, partner]] > 0).all() and (res.crash_time[0, others] == 0).all()
    kind = "teammate" if partner == 1 else "opponent"
    summary = summarize_races(res)
    assert summary["drone_contacts"] == {"teammate": 0, "opponent": 0, kind: 2}
    assert summary["crash_gates"] == {"0": 2}
    # flying at each other, each had the other ahead of it; drones that did not touch anyone record no bearing
    assert summary["contact_bearing"] == {"ahead": 2, "beside": 0, "behind": 0}
    assert (res.contact_bearing[0, others] == -1).all()
    # both closed in alike, so neither flew into the other alone
    assert summary["contact_fault"]["even"] == 2 and summary["contact_fault"]["mean_share"] == pytest.approx(0.5)
    assert (res.contact_fault[0, others] == -1).all()


def test_race_results_charge_a_contact_to_the_drone_that_flew_into_a_hovering_one(oval2):
    """Drone 0 flies at drone 1, which hovers where it started: drone 0's share of the contact is 1 (``own``),
    drone 1's is 0 (``other``); the summary of either team counts its own drone's side only."""
    env = make_env(oval2, worlds=1, drones=2, learners=(0,), auto_reset=False)
    env.set_opponent_policy(lambda obs: torch.zeros(1, 4))
    res = run_races(env, lambda obs: torch.cat([((env.pos[1] - env.pos[0]) / env.cfg.action.pos_scale).clamp(-1, 1),
                                                torch.zeros(1)])[None])
    assert res.crashed[0].all() and res.contact_fault[0].tolist() == pytest.approx([1.0, 0.0], abs=0.05)
    # the hovering drone drifts a hair (float32 hover thrust): the shares are 1 and 0 to well within 1e-3
    own, other = (summarize_races(res, [slot])["contact_fault"] for slot in (0, 1))
    assert own == pytest.approx({"own": 1, "even": 0, "other": 0, "mean_share": 1.0}, abs=1e-3)
    assert other == pytest.approx({"own": 0, "even": 0, "other": 1, "mean_share": 0.0}, abs=1e-3)


def test_race_results_count_a_pass_of_a_hovering_drone_for_both_sides(oval2):
    """Drone 0 starts 1.4 m before gate 0, behind drone 1, which hovers 0.4 m off the line 1 m before the gate; drone
    0 flies through the gate and on: it passes drone 1 once and is never passed, drone 1 the other way round."""
    env = make_env(oval2, worlds=1, drones=2, learners=(0,), auto_reset=False)
    env.set_opponent_policy(lambda obs: torch.zeros(1, 4))
    reset = env.reset

    def reset_and_place():
        reset()
        place(env, [[-1.4, -1.0, 1.0], [-0.9, -0.6, 1.0]])
        return env.current_observations()

    env.reset = reset_and_place
    res = run_races(env, waypoint_policy(env))
    assert not res.crashed[0].any() and res.gates_passed[0, 0] > 1
    assert res.passes[0].tolist() == [[1, 0], [0, 1]]
    summary = summarize_races(res, [0])
    assert summary["passes"] == pytest.approx({"made": 1, "suffered": 0, "made_per_race": 1.0,
                                                "suffered_per_race": 0.0})


def test_contact_bearing_splits_ahead_beside_and_behind_at_45_degrees():
    """Another drone within 45° of the direction of travel is ahead, within 45° of the opposite behind, else beside;
    next to a drone that stands still it is beside."""
    vel = torch.tensor([[2.0, 0.0, 0.0]] * 5 + [[0.0, 0.0, 0.0]])
    rel = torch.tensor([[0.1, 0.05, 0.0], [0.1, 0.0, -0.11], [0.0, 0.1, 0.0], [-0.1, 0.0, 0.09], [-0.1, -0.2, 0.0],
                        [0.1, 0.0, 0.0]])
    assert contact_bearing(rel, vel).tolist() == [0, 1, 1, 2, 1, 1]
    assert [BEARINGS[i] for i in contact_bearing(rel[:1], -vel[:1]).tolist()] == ["behind"]


def test_race_critic_sees_every_other_drone_opponents_first(oval2):
    """Give the critic, after the policy's inputs, each other drone of the world: relative position and velocity,
    still racing, lead in gates passed; opponents before the teammate, nothing but the lead once a drone left."""
    env = make_env(oval2, worlds=1, drones=4, learners=(0, 1), obs=ObsCfg(history_len=1), critic="race")
    env.set_opponent_policy(lambda obs: torch.zeros(obs.batch_size[0], 4))  # hovering opponents in slots 2 and 3
    env.reset()
    place(env, [[-1.0, -1.0, 1.0], [-1.0, -0.5, 1.0], [-1.0, -1.0, 1.8], [-1.0, -2.5, 1.0]])
    env.vel[2] = torch.tensor([1.0, 0.0, 0.0])
    env.gates_passed[3] = 2
    obs = env.get_observations()
    assert obs["critic"].shape == (2, env.obs_dim + 3 * 8)
    torch.testing.assert_close(obs["critic"][:, : env.obs_dim], obs["policy"])  # the critic's inputs copy the policy's
    rows = obs["critic"][0, env.obs_dim :].view(3, 8)  # drone 0: opponents 2 and 3, then teammate 1
    assert torch.allclose(rows[:, :3], torch.tensor([[0.0, 0.0, 0.8], [0.0, -1.5, 0.0], [0.0, 0.5, 0.0]]), atol=1e-6)
    torch.testing.assert_close(rows[:, 3:6], torch.tensor(  # velocities set by the test
        [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]))
    assert rows[:, 6].tolist() == pytest.approx([1.0, 1.0, 1.0])  # 0/1 flags
    assert rows[:, 7].tolist() == pytest.approx([0.0, 2.0, 0.0])  # gate counts
    env.out[3] = 1  # drone 3 leaves the race
    rows = env.get_observations()["critic"][1, env.obs_dim :].view(3, 8)  # drone 1: opponents 2 and 3, teammate 0
    assert rows[1].tolist() == pytest.approx([0.0] * 6 + [0.0, 2.0])  # masked zeros and a gate count
    assert torch.allclose(rows[2, :3], torch.tensor([0.0, -0.5, 0.0]), atol=1e-6)
    assert float(rows[2, 6]) == pytest.approx(1.0)  # a flag


def test_resetting_some_worlds_draws_starts_for_them_only_and_a_full_reset_draws_as_before(oval2):
    """Worlds 1 and 3 of 4 restart in the start box; 0 and 2 keep their state. A reset of every world draws the
    placements of a fresh env with the same seed (evaluation placements do not depend on earlier partial resets)."""
    env = make_env(oval2, worlds=4, drones=2, learners=(0,))
    fresh = make_env(oval2, worlds=4, drones=2, learners=(0,))
    torch.testing.assert_close(env.pos, fresh.pos)
    env.pos[:] = 5.0
    env._reset_worlds(torch.tensor([False, True, False, True]))
    pos = env.pos.view(4, 2, 3)
    kept = pos[[0, 2]]  # set by the test and kept
    torch.testing.assert_close(kept, torch.full_like(kept, 5.0))
    lo = torch.tensor(oval2.start.center) - torch.tensor(oval2.start.size) / 2
    hi = lo + torch.tensor(oval2.start.size)
    assert ((pos[[1, 3]] >= lo - 1e-6) & (pos[[1, 3]] <= hi + 1e-6)).all()
    assert ((pos[[1, 3], 0] - pos[[1, 3], 1]).norm(dim=-1) >= oval2.start.min_separation - 1e-6).all()


@pytest.mark.parametrize(("track_start_prob", "cut_at"), [(0.0, 0.5), (1.0, None)], ids=["box-start", "track-start"])
def test_cut_start_box_episodes_end_as_time_outs_after_the_cut(oval2, track_start_prob, cut_at):
    """With every start-box episode cut at 0.5 s, hovering drones time out after 24 control steps (0.5 s at 48 Hz),
    bootstrapped rather than terminated; episodes started along the track run to the time limit."""
    env = make_env(oval2, worlds=2, drones=2, learners=(0,),
                   episode={"track_start_prob": track_start_prob, "start_cut_prob": 1.0, "start_cut_s": 0.5})
    env.set_opponent_policy(lambda obs: torch.zeros(len(obs["policy"]), 4))
    env.reset()
    steps, dones, time_outs = 0, torch.zeros(2, dtype=torch.bool), None
    while steps < 60 and not dones.any():
        _, _, dones, extras = env.step(torch.zeros(2, 4))
        steps, time_outs = steps + 1, extras["time_outs"]
    if cut_at is None:
        assert not dones.any() and env.cut_time.isinf().all()
    else:
        assert steps == round(cut_at / env.dt) and dones.all() and time_outs.all()
