"""SE-IBR: sensitivity-enhanced iterated best response (Wang, Taubner & Schwager 2020; Spica et al. 2020).

A receding-horizon game-theoretic planner for every drone of a :class:`~spiral.env.RaceEnv`. It reads the race
state (positions, velocities, next gates), not observations. Every ``replan_every`` control steps each world's
game is solved: ``rounds`` rounds in which each racing drone in turn computes its best response (a QP within
what the airframe and flight stack allow, see :mod:`spiral.baselines.limits` and
:mod:`spiral.baselines.best_response`) to the latest plans of the others. The plans are then flown through the
env's own action interface: the planned position and velocity one control step ahead and the planned acceleration
one attitude lag further become a PID target with feed-forward (:mod:`spiral.baselines.tracking`). Formulation,
defaults and measurements: ``docs/se_ibr.md``; planning cost: :func:`planning_cost`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from pydantic import Field
from tensordict import TensorDict

from spiral.baselines.best_response import BestResponseQP, PlanLimits, SolverSettings
from spiral.baselines.centreline import Centreline
from spiral.baselines.game import GameParams, Player, gate_row_table, iterate_best_responses
from spiral.baselines.limits import PID_THRUST_FLOOR, flight_limits
from spiral.baselines.tracking import pid_target, sample_plans, target_actions
from spiral.config.base import NonNegFloat, PosFloat, PosInt, StrictModel
from spiral.env.race_env import RaceEnv

__all__ = ["PlannerPolicy", "SEIBRCfg", "SEIBRPlanner", "game_params", "opponent_policy", "plan_limits",
           "planning_cost", "se_ibr_policy"]


class SEIBRCfg(StrictModel):
    """Parameters of the SE-IBR planner. None of them refers to a particular track."""

    alpha: NonNegFloat = Field(default=1.0, description="Weight α of the sensitivity term; 0 = plain IBR")
    horizon: PosFloat = Field(default=1.8, description="Planning horizon [s]")
    dt: PosFloat = Field(default=0.12, description="Time between waypoints Δt [s]")
    rounds: PosInt = Field(default=2, description="IBR rounds L per planning step")
    first_rounds: PosInt = Field(default=4, description="IBR rounds when a drone has no previous plan")
    replan_every: PosInt = Field(default=3, description="Control steps between planning steps (plan held between)")
    thrust_frac: float = Field(default=0.85, gt=0, le=1,
                               description="Share of the airframe's thrust acceleration min(TWR·g, max_accel) a plan "
                                           "may use (the rest is headroom for attitude control)")
    tilt_frac: float = Field(default=0.9, gt=0, le=1, description="Share of the PID's tilt limit a plan may use")
    reach_frac: float = Field(default=1.0, gt=0, le=1,
                              description="Share of the action's reach (relative mode) a plan's PID target may use")
    jerk_ramp: PosFloat = Field(default=3.0, description="Attitude lags over which a plan may ramp its acceleration "
                                                         "from zero to the level maximum: jerk bound = level "
                                                         "acceleration / (jerk_ramp · attitude lag)")
    accel_lead: NonNegFloat | None = Field(default=None, description="How far ahead of the position reference the "
                                                                     "acceleration feed-forward is read [s]; None: "
                                                                     "the attitude loop's lag")
    gate_margin: NonNegFloat = Field(default=0.1, description="Margin inside opening/2 − radius [m]")
    funnel_slope: PosFloat = Field(default=1.0, description="Widening of the gate funnels per metre of depth")
    funnel_reach: PosFloat = Field(default=2.5, description="Distance from the next gate within which its approach "
                                                            "funnel is enforced [m]")
    capture: NonNegFloat = Field(default=0.3, description="Lateral distance beyond the usable opening, at a gate's "
                                                          "plane, within which a waypoint gets that gate's approach "
                                                          "rows [m]")
    capture_slope: NonNegFloat = Field(default=3.0, description="Growth of that distance per metre in front of the "
                                                                "plane")
    exit_reach: PosFloat = Field(default=0.6, description="Distance from a passed gate's centre within which its "
                                                          "exit funnel is enforced [m]")
    drone_margin: NonNegFloat = Field(default=0.15, description="Separation between drones beyond 2·radius [m]")
    wall_margin: NonNegFloat = Field(default=0.1, description="Distance kept from the ground and arena walls "
                                                              "beyond the radius [m]")
    progress_weight: PosFloat = Field(default=1.0, description="Weight of the progress at the horizon [1/m]")
    running_weight: NonNegFloat = Field(default=0.4, description="Weight of the progress of the first waypoint "
                                                                 "[1/m]: get ahead early, not only by the horizon")
    running_discount: float = Field(default=0.85, gt=0, le=1, description="Factor of that weight from one waypoint to "
                                                                         "the next (progress soon counts more)")
    smooth_weight: NonNegFloat = Field(default=1e-3, description="Weight of Σ‖a_k‖²·Δt [s³/m²]")
    soft_penalty: PosFloat = Field(default=1e3, description="Linear penalty per unit of slack in the fallback")
    solver_tol: PosFloat = Field(default=1e-7, description="Clarabel feasibility and gap tolerances")
    solver_refine: bool = Field(
        default=False, description="Iterative refinement of Clarabel's linear solves (off: about a third less time per "
        "solve; plans move by about 1e-6 m, docs/se_ibr.md)")
    lookahead: NonNegFloat = Field(default=1.0, description="Control steps ahead at which the plan is sampled")
    guard_steps: int = Field(default=3, ge=0, description="Waypoints over which a flown drone also avoids the "
                                                          "constant-velocity extrapolation of drones another "
                                                          "planner flies")
    sensitivity: bool = Field(default=True, description="Compute the sensitivity term (False skips the code "
                                                        "path; with α = 0 both must agree)")


def plan_limits(env: RaceEnv, cfg: SEIBRCfg) -> PlanLimits:
    """What a plan may ask of ``env``'s drones: the airframe's thrust and tilt, drag, the action's reach and a jerk
    bound from the attitude loop.

    Thrust ``thrust_frac·min(TWR·g, max_accel)`` (at least 1.05 g), tilt ``tilt_frac·max_tilt``, the PID's thrust
    floor, the PID target within ``reach_frac·pos_scale`` of the drone on each axis (relative mode) or inside the
    arena (absolute mode), and jerk ``level_accel / (jerk_ramp·attitude_lag)``. See
    :func:`~spiral.baselines.limits.flight_limits` for the closed forms.
    """
    lim = flight_limits(env.world.airframe, env.cfg.action, gravity=env.world.sim.gravity)
    g = lim.gravity
    if lim.reach is not None:
        hi = np.full(3, cfg.reach_frac * lim.reach)
        lo, absolute = -hi, False
    else:
        lo, hi, absolute = np.asarray(env.track.bounds.min, float), np.asarray(env.track.bounds.max, float), True
    return PlanLimits(thrust=max(cfg.thrust_frac * lim.thrust, 1.05 * g),
                      tan_tilt=math.tan(math.radians(cfg.tilt_frac * lim.tilt_deg)), floor=PID_THRUST_FLOOR * g,
                      gravity=g, drag=np.asarray(lim.drag_per_mass), kp=np.asarray(lim.kp), kd=np.asarray(lim.kd),
                      target_lo=lo, target_hi=hi, absolute=absolute,
                      jerk=lim.level_accel / (cfg.jerk_ramp * lim.attitude_lag))


def game_params(env: RaceEnv, cfg: SEIBRCfg, steps: int) -> GameParams:
    """Geometry and weights of the game from the track, the airframe's radius and ``cfg``."""
    track, r = env.track, env.world.airframe.radius
    gates = range(len(track.gates))
    return GameParams(
        steps=steps, dt=cfg.dt, gate_half=np.array([track.gate_opening(i) / 2 - r - cfg.gate_margin for i in gates]),
        tube=max(track.gate_bar(i) for i in gates) / 2 + r + cfg.gate_margin, slope=cfg.funnel_slope,
        reach=cfg.funnel_reach, exit_reach=cfg.exit_reach, capture=cfg.capture, capture_slope=cfg.capture_slope,
        separation=2 * r + cfg.drone_margin, progress_weight=cfg.progress_weight, running_weight=cfg.running_weight,
        discount=cfg.running_discount, alpha=cfg.alpha, guard_steps=cfg.guard_steps,
        frame_clear=max(track.gate_size(i) for i in gates) / 2 + r + cfg.gate_margin, sensitivity=cfg.sensitivity)


