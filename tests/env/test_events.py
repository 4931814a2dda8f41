"""Race events: lap splits, closing in, overtakes, and the race outcome (first finisher)."""

from __future__ import annotations

import pytest
import torch

from spiral.config import RewardCfg
from spiral.env.events import closing_in, lap_splits, overtakes
from tests.env.helpers import make_env, place, waypoint_policy


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


@pytest.mark.parametrize("winner", ["learner", "opponent"])
def test_race_outcome_pays_the_first_finishers_team_and_charges_the_other_once(oval2, winner):
    """One drone flies the lap while the other holds its position far from the line: at the step the flyer
    completes the lap it gets +w and the other team's racing drone −w, and nothing more afterwards."""
    reward = RewardCfg(progress=0.0, gate=0.0, alignment=0.0, lap=0.0, collision=0.0, proximity=0.0, closing=0.0,
                       win=5.0)
    env = make_env(oval2, worlds=1, drones=2, learners=(0,), training=False, reward=reward)
    flyer = 0 if winner == "learner" else 1
    fly = waypoint_policy(env, torch.tensor([flyer]))
    hold = torch.zeros(1, 4)
    env.set_opponent_policy(lambda obs: fly(obs) if flyer == 1 else hold)
    obs = env.reset()
    assert env.contested.all()
    place(env, [[-1.2, -1.0, 1.0], [2.5, -2.5, 1.0]] if flyer == 0 else [[2.5, -2.5, 1.0], [-1.2, -1.0, 1.0]])
    paid_at = []
    for step in range(env.max_episode_length):
        before = env.records.term_sums["win"].clone()
        obs, _, _, _ = env.step(fly(obs) if flyer == 0 else hold)
        if (env.records.term_sums["win"] != before).any():
            paid_at.append(step)
        if env.records.finished[flyer]:
            break
    for _ in range(5):
        env.step(hold)
    assert bool(env.records.finished[flyer]) and not bool(env.records.crashed.any())
    assert paid_at == [step]
    assert env.records.term_sums["win"].tolist() == pytest.approx([5.0, -5.0] if flyer == 0 else [-5.0, 5.0])
    assert not env.contested.any()


def test_race_outcome_between_two_learner_drones_pays_by_race_team(oval2):
    """A mirror world whose two drones are both learners (no opponent policy): the race is contested, and when slot
    1 finishes first it gets +w and slot 0, still racing, −w."""
    reward = RewardCfg(progress=0.0, gate=0.0, alignment=0.0, lap=0.0, collision=0.0, proximity=0.0, closing=0.0,
                       win=5.0)
    env = make_env(oval2, worlds=1, drones=2, learners=(0, 1), training=False, reward=reward)
    fly = waypoint_policy(env, torch.tensor([1]))
    obs = env.reset()
    assert env.contested.all()
    place(env, [[2.5, -2.5, 1.0], [-1.2, -1.0, 1.0]])
    for _ in range(env.max_episode_length):
        obs, _, _, _ = env.step(torch.cat([torch.zeros(1, 4), fly(obs)]))
        if env.records.finished[1]:
            break
    assert bool(env.records.finished[1]) and not bool(env.records.crashed.any())
    assert env.records.term_sums["win"].tolist() == pytest.approx([-5.0, 5.0])
