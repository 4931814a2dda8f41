"""SE-IBR planner: gate passage, separation, multipliers, the α = 0 reduction, the fallback, flying the plan."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from spiral.baselines import SEIBRPlanner, opponent_policy, planning_cost, se_ibr_policy
from spiral.baselines.best_response import BestResponseQP, PlanLimits, RowData, SolverSettings
from spiral.baselines.game import Player, plan_phases, player_rows
from spiral.baselines.tracking import integrate_plan
from spiral.config import AIRFRAMES, EnvCfg, SimCfg, TrackSpec
from spiral.env import RaceEnv, RaceSetting, run_races

CF2X = AIRFRAMES["cf2x"]


def make_env(track: TrackSpec, *, worlds: int = 1, drones: int = 1, learners=None) -> RaceEnv:
    learners = list(range(drones)) if learners is None else learners
    return RaceEnv(RaceSetting(track, CF2X, SimCfg()), EnvCfg(), world_count=worlds, drones_per_world=drones,
                   learner_slots=learners, seed=0, training=False)


def place(env: RaceEnv, pos: list[list[float]], vel: list[list[float]] | None = None) -> None:
    """Put the drones of world 0 at ``pos`` with velocities ``vel`` (rest when None)."""
    n = len(pos)
    env.pos[:n] = torch.tensor(pos)
    env.vel[:n] = torch.tensor(vel) if vel is not None else 0.0


def crossing(planner: SEIBRPlanner, slot: int, gate: int) -> np.ndarray:
    """Point where the plan of ``slot`` (world 0) crosses ``gate``'s plane forwards, in the gate's (y, z) axes."""
    line, plan = planner.line, planner.plans[0, slot]
    d = line.depth(plan, np.full(len(plan), gate))
    k = int(np.nonzero((d[:-1] < 0) & (d[1:] >= 0))[0][0])
    hit = plan[k] + (plan[k + 1] - plan[k]) * d[k] / (d[k] - d[k + 1]) - line.center[gate]
    return np.array([hit @ line.axis_y[gate], hit @ line.axis_z[gate]])


def min_plan_separation(planner: SEIBRPlanner, a: int, b: int) -> float:
    """Smallest distance between the waypoints p_1 … p_N of slots ``a`` and ``b`` of world 0."""
    return float(np.linalg.norm(planner.plans[0, a, 1:] - planner.plans[0, b, 1:], axis=1).min())


def test_single_player_plan_crosses_the_gate_inside_its_opening(circuit6):
    """Plan a solo drone from the start box through gate 0's opening, radius and margin kept from the frame."""
    env = make_env(circuit6)
    planner = SEIBRPlanner(env)
    planner.replan()
    hit = crossing(planner, 0, 0)
    limit = circuit6.gate_opening(0) / 2 - CF2X.radius
    assert np.all(np.abs(hit) <= limit - planner.cfg.gate_margin + 1e-4)
    phase, _, _ = plan_phases(planner.line, planner.plans[0, 0], 0)
    assert phase[-1] >= 1


def test_plan_respects_thrust_tilt_reach_and_jerk_bounds(circuit6):
    """Keep every node of a plan from rest inside the thrust ball, the tilt cone, the action's reach and the jerk bound,
    with its waypoints where its accelerations lead."""
    env = make_env(circuit6)
    planner = SEIBRPlanner(env)
    planner.replan()
    lim, dt = planner.limits, planner.cfg.dt
    acc, plan = planner.plan_acc[0, 0], planner.plans[0, 0]
    pos, vel = integrate_plan(plan[0], env.vel[0].numpy().astype(float), acc, dt)
    np.testing.assert_allclose(pos, plan, atol=1e-6)
    thrust = acc + lim.drag * vel + np.array([0.0, 0.0, lim.gravity])
    tol = 1e-5
    assert np.linalg.norm(thrust, axis=1).max() <= lim.thrust * (1 + tol)
    assert np.all(np.linalg.norm(thrust[:, :2], axis=1) <= lim.tan_tilt * thrust[:, 2] + tol)
    offset = (acc + lim.kd * vel) / lim.kp
    assert np.abs(offset[1:]).max() <= lim.target_hi[0] + tol
    assert np.linalg.norm(np.diff(acc, axis=0), axis=1).max() <= lim.jerk * dt * (1 + tol)
    assert np.linalg.norm(vel, axis=1).max() >= 2.0  # it does race


