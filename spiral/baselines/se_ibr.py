"""SE-IBR: sensitivity-enhanced iterated best response (Wang, Taubner & Schwager 2020; Spica et al. 2020).

A receding-horizon game-theoretic planner for every drone of a :class:`~spiral.env.RaceEnv`. It reads the race
state (positions, velocities, next gates), not observations. Every ``replan_every`` control steps each world's
game is solved: ``rounds`` rounds in which each racing drone in turn computes its best response (a QP, see
:mod:`spiral.baselines.best_response`) to the latest plans of the others. The plans are then flown through the
env's own action interface: the plan's reference position, velocity and acceleration at the next control step are
turned into a PID target with feed-forward. Formulation, defaults and measurements: ``docs/se_ibr.md``.
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

from spiral.baselines.best_response import BestResponseQP
from spiral.baselines.centreline import Centreline
from spiral.baselines.game import GameParams, Player, gate_row_table, iterate_best_responses
from spiral.config.base import NonNegFloat, PosFloat, PosInt, StrictModel
from spiral.env.race_env import RaceEnv

__all__ = ["PlannerPolicy", "SEIBRCfg", "SEIBRPlanner", "dynamic_limits", "game_params", "opponent_policy",
           "se_ibr_policy"]


class SEIBRCfg(StrictModel):
    """Parameters of the SE-IBR planner. None of them refers to a particular track."""

    alpha: NonNegFloat = Field(default=1.0, description="Weight α of the sensitivity term; 0 = plain IBR")
    horizon: PosFloat = Field(default=1.8, description="Planning horizon [s]")
    dt: PosFloat = Field(default=0.15, description="Time between waypoints Δt [s]")
    rounds: PosInt = Field(default=2, description="IBR rounds L per planning step")
    first_rounds: PosInt = Field(default=4, description="IBR rounds when a drone has no previous plan")
    replan_every: PosInt = Field(default=2, description="Control steps between planning steps (plan held between)")
    speed_frac: float = Field(default=1.0, gt=0, le=1,
                              description="Speed bound as a share of the largest steady speed whose PID target "
                                          "(with room for a_max) fits in the action: min((K_p·pos_scale − a_max)/K_d)")
    accel_frac: float = Field(default=0.35, gt=0, le=1,
                              description="Acceleration bound as a share of the airframe's level-flight "
                                          "acceleration g·√(TWR² − 1)")
    gate_margin: NonNegFloat = Field(default=0.08, description="Margin inside opening/2 − radius [m]")
    funnel_slope: PosFloat = Field(default=1.5, description="Widening of the gate funnels per metre of depth")
    funnel_reach: PosFloat = Field(default=1.5, description="Distance from the next gate within which its approach "
                                                            "funnel is enforced [m]")
    exit_reach: PosFloat = Field(default=0.6, description="Distance from a passed gate's centre within which its "
                                                          "exit funnel is enforced [m]")
    drone_margin: NonNegFloat = Field(default=0.15, description="Separation between drones beyond 2·radius [m]")
    wall_margin: NonNegFloat = Field(default=0.1, description="Distance kept from the ground and arena walls "
                                                              "beyond the radius [m]")
    progress_weight: PosFloat = Field(default=1.0, description="Weight of the progress at the horizon [1/m]")
    smooth_weight: NonNegFloat = Field(default=1e-3, description="Weight of Σ‖a_k‖²·Δt [s³/m²]")
    soft_penalty: PosFloat = Field(default=1e3, description="Linear penalty per unit of slack in the fallback")
    solver_tol: PosFloat = Field(default=1e-7, description="Clarabel feasibility and gap tolerances")
    lookahead: NonNegFloat = Field(default=1.0, description="Control steps ahead at which the plan is sampled")
    guard_steps: int = Field(default=3, ge=0, description="Waypoints over which a flown drone also avoids the "
                                                          "constant-velocity extrapolation of drones another "
                                                          "planner flies")
    sensitivity: bool = Field(default=True, description="Compute the sensitivity term (False skips the code "
                                                        "path; with α = 0 both must agree)")


def dynamic_limits(env: RaceEnv, cfg: SEIBRCfg) -> tuple[float, float]:
    """Speed and acceleration bounds (v_max [m/s], a_max [m/s²]) from the airframe, its PID and the action.

    ``a_max = accel_frac·g·√(TWR² − 1)`` (capped at ``K_p·reach/2``); ``v_max`` is ``speed_frac`` times the fastest
    steady speed whose PID target, with room for ``a_max`` of feed-forward, fits in the action:
    ``min_axis (K_p·reach − a_max)/K_d``. ``reach`` is ``pos_scale`` in relative mode, half the arena's smallest
    extent in absolute mode.
    """
    air, act, track = env.world.airframe, env.cfg.action, env.track
    kp, kd = np.asarray(air.pid.pos_p, float), np.asarray(air.pid.pos_d, float)
    reach = act.pos_scale if act.mode == "relative" else 0.5 * float(np.min(np.subtract(track.bounds.max,
                                                                                      track.bounds.min)))
    # A short action reach also caps the acceleration: at most half of it goes to acceleration feed-forward.
    a_max = min(cfg.accel_frac * env.world.sim.gravity * math.sqrt(air.thrust_to_weight**2 - 1.0),
                0.5 * float(np.min(kp)) * reach)
    v_max = cfg.speed_frac * float(np.min((kp * reach - a_max) / kd))
    return v_max, a_max


def game_params(env: RaceEnv, cfg: SEIBRCfg, steps: int) -> GameParams:
    """Geometry and weights of the game from the track, the airframe's radius and ``cfg``."""
    track, r = env.track, env.world.airframe.radius
    gates = range(len(track.gates))
    return GameParams(
        steps=steps, dt=cfg.dt, gate_half=np.array([track.gate_opening(i) / 2 - r - cfg.gate_margin for i in gates]),
        tube=max(track.gate_bar(i) for i in gates) / 2 + r + cfg.gate_margin, slope=cfg.funnel_slope,
        reach=cfg.funnel_reach, exit_reach=cfg.exit_reach, separation=2 * r + cfg.drone_margin,
        progress_weight=cfg.progress_weight, alpha=cfg.alpha, guard_steps=cfg.guard_steps,
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
        self.own_slots = set(range(env.drones_per_world) if own_slots is None else own_slots)
        """Slots this planner flies; the others are predicted in its game but flown by someone else."""
        self.cfg = SEIBRCfg(**{**(cfg.model_dump() if cfg is not None else {}), **overrides})
        c, track, air = self.cfg, env.track, env.world.airframe
        self.N = max(2, round(c.horizon / c.dt))
        self.W, self.D = env.world_count, env.drones_per_world
        self.ctrl_dt = float(env.dt)
        self.line = Centreline(track)
        self.kp, self.kd, self.ki = (np.asarray(x, float) for x in (air.pid.pos_p, air.pid.pos_d, air.pid.pos_i))
        self.v_max, self.a_max = dynamic_limits(env, c)
        self.params = game_params(env, c, self.N)
        self.gate_table = gate_row_table(self.line, self.params)
        margin = air.radius + c.wall_margin
        self.lo = np.asarray(track.bounds.min, float) + margin
        self.hi = np.asarray(track.bounds.max, float) - margin
        self.plans = np.zeros((self.W, self.D, self.N + 1, 3))
        """Latest plan p_0 … p_N of each drone (world-time ``plan_time`` at p_0)."""
        self.plan_v0 = np.zeros((self.W, self.D, 3))
        self.duals = np.zeros((self.W, self.D, self.D, self.N))
        """``duals[w, i, j, k]``: multiplier of i's collision row against j at waypoint k."""
        self.has_plan = np.zeros((self.W, self.D), dtype=bool)
        self.fallback = np.zeros((self.W, self.D), dtype=bool)
        """Whether each drone's current plan comes from the soft-constraint fallback."""
        self.plan_time = np.full(self.W, -np.inf)
        self._qps: dict[tuple[int, int], BestResponseQP] = {}
        self.drone_ms: list[float] = []
        """Time of each drone's best responses in one planning step (all rounds) [ms]."""
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

    def timing(self) -> dict[str, float]:
        """Planning cost: ms per plan per drone (median, p95), per world step, and the fallback rate."""
        d = np.asarray(self.drone_ms) if self.drone_ms else np.zeros(1)
        w = np.asarray(self.world_ms) if self.world_ms else np.zeros(1)
        return {"plans": len(self.drone_ms), "drone_ms_median": float(np.median(d)),
                "drone_ms_p95": float(np.percentile(d, 95)), "world_ms_median": float(np.median(w)),
                "world_ms_p95": float(np.percentile(w, 95)), "solves": self.solves,
                "soft_fraction": self.soft_solves / max(self.solves, 1)}

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
            self._qps[key] = BestResponseQP(steps=self.N, others=self.D - 1, dt=c.dt, v_max=self.v_max,
                                            a_max=self.a_max, smooth=c.smooth_weight, lo=self.lo, hi=self.hi,
                                            soft_penalty=c.soft_penalty, tol=c.solver_tol)
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
            if self.has_plan[w, s]:
                plan, duals = self._shifted(w, s, t - self.plan_time[w])
            else:
                plan = p0 + v0 * self.cfg.dt * np.arange(self.N + 1)[:, None]
                duals, fresh = np.zeros((self.D, self.N)), True
            plan[0] = p0
            players.append(Player(slot=s, p0=p0, v0=v0, next_gate=int(state["gate"][i]),
                                  passed_any=bool(state["passed"][i]), plan=plan, duals=duals, qp=self._qp(w, s),
                                  owned=s in self.own_slots))
        if not players:
            return
        n_rounds = rounds or (self.cfg.first_rounds if fresh else self.cfg.rounds)
        iterate_best_responses(self.line, self.gate_table, players, self.D, self.params, n_rounds)
        for pl in players:
            self.plans[w, pl.slot], self.plan_v0[w, pl.slot] = pl.plan, pl.v0
            self.duals[w, pl.slot] = pl.duals
            self.has_plan[w, pl.slot] = True
            self.fallback[w, pl.slot] = pl.last is not None and pl.last.soft
            self.drone_ms.append(pl.solve_ms)
        self.solves += n_rounds * len(players)
        self.soft_solves += sum(pl.soft_count for pl in players)
        self.plan_time[w] = t
        self.world_ms.append(1e3 * (time.perf_counter() - t0))

    # Flying the plan

    def _reference(self, idx: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity and acceleration of the plans of drones ``idx`` at ``tau`` after planning (cubic
        Hermite through the waypoints, velocities by central differences, v_0 the measured one)."""
        w, s, dt, N = idx // self.D, idx % self.D, self.cfg.dt, self.N
        P = self.plans[w, s]
        V = np.empty_like(P)
        V[:, 0] = self.plan_v0[w, s]
        V[:, 1:N] = (P[:, 2:] - P[:, :-2]) / (2 * dt)
        V[:, N] = (P[:, N] - P[:, N - 1]) / dt
        x = np.clip(tau / dt, 0.0, float(N))
        j = np.minimum(np.floor(x).astype(np.int64), N - 1)
        u = (x - j)[:, None]
        rows = np.arange(len(idx))
        p0, p1, v0, v1 = P[rows, j], P[rows, j + 1], V[rows, j] * dt, V[rows, j + 1] * dt
        pos = (2 * u**3 - 3 * u**2 + 1) * p0 + (u**3 - 2 * u**2 + u) * v0 + (-2 * u**3 + 3 * u**2) * p1 \
            + (u**3 - u**2) * v1
        vel = ((6 * u**2 - 6 * u) * p0 + (3 * u**2 - 4 * u + 1) * v0 + (-6 * u**2 + 6 * u) * p1
               + (3 * u**2 - 2 * u) * v1) / dt
        acc = ((12 * u - 6) * p0 + (6 * u - 4) * v0 + (-12 * u + 6) * p1 + (6 * u - 2) * v1) / dt**2
        return pos, vel, acc

    def _track(self, idx: np.ndarray, state: dict[str, np.ndarray]) -> np.ndarray:
        """Env actions that make the PID follow the plans: target = p_ref + (a_ref + K_d·v_ref − K_i·I)/K_p."""
        out = np.zeros((len(idx), 4))
        w, s = idx // self.D, idx % self.D
        ok = state["racing"][idx] & self.has_plan[w, s]
        if not ok.any():
            return out
        sel = idx[ok]
        tau = state["time"][sel // self.D] - self.plan_time[sel // self.D] + self.cfg.lookahead * self.ctrl_dt
        pos, vel, acc = self._reference(sel, tau)
        target = pos + (acc + self.kd * vel - self.ki * state["integral"][sel]) / self.kp
        act = self.env.cfg.action
        if act.mode == "relative":
            a = (target - state["pos"][sel]) / act.pos_scale
            a /= np.maximum(1.0, np.abs(a).max(axis=1, keepdims=True))
        else:
            lo, hi = np.asarray(self.env.track.bounds.min), np.asarray(self.env.track.bounds.max)
            a = np.clip(2.0 * (target - lo) / (hi - lo) - 1.0, -1.0, 1.0)
        out[ok, :3] = a
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
