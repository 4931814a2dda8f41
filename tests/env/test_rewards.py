"""Reward terms: weights on a hand-made transition, the proximity, contact, closing and overtake terms, gate and
lap bonuses."""

from __future__ import annotations

import pytest
import torch

from spiral.config import RewardCfg
from spiral.env import compute_rewards, run_races
from spiral.env.rewards import REWARD_TERMS, StepOutcome
from tests.env.helpers import make_env, place, waypoint_policy


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
    """With the closing term at weight 0 every total equals, bit for bit, the sum of the other terms in the same order
    (for 154 drones one reduction over a stack of one more row would round differently)."""
    g = torch.Generator().manual_seed(0)
    outcome = StepOutcome(
        dist_before=3 * torch.rand(drones, generator=g), dist_after=3 * torch.rand(drones, generator=g),
        gates_passed=(torch.rand(drones, generator=g) < 0.1).int(), crashed_now=torch.rand(drones, generator=g) < 0.05,
        heading=torch.randn(drones, 3, generator=g), to_gate=torch.randn(drones, 3, generator=g),
        lap_time=3 + torch.rand(drones, generator=g), nearest=torch.rand(drones, generator=g),
        race_result=torch.randint(-1, 2, (drones,), generator=g).float())
    total, terms = compute_rewards(outcome, RewardCfg(proximity=0.1, win=3, closing=0.0))
    others = [terms[name] for name in REWARD_TERMS if name != "closing"]
    without = others[0]
    for term in others[1:]:
        without = without + term
    assert torch.equal(total, without)  # exact: one process, the same tensors; adding 0.0 is exact


def test_proximity_penalty_grows_linearly_inside_the_safe_distance(oval2):
    """Pay −w·(1 − d/d_safe) for the nearest racing drone: 0.2 m apart with d_safe 0.5 m costs 0.6·w per step,
    1 m apart costs nothing, and a lone drone pays nothing."""
    reward = RewardCfg(progress=0.0, gate=0.0, alignment=0.0, proximity=0.1, proximity_distance=0.5, closing=0.0,
                       win=0.0)
    env = make_env(oval2, worlds=1, drones=2, learners=(0, 1), training=False, reward=reward)
    env.reset()
    for gap, expected in ((0.2, -0.06), (1.0, 0.0)):
        place(env, [[-1.5, -1.0, 1.0], [-1.5, -1.0 + gap, 1.0]])
        hold = torch.zeros(2, 4)
        _, rewards, _, _ = env.step(hold)
        assert rewards.tolist() == pytest.approx([expected, expected], abs=2e-3)
    solo = make_env(oval2, worlds=1, training=False, reward=reward)
    _, rewards, _, _ = solo.step(torch.zeros(1, 4))
    assert float(solo.records.term_sums["proximity"][0]) == pytest.approx(0.0, abs=1e-12)  # clamped to 0


def test_closing_penalty_is_weighted_into_the_reward(oval2):
    """Two drones 0.5 m apart on one line, the one behind 1 m/s faster: with weight 2 and a 1 m window it pays
    2 · 1 · 1 · (1 − 0.5) = 1 after the step (the gap shrinks a little), the one ahead nothing."""
    reward = RewardCfg(progress=0.0, gate=0.0, alignment=0.0, proximity=0.0, win=0.0, closing=2.0, closing_distance=1.0)
    env = make_env(oval2, worlds=1, drones=2, learners=(0, 1), training=False, reward=reward)
    env.reset()
    place(env, [[-1.70, -1.0, 1.0], [-1.20, -1.0, 1.0]])
    env.vel[:2] = torch.tensor([[2.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    _, rewards, _, _ = env.step(torch.zeros(2, 4))
    assert float(rewards[1]) == pytest.approx(0.0, abs=1e-12) and -1.1 < float(rewards[0]) < -0.5  # clamped to 0


def test_scripted_lap_pays_each_gate_once_and_the_lap_bonus_once(oval2):
    """Fly gate 0, gate 1, gate 0 again: three gate bonuses, one lap bonus of 100 / lap time, success."""
    env = make_env(oval2, worlds=1, training=False, reward=RewardCfg(progress=0.0, alignment=0.0))
    policy = waypoint_policy(env)
    obs = env.reset()
    steps = 0
    while not (env.records.finished | env.records.crashed).all() and steps < env.max_episode_length:
        obs, _, _, _ = env.step(policy(obs))
        steps += 1
    assert bool(env.records.finished[0]) and not bool(env.records.crashed[0])
    assert float(env.records.term_sums["gate"][0]) == pytest.approx(3.0 * env.cfg.reward.gate)
    lap = float(env.records.lap_time[0])
    assert float(env.records.term_sums["lap"][0]) == pytest.approx(100.0 / lap, rel=1e-5)
    assert (steps - 1) * env.dt < lap <= steps * env.dt + 1e-6


def test_three_lap_race_pays_the_lap_bonus_for_each_lap_by_its_own_time(oval2):
    """A scripted 3-lap race on the two-gate oval: the lap term pays 100 / T at each of the three laps, T that lap's
    time (first lap from the start, the others gate 0 to gate 0), and the three times add up to the race time."""
    env = make_env(oval2, worlds=1, training=False, reward=RewardCfg(progress=0.0, alignment=0.0),
                   episode={"track_start_prob": 0.0, "laps": 3})
    res = run_races(env, waypoint_policy(env))
    assert bool(res.finished[0, 0]) and env.passes_needed == 2 * 3 + 1
    ends = res.split_time[0, 0, [2, 4, 6]]  # passages closing laps 1, 2 and 3
    laps = torch.cat([ends[:1], ends.diff()])
    assert float(laps.sum()) == pytest.approx(float(res.lap_time[0, 0]), rel=1e-6)
    assert float(env.records.term_sums["lap"][0]) == pytest.approx(float((100.0 / laps).sum()), rel=1e-5)
    assert float(env.records.term_sums["gate"][0]) == pytest.approx(7.0 * env.cfg.reward.gate)