@pytest.fixture()
def collision_course(line2):
    """Two drones converging on gate 0 of ``line2`` from either side at 1.5 m/s."""
    env = make_env(line2, drones=2)
    place(env, [[-1.0, -0.45, 1.0], [-1.0, 0.45, 1.0]], [[1.0, 1.2, 0.0], [1.0, -1.2, 0.0]])
    return env


def test_players_on_a_collision_course_keep_the_separation(collision_course):
    """Keep the planned waypoints of two converging drones at least 2·radius + margin apart, without fallback."""
    planner = SEIBRPlanner(collision_course, alpha=0.0)
    planner.replan(rounds=3)
    sep = planner.params.separation
    assert min_plan_separation(planner, 0, 1) >= sep - 1e-4
    assert not planner.fallback[0].any()
    assert np.abs(crossing(planner, 0, 0)).max() < 0.3 and np.abs(crossing(planner, 1, 0)).max() < 0.3


def blocked_ahead(*, refine: bool = False) -> tuple[BestResponseQP, RowData]:
    """A 6-node best response racing along +x towards a player 0.5 m ahead (another one far behind)."""
    n = 6
    limits = PlanLimits(thrust=20.0, tan_tilt=1.0, floor=3.0, gravity=9.81, drag=np.zeros(3), kp=np.full(3, 8.0),
                        kd=np.full(3, 4.0), target_lo=np.full(3, -2.0), target_hi=np.full(3, 2.0), jerk=60.0)
    qp = BestResponseQP(steps=n, others=2, dt=0.15, limits=limits, smooth=1e-3, lo=np.full(3, -10.0),
                        hi=np.full(3, 10.0), solver=SolverSettings(refine=refine))
    q = np.zeros((n, 3))
    q[-1, 0] = -1.0  # progress along +x at the horizon
    coll_a = np.zeros((n, 2, 3))
    coll_a[:, 0] = (1.0, 0.0, 0.0)  # other 0 sits at x = 0.5 ahead: x_k ≤ 0.5 − 0.2
    coll_a[:, 1] = (-1.0, 0.0, 0.0)  # other 1 far behind at x = −5: −x_k ≤ 5 − 0.2
    coll_b = np.stack([np.full(n, 0.3), np.full(n, 4.8)], axis=1)
    rows = RowData(p0=np.array([0.0, 0.0, 1.0]), v0=np.array([1.0, 0.0, 0.0]), q=q, gate_a=np.zeros((n, 4, 3)),
                   gate_b=np.full((n, 4), np.inf), coll_a=coll_a, coll_b=coll_b)
    return qp, rows


def test_duals_are_non_negative_and_zero_on_slack_rows():
    """Price the blocking half-plane ahead (μ > 0 where it is tight) and give zero to slack rows and a far one."""
    qp, rows = blocked_ahead()
    coll_a, coll_b = rows.coll_a, rows.coll_b
    sol = qp.solve(rows)
    assert not sol.soft
    slack = coll_b - np.einsum("koc,kc->ko", coll_a, sol.plan)
    assert np.all(slack >= -1e-6)
    assert np.all(sol.raw_coll_dual >= -1e-7)
    assert np.all(sol.coll_dual[:, 1] < 1e-6)
    assert np.all(sol.coll_dual[slack[:, 0] > 1e-3, 0] < 1e-6)
    assert sol.coll_dual[-1, 0] == pytest.approx(1.0, abs=0.02)  # it absorbs the progress weight
    assert np.abs(sol.coll_dual * slack).max() < 1e-6


def test_iterative_refinement_moves_the_plan_and_its_duals_at_solver_tolerance_only():
    """The solver setting ``solver_refine`` trades time for digits far below what the planner uses."""
    plain, refined = (qp.solve(rows) for qp, rows in (blocked_ahead(), blocked_ahead(refine=True)))
    assert not plain.soft and not refined.soft
    assert np.abs(plain.plan - refined.plan).max() < 1e-5  # metres
    assert np.abs(plain.coll_dual - refined.coll_dual).max() < 1e-4


