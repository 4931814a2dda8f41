"""Race events: lap splits, closing in, overtakes, contact fault, and the race outcome (first finisher, forfeit)."""

from __future__ import annotations

import pytest
import torch

from spiral.config import RewardCfg
from spiral.env.events import closing_in, contact_fault, lap_splits, overtakes
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
    reward = RewardCfg(progress=0.0, gate=0.0, alignment=0.0, lap=0.0, collision=0.0, win=5.0)
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
    env = make_env(oval2, worlds=1, drones=2, learners=(0, 1), training=False, reward=reward)
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
    env = make_env(oval2, worlds=1, drones=2, learners=(0,), training=False, reward=reward)
    env.set_opponent_policy(lambda obs: torch.tensor([[0.0, 0.0, -1.0, 0.0]]))
    env.reset()
    for _ in range(100):
        env.step(torch.zeros(1, 4))
        if env.crashed[1]:
            break
    assert bool(env.crashed[1]) and not bool(env.crashed[0])
    assert env.term_sums["win"].tolist() == pytest.approx([0.0, -5.0 if forfeit else 0.0])
    assert bool(env.contested[0])  # nobody has finished: the race is still open for the learner
