"""Flying a plan: the reference is the planned motion, the PID follows it, saturation keeps the cross-track part."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from spiral.baselines import SEIBRPlanner
from spiral.baselines.tracking import integrate_plan, sample_plans, target_actions
from spiral.config import AIRFRAMES, EnvCfg, SimCfg
from spiral.config.env import ActionCfg
from spiral.env import RaceEnv, RaceSetting


def straight_plan(planner: SEIBRPlanner, p0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Waypoints and node accelerations from rest along +x: up to 6 m/s² and back to 0 within 0.72 s (2.9 m/s)."""
    t = np.arange(planner.N + 1) * planner.cfg.dt
    acc = np.zeros((planner.N + 1, 3))
    acc[:, 0] = np.interp(t, [0.0, 0.24, 0.48, 0.72], [0.0, 6.0, 6.0, 0.0])
    pos, _ = integrate_plan(p0, np.zeros(3), acc, planner.cfg.dt)
    return pos, acc


def test_reference_passes_the_waypoints_with_the_planned_accelerations():
    """Sample a plan at its node times: positions are the waypoints, accelerations the node values, velocity exact."""
    dt, v0 = 0.12, np.array([1.0, -0.5, 0.2])
    acc = np.array([[0.0, 0.0, 0.0], [3.0, 1.0, -2.0], [5.0, -1.0, 0.0], [-2.0, 0.0, 1.0]])
    pos, vel = integrate_plan(np.zeros(3), v0, acc, dt)
    t = dt * np.arange(4)
    p, v, a = sample_plans(np.repeat(pos[None], 4, 0), np.repeat(acc[None], 4, 0), np.tile(v0, (4, 1)), dt, t)
    np.testing.assert_allclose(p, pos, atol=1e-12)
    np.testing.assert_allclose(v, vel, atol=1e-12)
    np.testing.assert_allclose(a, acc, atol=1e-12)
    mid = sample_plans(pos[None], acc[None], v0[None], dt, np.array([1.5 * dt]))[2]
    np.testing.assert_allclose(mid[0], 0.5 * (acc[1] + acc[2]))  # linear in between


def test_pid_follows_a_straight_plan_within_45_millimetres(line2):
    """Fly a hand-made plan (to 2.9 m/s through gate 0) through the env and PID: within 0.045 m of the reference."""
    env = RaceEnv(RaceSetting(line2, AIRFRAMES["cf2x"], SimCfg()), EnvCfg(), world_count=1, drones_per_world=1, seed=0,
                  training=False)
    env.reset()
    planner = SEIBRPlanner(env)
    p0 = np.array([-2.0, 0.0, 1.0])
    env.pos[0], env.vel[0] = torch.tensor(p0, dtype=torch.float32), 0.0
    pos, acc = straight_plan(planner, p0)
    planner.plans[0, 0], planner.plan_acc[0, 0], planner.plan_v0[0, 0] = pos, acc, 0.0
    planner.has_plan[0, 0], planner.plan_time[0] = True, 0.0
    errors = []
    for k in range(round(planner.N * planner.cfg.dt / env.dt)):
        ref = planner.reference(np.array([0]), np.array([k * env.dt]))[0][0]
        errors.append(np.linalg.norm(env.pos[0].numpy() - ref))
        env.step(planner.follow(torch.arange(1)))
    assert max(errors) < 0.045
    assert int(env.gates_passed[0]) == 1 and not bool(env.records.crashed[0])


def test_saturation_shortens_the_along_track_part_first():
    """Keep the cross-track offset exactly when the along-track one exceeds the reach; clip per axis only beyond."""
    action = ActionCfg(pos_scale=2.0)
    lo, hi = np.full(3, -5.0), np.full(3, 5.0)
    pos, along = np.zeros((2, 3)), np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    target = np.array([[6.0, 1.0, -0.5], [6.0, 3.0, 0.0]])  # along-track 6 m, cross-track 1.1 m and 3 m
    out = target_actions(target, pos, along, action, arena_lo=lo, arena_hi=hi)
    assert out[0] == pytest.approx([1.0, 0.5, -0.25])
    assert out[1] == pytest.approx([1.0, 1.0, 0.0])  # y alone exceeds the reach: clipped; x keeps what fits
    inside = target_actions(np.array([[1.0, -1.0, 0.5]]), np.zeros((1, 3)), along[:1], action, arena_lo=lo,
                            arena_hi=hi)
    assert inside[0] == pytest.approx([0.5, -0.5, 0.25])
