"""RaceEnv: contested races, episode ends (crashes, contact margin, time limit, start cuts, non-finite states),
absent slots and resets."""

from __future__ import annotations

import math

import pytest
import torch

from spiral.env import run_races
from spiral.env.race_env import restart_worlds
from tests.env.helpers import make_env


def test_only_start_box_races_against_opponents_are_contested(oval2):
    """Contest the winner of start-box races with opponents present, not of track starts or solo flights."""
    def contested(track_start_prob: float, opponents: bool) -> torch.Tensor:
        env = make_env(oval2, worlds=4, drones=2, learners=(0,), episode={"track_start_prob": track_start_prob})
        env.set_opponent_policy((lambda obs: torch.zeros(len(obs["policy"]), 4)) if opponents else None)
        env.reset()
        return env.contested

    assert contested(0.0, opponents=True).all()
    assert not contested(1.0, opponents=True).any()
    assert not contested(0.0, opponents=False).any()
    solo = make_env(oval2, worlds=4, drones=1, learners=(0,))
    assert not solo.contested.any()


def test_crash_pays_the_penalty_once_and_ends_the_episode(oval2):
    """Dive into the ground: one collision penalty, done, then an automatic reset of that world only."""
    env = make_env(oval2, worlds=2)
    down = torch.tensor([[0.0, 0.0, -1.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    penalties, done_at = [], None
    for step in range(120):
        before = env.records.term_sums["collision"].clone()
        _, _, done, extras = env.step(down)
        penalties.append(float(env.records.term_sums["collision"][0] - before[0]) if not done[0] else None)
        if done[0]:
            done_at = step
            break
    assert done_at is not None
    assert not bool(extras["time_outs"][0])
    assert float(env.stats.sums["crash_ground"]) == pytest.approx(1.0)  # a count
    assert float(env.stats.sums["term_collision"]) == pytest.approx(-env.cfg.reward.collision)
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
    assert env.records.absent.view(2, 2)[:, 1].all() and not env.records.absent.view(2, 2)[:, 0].any()
    res = run_races(make_env(oval2, worlds=2, drones=2, learners=(0,), training=False), lambda o: torch.zeros(2, 4))
    assert not res.present[:, 1].any()


@pytest.mark.bitwise
def test_same_seed_gives_the_same_start_placements(oval2):
    """Draw identical start positions for the same seed, different ones for another seed."""
    a, b = make_env(oval2, worlds=4, drones=4, learners=(0, 1, 2, 3)), make_env(oval2, worlds=4, drones=4,
                                                                               learners=(0, 1, 2, 3))
    assert torch.equal(a.pos, b.pos)
    d = torch.cdist(a.pos.view(4, 4, 3), a.pos.view(4, 4, 3)) + torch.eye(4) * 10
    assert float(d.min()) >= 0.25


def test_resetting_some_worlds_draws_starts_for_them_only_and_a_full_reset_draws_as_before(oval2):
    """Worlds 1 and 3 of 4 restart in the start box; 0 and 2 keep their state. A reset of every world draws the
    placements of a fresh env with the same seed (evaluation placements do not depend on earlier partial resets)."""
    env = make_env(oval2, worlds=4, drones=2, learners=(0,))
    fresh = make_env(oval2, worlds=4, drones=2, learners=(0,))
    torch.testing.assert_close(env.pos, fresh.pos)
    env.pos[:] = 5.0
    restart_worlds(env, torch.tensor([False, True, False, True]))
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