def test_game_duals_vanish_when_players_are_far_apart(collision_course):
    """Give non-negative multipliers on a collision course and all-zero ones when the drones race 4 m apart."""
    planner = SEIBRPlanner(collision_course, alpha=0.0)
    planner.replan(rounds=1)
    assert np.all(planner.duals[0] >= 0.0) and planner.duals[0].max() > 1e-3
    place(collision_course, [[-1.0, -2.0, 1.0], [-1.0, 2.0, 1.0]])
    far = SEIBRPlanner(collision_course, alpha=0.0)
    far.replan()
    assert np.all(far.duals[0] < 1e-6)


@pytest.mark.bitwise
def test_alpha_zero_reproduces_plain_ibr_and_alpha_changes_the_plan(collision_course):
    """Give identical plans for α = 0 with and without the sensitivity code path, and a different one for α > 0."""
    plans = []
    for kw in ({"alpha": 0.0}, {"alpha": 0.0, "sensitivity": False}, {"alpha": 1.0}):
        planner = SEIBRPlanner(collision_course, **kw)
        planner.replan(rounds=3)
        plans.append(planner.plans[0].copy())
    assert np.array_equal(plans[0], plans[1])
    assert np.abs(plans[2] - plans[0]).max() > 1e-3


def test_sensitivity_term_is_alpha_times_the_other_players_multipliers_along_the_half_plane(collision_course):
    """Change a player's linear objective by exactly −α·μ_k·β_k per waypoint, μ the other's duals against it."""
    planner = SEIBRPlanner(collision_course, alpha=2.5)
    planner.replan(rounds=2)
    state = planner._state()
    players = [Player(slot=s, p0=state["pos"][s], v0=state["vel"][s], next_gate=0, passed_any=False,
                      plan=planner.plans[0, s].copy(), duals=planner.duals[0, s].copy(), qp=planner._qp(0, s))
               for s in range(2)]
    mu = players[1].duals[0]
    assert mu.max() > 1e-3  # the other player's rows against slot 0 bind somewhere
    with_term = player_rows(planner.line, planner.gate_table, players[0], players, 2, planner.params)
    params_ibr = replace(planner.params, alpha=0.0)
    without = player_rows(planner.line, planner.gate_table, players[0], players, 2, params_ibr)
    beta = with_term.coll_a[:, 0]  # unit vectors from slot 0 towards slot 1
    np.testing.assert_allclose(with_term.q - without.q, -2.5 * mu[:, None] * beta, atol=1e-12)


def test_fallback_relaxes_only_the_geometry_rows_when_that_suffices():
    """A collision row the drone cannot meet at once (x_1 ≤ −1 m from x_0 = 0 at 1 m/s): the fallback crosses it and
    the flight stack's rows (reach, jerk) still hold exactly."""
    qp, rows = blocked_ahead()
    rows.coll_b[:2, 0] = -1.0
    sol = qp.solve(rows)
    assert sol.soft and sol.status == "Solved"
    assert sol.plan[0, 0] > -1.0  # the first collision row is crossed, not met
    lim, dt = qp.limits, qp.dt
    vel = np.diff(np.concatenate([rows.p0[None], sol.plan]), axis=0) / dt  # mean velocity per interval
    offset = (sol.acc[1:] + lim.kd * vel[1:]) / lim.kp  # the PID target offset, roughly
    assert np.all(np.abs(offset) <= lim.target_hi + 0.5)
    jerk = np.linalg.norm(np.diff(np.concatenate([np.zeros((1, 3)), sol.acc]), axis=0), axis=1)
    assert np.all(jerk <= lim.jerk * dt + 1e-5)


def test_fallback_relaxes_the_flight_stack_rows_when_geometry_alone_cannot():
    """A commanded acceleration beyond the thrust cone (a0 = 30 m/s², thrust ≤ 20): the jerk bound cannot be met
    from it, so the last fallback (slack on every row) returns a finite plan within the thrust cone."""
    qp, rows = blocked_ahead()
    rows.a0 = np.array([30.0, 0.0, 0.0])
    sol = qp.solve(rows)
    assert sol.soft and sol.status == "Solved"
    thrust = sol.acc + np.array([0.0, 0.0, qp.limits.gravity])
    assert np.all(np.isfinite(sol.plan)) and np.all(np.linalg.norm(thrust, axis=1) <= qp.limits.thrust + 1e-5)


