"""Separation filter: the closed-form target shift, who it applies to, one team's drones only, and two drones flying
through each other."""

from __future__ import annotations

import pytest
import torch

from spiral.config import AIRFRAMES, EnvCfg, ObsCfg, SeparationCfg, SimCfg, TrackSpec
from spiral.config.env import ActionCfg
from spiral.env import RaceEnv, RaceSetting
from spiral.env.actions import ActionMap
from spiral.env.separation import separation_offsets

FILTER = SeparationCfg(distance=0.25, horizon_s=0.4, gain=1.5)


def pair(p1: list[float], v0: list[float], v1: list[float]) -> tuple[torch.Tensor, torch.Tensor]:
    """One world: drone 0 at the origin, drone 1 at ``p1``, with velocities ``v0`` and ``v1``."""
    return torch.tensor([[[0.0, 0.0, 0.0], p1]]), torch.tensor([[v0, v1]])


def test_approaching_drones_are_shifted_apart_along_their_closest_approach():
    """Drone 1 0.4 m ahead and 0.1 m to the side, closing at 2 m/s: closest approach at t* = 0.2 s (inside the
    0.4 s horizon), 0.1 m apart, so each target moves 1.5 (1 − 0.1/0.25) = 0.9 m sideways, in opposite directions."""
    pos, vel = pair([0.4, 0.1, 0.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0])
    shift = separation_offsets(pos, vel, torch.ones(1, 2, dtype=torch.bool), FILTER)
    torch.testing.assert_close(shift[0], torch.tensor([[0.0, -0.9, 0.0], [0.0, 0.9, 0.0]]))
    # A shorter look-ahead stops at t* = 0.1 s: separation (−0.2, −0.1), shift 1.5 (1 − √0.05/0.25) along it.
    racing = torch.ones(1, 2, dtype=torch.bool)
    short = separation_offsets(pos, vel, racing, FILTER.model_copy(update={"horizon_s": 0.1}))
    d = 0.05 ** 0.5
    torch.testing.assert_close(short[0, 0], 1.5 * (1 - d / 0.25) * torch.tensor([-0.2, -0.1, 0.0]) / d)


def test_a_head_on_approach_is_pushed_back_along_the_line():
    """Meeting exactly (predicted distance 0) still shifts both drones, back along the line joining them."""
    pos, vel = pair([0.4, 0.0, 0.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0])
    shift = separation_offsets(pos, vel, torch.ones(1, 2, dtype=torch.bool), FILTER)
    torch.testing.assert_close(shift[0], torch.tensor([[-1.5, 0.0, 0.0], [1.5, 0.0, 0.0]]))


@pytest.mark.parametrize(("p1", "v0"), [([1.0, 0.0, 0.0], [1.0, 0.0, 0.0]), ([0.3, 0.0, 0.0], [-1.0, 0.0, 0.0])],
                         ids=["too-far-for-the-horizon", "parting"])
def test_drones_that_stay_clear_within_the_horizon_are_left_alone(p1, v0):
    pos, vel = pair(p1, v0, [0.0, 0.0, 0.0])
    assert not separation_offsets(pos, vel, torch.ones(1, 2, dtype=torch.bool), FILTER).any()


def test_drones_out_of_the_race_neither_push_nor_are_pushed():
    """Three drones at 0.1 m spacing; drone 2 has crashed: only 0 and 1 shift, and only from each other."""
    pos = torch.tensor([[[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]]])
    racing = torch.tensor([[True, True, False]])
    shift = separation_offsets(pos, torch.zeros_like(pos), racing, FILTER)
    torch.testing.assert_close(shift[0], torch.tensor([[-0.9, 0.0, 0.0], [0.9, 0.0, 0.0], [0.0, 0.0, 0.0]]))


@pytest.mark.parametrize(("team", "shifted"), [("all", [0, 1, 2, 3]), ("a", [0, 1]), ("b", [2, 3])])
def test_a_one_team_filter_shifts_only_that_teams_targets_and_still_avoids_every_drone(line2, team, shifted):
    """2v2, at rest: drone 0 (team A) 0.1 m from drone 2 (team B), drone 1 (A) 0.1 m from drone 3 (B); zero actions.
    Each shifted drone's target moves 0.9 m away from its neighbour of the other team, the others' stay put."""
    cfg = EnvCfg(action={"separation": FILTER, "separation_team": team})
    actions = ActionMap(cfg, line2, world_count=2, drones_per_world=4, device=torch.device("cpu"))
    pos = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 1.0], [0.1, 0.0, 1.0], [0.1, 1.0, 1.0]]).repeat(2, 1)
    racing = torch.ones(8, dtype=torch.bool)
    target = actions.targets(torch.zeros(8, 4), pos, torch.zeros(8, 3), torch.zeros(8), racing)
    away = torch.tensor([[-0.9, 0.0, 0.0], [-0.9, 0.0, 0.0], [0.9, 0.0, 0.0], [0.9, 0.0, 0.0]])
    expected = pos.view(2, 4, 3) + away * torch.tensor([float(i in shifted) for i in range(4)])[:, None]
    torch.testing.assert_close(target[:, :3], expected.view(8, 3))


def test_a_one_team_filter_needs_a_filter():
    with pytest.raises(ValueError, match="separation_team"):
        ActionCfg(separation_team="a")


HEAD_ON = ([[0.5, 1.5, 1.0], [2.0, 1.52, 1.0]], [[2.0, 1.52, 1.0], [0.5, 1.5, 1.0]])
MERGE = ([[0.5, 1.2, 1.0], [0.5, 1.8, 1.0]], [[2.0, 1.5, 1.0], [2.0, 1.5, 1.0]])


@pytest.mark.parametrize("separation", [None, FILTER], ids=["paper-stack", "with-filter"])
@pytest.mark.parametrize(("start", "goal"), [HEAD_ON, MERGE], ids=["head-on", "merging-onto-one-point"])
def test_filter_keeps_two_drones_flying_into_each_other_apart(line2: TrackSpec, separation, start, goal):
    """Head-on: two drones 1.5 m apart each fly to the other's start, 2 cm off the line (closing at up to 4.7 m/s;
    a 0.2 s horizon sees the other too late). Merging: two drones 0.6 m apart fly to the same point 1.5 m ahead.
    Without the filter they collide; with it they stay apart and end within 0.2 m of their goals."""
    cfg = EnvCfg(obs=ObsCfg(history_len=1), action={"separation": separation},
                 episode={"track_start_prob": 0.0, "time_limit_s": 3.0})
    env = RaceEnv(RaceSetting(line2, AIRFRAMES["cf2x"], SimCfg()), cfg, world_count=1, drones_per_world=2,
                  learner_slots=(0,), seed=0, training=False)
    start, goal = torch.tensor(start), torch.tensor(goal)

    def fly(idx: torch.Tensor) -> torch.Tensor:
        rel = (goal[idx] - env.pos[idx]) / env.cfg.action.pos_scale
        return torch.cat([rel.clamp(-1, 1), torch.zeros(len(idx), 1)], dim=-1)

    env.set_opponent_policy(lambda obs: fly(env.opponent_idx))
    env.reset()
    env.pos[:] = start
    env.vel.zero_()
    closest = float("inf")
    for _ in range(env.max_episode_length):
        env.step(fly(env.learner_idx))
        closest = min(closest, float((env.pos[0] - env.pos[1]).norm()))
    if separation is None:
        assert env.records.crashed.all()
    else:
        assert not env.records.crashed.any() and closest > 2 * AIRFRAMES["cf2x"].radius
        assert float((env.pos - goal).norm(dim=-1).max()) < 0.2