class SEIBRPlanner:
    """SE-IBR planner for every racing drone of ``env``; :meth:`act` returns env actions for chosen drones.

    Each call of :meth:`act` plans the worlds of the requested drones when their plan is due (all racing drones of
    such a world take part in its game) and converts each requested drone's plan into its action. Two planners on
    one env (e.g. SE-IBR for the learner slots, IBR for the opponents) each solve the full game with their own
    parameters and fly only their own drones (``own_slots``); a flown drone then also keeps clear of the
    constant-velocity extrapolation of the drones it does not fly, over the first ``guard_steps`` waypoints.
    """

    def __init__(self, env: RaceEnv, *, own_slots: Sequence[int] | None = None, cfg: SEIBRCfg | None = None,
                 **overrides: Any) -> None:
        self.env = env
        env.world_tracks.one("the SE-IBR planner")
        self.own_slots = set(range(env.drones_per_world) if own_slots is None else own_slots)
        """Slots this planner flies; the others are predicted in its game but flown by someone else."""
        self.cfg = SEIBRCfg(**{**(cfg.model_dump() if cfg is not None else {}), **overrides})
        c, air = self.cfg, env.world.airframe
        self.N = max(2, round(c.horizon / c.dt))
        self.W, self.D = env.world_count, env.drones_per_world
        self.ctrl_dt = float(env.dt)
        self.kp, self.kd, self.ki = (np.asarray(x, float) for x in (air.pid.pos_p, air.pid.pos_d, air.pid.pos_i))
        self.limits = plan_limits(env, c)
        self.accel_lead = c.accel_lead if c.accel_lead is not None else flight_limits(
            air, env.cfg.action, gravity=env.world.sim.gravity).attitude_lag
        """How far ahead the acceleration feed-forward is read [s]."""
        self._init_track()
        self._init_plans()

    def _init_track(self) -> None:
        """The track's centreline, the game's geometry and the arena the waypoints stay in."""
        c, track = self.cfg, self.env.track
        self.line = Centreline(track)
        self.params = game_params(self.env, c, self.N)
        self.gate_table = gate_row_table(self.line, self.params)
        margin = self.env.world.airframe.radius + c.wall_margin
        self.arena_lo, self.arena_hi = np.asarray(track.bounds.min, float), np.asarray(track.bounds.max, float)
        self.lo = np.asarray(track.bounds.min, float) + margin
        self.hi = np.asarray(track.bounds.max, float) - margin

    def _init_plans(self) -> None:
        """Plan, multiplier and planning-cost buffers, empty."""
        self.plans = np.zeros((self.W, self.D, self.N + 1, 3))
        """Latest plan p_0 … p_N of each drone (world-time ``plan_time`` at p_0)."""
        self.plan_v0 = np.zeros((self.W, self.D, 3))
        self.plan_acc = np.zeros((self.W, self.D, self.N + 1, 3))
        """Node accelerations A_0 … A_N of each plan (linear in between)."""
        self.duals = np.zeros((self.W, self.D, self.D, self.N))
        """``duals[w, i, j, k]``: multiplier of i's collision row against j at waypoint k."""
        self.has_plan = np.zeros((self.W, self.D), dtype=bool)
        self.fallback = np.zeros((self.W, self.D), dtype=bool)
        """Whether each drone's current plan comes from the soft-constraint fallback."""
        self.plan_time = np.full(self.W, -np.inf)
        self._qps: dict[tuple[int, int], BestResponseQP] = {}
        self.drone_ms: list[float] = []
        """Wall time of each drone's best responses in one planning step (all rounds) [ms]."""
        self.drone_cpu_ms: list[float] = []
        """Processor time of the same [ms]."""
        self.world_ms: list[float] = []
        """Wall time of each world's planning step [ms]."""
        self.solves = 0
        self.soft_solves = 0

    # Public

    def act(self, drone_idx: torch.Tensor) -> torch.Tensor:
        """Actions (n, 4) in [−1, 1] for the flat drone indices ``drone_idx`` (n,), planning where due."""
        idx = drone_idx.detach().cpu().numpy().astype(np.int64)
        state = self._state()
        for w in np.unique(idx // self.D):
            if self._due(int(w), state):
                self._plan_world(int(w), state)
        return torch.as_tensor(self._track(idx, state), dtype=torch.float32, device=self.env.device)

    def replan(self, worlds: Sequence[int] | None = None, *, rounds: int | None = None) -> None:
        """Solve the game of ``worlds`` (all when None) now, with ``rounds`` rounds if given."""
        state = self._state()
        for w in range(self.W) if worlds is None else worlds:
            self._plan_world(int(w), state, rounds=rounds)

    def reset(self) -> None:
        """Forget every plan and multiplier (the next call plans from scratch)."""
        self.has_plan[:] = False
        self.duals[:] = 0.0
        self.plan_time[:] = -np.inf

    def timing(self) -> dict[str, Any]:
        """Planning cost of this planner so far; see :func:`planning_cost`."""
        return planning_cost(self)

    # Planning

    def _state(self) -> dict[str, np.ndarray]:
        e = self.env
        return {"pos": e.pos.detach().cpu().numpy().astype(float), "vel": e.vel.detach().cpu().numpy().astype(float),
                "gate": e.next_gate.detach().cpu().numpy().astype(np.int64),
                "passed": e.gates_passed.detach().cpu().numpy() > 0,
                "racing": e.out.detach().cpu().numpy() == 0,
                "integral": e.integral.detach().cpu().numpy().astype(float),
                "time": e.world_time().detach().cpu().numpy().astype(float)}

    def _due(self, w: int, state: dict[str, np.ndarray]) -> bool:
        racing = state["racing"][w * self.D:(w + 1) * self.D]
        if not racing.any():
            return False
        t = state["time"][w]
        if t < self.plan_time[w] - 1e-9 or not self.has_plan[w][racing].all():
            return True
        return t - self.plan_time[w] >= self.cfg.replan_every * self.ctrl_dt - 1e-6

    def _qp(self, w: int, s: int) -> BestResponseQP:
        key = (w, s)
        if key not in self._qps:
            c = self.cfg
            solver = SolverSettings(soft_penalty=c.soft_penalty, tol=c.solver_tol, refine=c.solver_refine)
            self._qps[key] = BestResponseQP(steps=self.N, others=self.D - 1, dt=c.dt, limits=self.limits,
                                            smooth=c.smooth_weight, lo=self.lo, hi=self.hi, solver=solver)
        return self._qps[key]

    def _shifted(self, w: int, s: int, elapsed: float) -> tuple[np.ndarray, np.ndarray]:
        """Previous plan and multipliers re-timed to start ``elapsed`` seconds later (extrapolated at the end)."""
        k = elapsed / self.cfg.dt + np.arange(self.N + 1)
        i0 = np.clip(np.floor(k).astype(np.int64), 0, self.N - 1)
        frac = (k - i0)[:, None]
        p = self.plans[w, s]
        plan = p[i0] + frac * (p[i0 + 1] - p[i0])
        kd = np.clip(k[1:] - 1.0, 0.0, self.N - 1.0)
        duals = np.stack([np.interp(kd, np.arange(self.N), row) for row in self.duals[w, s]])
        return plan, duals

    def _plan_world(self, w: int, state: dict[str, np.ndarray], *, rounds: int | None = None) -> None:
        t0 = time.perf_counter()
        t = float(state["time"][w])
        if t < self.plan_time[w] - 1e-9:  # the world was reset
            self.has_plan[w] = False
            self.duals[w] = 0.0
        players, fresh = [], False
        for s in range(self.D):
            i = w * self.D + s
            if not state["racing"][i]:
                self.has_plan[w, s] = False
                continue
            p0, v0 = state["pos"][i], state["vel"][i]
            a0 = None
            if self.has_plan[w, s]:
                plan, duals = self._shifted(w, s, t - self.plan_time[w])
                a0 = self.reference(np.array([i]), np.array([t - self.plan_time[w]]))[2][0]  # continue smoothly
            else:
                plan = p0 + v0 * self.cfg.dt * np.arange(self.N + 1)[:, None]
                duals, fresh = np.zeros((self.D, self.N)), True
            plan[0] = p0
            players.append(Player(slot=s, p0=p0, v0=v0, a0=a0, next_gate=int(state["gate"][i]),
                                  passed_any=bool(state["passed"][i]), plan=plan, duals=duals, qp=self._qp(w, s),
                                  owned=s in self.own_slots))
        if not players:
            return
        n_rounds = rounds or (self.cfg.first_rounds if fresh else self.cfg.rounds)
        iterate_best_responses(self.line, self.gate_table, players, self.D, self.params, n_rounds)
        for pl in players:
            self.plans[w, pl.slot], self.plan_v0[w, pl.slot] = pl.plan, pl.v0
            self.plan_acc[w, pl.slot] = pl.acc
            self.duals[w, pl.slot] = pl.duals
            self.has_plan[w, pl.slot] = True
            self.fallback[w, pl.slot] = pl.last is not None and pl.last.soft
            self.drone_ms.append(pl.solve_ms)
            self.drone_cpu_ms.append(pl.solve_cpu_ms)
        self.solves += n_rounds * len(players)
        self.soft_solves += sum(pl.soft_count for pl in players)
        self.plan_time[w] = t
        self.world_ms.append(1e3 * (time.perf_counter() - t0))

    # Flying the plan

    def reference(self, idx: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity and acceleration of the current plans of flat drones ``idx`` at ``tau`` after their
        planning time (see :func:`~spiral.baselines.tracking.sample_plans`)."""
        w, s = idx // self.D, idx % self.D
        return sample_plans(self.plans[w, s], self.plan_acc[w, s], self.plan_v0[w, s], self.cfg.dt, tau)

    def follow(self, drone_idx: torch.Tensor) -> torch.Tensor:
        """Actions (n, 4) that fly the current plans of ``drone_idx`` (n,) without replanning."""
        idx = drone_idx.detach().cpu().numpy().astype(np.int64)
        return torch.as_tensor(self._track(idx, self._state()), dtype=torch.float32, device=self.env.device)

    def _track(self, idx: np.ndarray, state: dict[str, np.ndarray]) -> np.ndarray:
        """Env actions that make the PID follow the plans: target = p_ref + (a_ref + K_d·v_ref − K_i·I)/K_p."""
        out = np.zeros((len(idx), 4))
        w, s = idx // self.D, idx % self.D
        ok = state["racing"][idx] & self.has_plan[w, s]
        if not ok.any():
            return out
        sel = idx[ok]
        tau = state["time"][sel // self.D] - self.plan_time[sel // self.D] + self.cfg.lookahead * self.ctrl_dt
        pos, vel, _ = self.reference(sel, tau)
        acc = self.reference(sel, tau + self.accel_lead)[2]
        target = pid_target(pos, vel, acc, state["integral"][sel], kp=self.kp, kd=self.kd, ki=self.ki)
        out[ok, :3] = target_actions(target, state["pos"][sel], vel, self.env.cfg.action, arena_lo=self.arena_lo,
                                     arena_hi=self.arena_hi)
        return out


class PlannerPolicy:
    """``policy(obs) -> actions`` for a set of drones of an env, backed by a :class:`SEIBRPlanner`."""

    def __init__(self, planner: SEIBRPlanner, drone_idx: torch.Tensor, rows: torch.Tensor, num_rows: int) -> None:
        self.planner, self.drone_idx, self.rows, self.num_rows = planner, drone_idx, rows, num_rows

    def __call__(self, obs: TensorDict) -> torch.Tensor:
        """Actions of the policy's rows (observations are not used: the planner reads the race state)."""
        out = torch.zeros(self.num_rows, 4, device=self.planner.env.device)
        out[self.rows] = self.planner.act(self.drone_idx)
        return out


def se_ibr_policy(env: RaceEnv, slots: Sequence[int] | None = None, **kw: Any) -> PlannerPolicy:
    """Policy for the learner slots of ``env`` (``slots``: a subset of them; the rest get zero actions).

    ``run_races(env, se_ibr_policy(env))`` with every slot a learner slot is a self-match. ``kw`` are
    :class:`SEIBRCfg` fields.
    """
    chosen = list(env.learner_slots if slots is None else slots)
    unknown = set(chosen) - set(env.learner_slots)
    if unknown:
        raise ValueError(f"slots {sorted(unknown)} are not learner slots {env.learner_slots}")
    keep = torch.tensor([s in chosen for s in env.learner_slots], device=env.device).repeat(env.world_count)
    rows = torch.nonzero(keep).flatten()
    return PlannerPolicy(SEIBRPlanner(env, own_slots=chosen, **kw), env.learner_idx[rows], rows, env.num_envs)


def opponent_policy(env: RaceEnv, **kw: Any) -> PlannerPolicy:
    """Policy for the opponent slots of ``env``, for ``env.set_opponent_policy``; ``kw`` are SEIBRCfg fields."""
    n = env.opponent_idx.numel()
    planner = SEIBRPlanner(env, own_slots=env.opponent_slots, **kw)
    return PlannerPolicy(planner, env.opponent_idx, torch.arange(n, device=env.device), n)


def planning_cost(*sources: SEIBRPlanner | PlannerPolicy | Any) -> dict[str, Any]:
    """Planning cost pooled over planners (or policies backed by one; anything else is skipped).

    A plan is one drone's best responses in one planning step (all IBR rounds, building the rows included):
    ``plan_ms_median`` and ``plan_ms_p95`` are its wall-clock milliseconds per plan per drone, ``plan_cpu_ms_*`` the
    processor time of the same (what the wall time would be on a core of its own; on a loaded machine the wall time
    also counts the time other processes held the core). ``world_ms_*`` time one world's whole game per planning
    step. Also the number of plans, of best responses (``solves``) and the share of those that needed the soft
    fallback. ``None`` without plans.
    """
    planners = [x.planner if isinstance(x, PlannerPolicy) else x for x in sources]
    planners = [p for p in planners if isinstance(p, SEIBRPlanner)]

    def pooled(name: str) -> np.ndarray:
        return np.concatenate([np.asarray(getattr(p, name), float) for p in planners]) if planners else np.zeros(0)

    def stat(x: np.ndarray, q: float) -> float | None:
        return float(np.percentile(x, q)) if x.size else None

    drone, cpu, world = pooled("drone_ms"), pooled("drone_cpu_ms"), pooled("world_ms")
    solves, soft = sum(p.solves for p in planners), sum(p.soft_solves for p in planners)
    return {"plans": int(drone.size), "plan_ms_median": stat(drone, 50), "plan_ms_p95": stat(drone, 95),
            "plan_cpu_ms_median": stat(cpu, 50), "plan_cpu_ms_p95": stat(cpu, 95),
            "world_ms_median": stat(world, 50), "world_ms_p95": stat(world, 95), "solves": int(solves),
            "soft_fraction": soft / solves if solves else 0.0}