def test_infeasible_start_falls_back_to_soft_constraints(line2):
    """Plan two overlapping drones with the soft fallback: finite plans that separate them, no exception."""
    env = make_env(line2, drones=2)
    place(env, [[-1.0, 0.0, 1.0], [-1.0, 0.02, 1.0]])
    planner = SEIBRPlanner(env, alpha=1.0)
    actions = planner.act(torch.arange(2))
    assert planner.soft_solves > 0
    assert np.all(np.isfinite(planner.plans[0]))
    assert np.linalg.norm(planner.plans[0, 0, -1] - planner.plans[0, 1, -1]) > 0.1
    assert actions.shape == (2, 4) and torch.all(actions.abs() <= 1.0)


def test_self_match_policy_finishes_the_lap(oval2):
    """Fly a 1v1 self-match on the two-gate oval through run_races: both drones finish without collision."""
    env = make_env(oval2, worlds=2, drones=2)
    policy = se_ibr_policy(env)
    res = run_races(env, policy)
    assert bool(res.finished.all())
    assert float(res.lap_time.max()) < 6.0
    timing = policy.planner.timing()
    assert timing["plans"] > 0 and 0 < timing["plan_ms_median"] <= timing["plan_ms_p95"]
    assert 0 < timing["plan_cpu_ms_median"] <= timing["plan_cpu_ms_p95"]


def test_opponent_policy_drives_the_opponent_slot(oval2):
    """Drive slot 1 from opponent_policy (IBR) against an SE-IBR learner; each planner flies only its drones."""
    env = make_env(oval2, drones=2, learners=[0])
    env.set_opponent_policy(opponent_policy(env, alpha=0.0))
    learner = se_ibr_policy(env, alpha=1.0)
    res = run_races(env, learner)
    assert bool(res.present.all()) and bool(res.finished.all())
    assert learner(env.get_observations()).shape == (1, 4)
    pooled = planning_cost(learner, env.opponent_policy, "not a planner")
    own, other = learner.planner.timing(), env.opponent_policy.planner.timing()
    assert pooled["plans"] == own["plans"] + other["plans"] > 0
    assert min(own["plan_ms_median"], other["plan_ms_median"]) <= pooled["plan_ms_median"] <= pooled["plan_ms_p95"]
    assert planning_cost()["plan_ms_median"] is None


@pytest.mark.parametrize(("dz", "inside", "outside"), [(0.25, 1.10, 1.25), (0.60, 1.60, 1.30)])
def test_segment_recrossing_a_passed_gate_keeps_off_its_frame(line2, dz, inside, outside):
    """Give both ends of a segment re-crossing gate 0's plane near its bar the tube, or beyond the frame when wide."""
    planner = SEIBRPlanner(make_env(line2))
    n = planner.N
    plan = np.zeros((n + 1, 3))
    plan[:, 0] = np.linspace(0.5, -0.7, n + 1)  # turning back through gate 0's plane (x = 0) after passing it
    plan[:, 2] = 1.0 + dz
    pl = Player(slot=0, p0=plan[0], v0=np.zeros(3), next_gate=1, passed_any=True, plan=plan,
                duals=np.zeros((1, n)), qp=planner._qp(0, 0))
    rows = player_rows(planner.line, planner.gate_table, pl, [pl], 1, planner.params)
    constrained = np.nonzero((rows.frame_b < 1e20).any(axis=1))[0] + 1  # waypoint indices with frame rows
    k = int(np.nonzero(plan[1:, 0] < 0)[0][0]) + 1
    assert constrained.tolist() == [k - 1, k]
    a, b = rows.frame_a[k - 1], rows.frame_b[k - 1]
    assert np.all(a @ np.array([-0.1, 0.0, inside]) <= b)
    assert np.any(a @ np.array([-0.1, 0.0, outside]) > b)
