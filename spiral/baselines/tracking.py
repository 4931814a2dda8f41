"""Flying a plan through the PID: the plan as a smooth reference, and the target that makes the PID follow it.

A plan is the measured position ``p_0`` and velocity ``v_0``, the node accelerations ``A_0 … A_N`` Δt apart (linear in
between; ``A_0`` continues the previous plan) and the waypoints ``p_1 … p_N`` they lead to
(:mod:`spiral.baselines.best_response`). The reference is that motion itself, so what is flown is what was checked.

The PID's position law (``spiral.sim.pid``, drag compensated inside it) gives the net acceleration
``a = K_p∘(p* − p) + K_i∘I − K_d∘v``. The target ``p* = p_ref + (a_ref + K_d∘v_ref − K_i∘I)/K_p`` therefore
makes it apply ``a_ref + K_p∘(p_ref − p) + K_d∘(v_ref − v)``: the plan's acceleration as feed-forward plus
feedback on the tracking error. A target beyond the action's reach gives up the along-track part of its offset
first (see :func:`target_actions`).
"""

from __future__ import annotations

import numpy as np

from spiral.config.env import ActionCfg

__all__ = ["integrate_plan", "pid_target", "sample_plans", "target_actions"]


def integrate_plan(p0: np.ndarray, v0: np.ndarray, acc: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Node positions and velocities (N + 1, 3 each) of the motion with node accelerations ``acc`` (N + 1, 3), linear
    in between, from ``p0`` and ``v0`` (3,): the planner's model of a plan."""
    pos, vel = [np.asarray(p0, float)], [np.asarray(v0, float)]
    for k in range(len(acc) - 1):
        pos.append(pos[-1] + vel[-1] * dt + dt**2 * (acc[k] / 3.0 + acc[k + 1] / 6.0))
        vel.append(vel[-1] + dt * (acc[k] + acc[k + 1]) / 2.0)
    return np.array(pos), np.array(vel)


def sample_plans(plans: np.ndarray, acc: np.ndarray, v0: np.ndarray, dt: float, tau: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position, velocity and acceleration (M, 3 each) of ``plans`` at ``tau`` (M,) after p_0.

    ``plans`` (M, N + 1, 3) are the waypoints p_0 … p_N and ``acc`` (M, N + 1, 3) the node accelerations; the
    acceleration is linear between nodes and the motion starts with the velocity ``v0`` (M, 3), exactly as the
    planner modelled it. Times past the last node give the last node's values.
    """
    n = plans.shape[1] - 1
    tau = np.clip(np.asarray(tau, float), 0.0, n * dt)
    vel_nodes = v0[:, None] + np.concatenate([np.zeros_like(acc[:, :1]),
                                              np.cumsum(0.5 * dt * (acc[:, 1:] + acc[:, :-1]), axis=1)], axis=1)
    j = np.minimum(np.floor(tau / dt).astype(np.int64), n - 1)
    u = (tau - j * dt)[:, None]
    rows = np.arange(len(plans))
    a_j, jerk = acc[rows, j], (acc[rows, j + 1] - acc[rows, j]) / dt
    v_j = vel_nodes[rows, j]
    pos = plans[rows, j] + v_j * u + 0.5 * a_j * u**2 + jerk * u**3 / 6.0
    return pos, v_j + a_j * u + 0.5 * jerk * u**2, a_j + jerk * u


def pid_target(pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, integral: np.ndarray, *, kp: np.ndarray,
               kd: np.ndarray, ki: np.ndarray) -> np.ndarray:
    """PID target ``p_ref + (a_ref + K_d∘v_ref − K_i∘I)/K_p`` (M, 3) for references and integral states (M, 3)."""
    return pos + (acc + kd * vel - ki * integral) / kp


def target_actions(target: np.ndarray, pos: np.ndarray, along: np.ndarray, action: ActionCfg, *,
                   arena_lo: np.ndarray, arena_hi: np.ndarray) -> np.ndarray:
    """Position part (M, 3) of the env action that sets a PID target for ``target`` (M, 3), saturated along the path.

    Relative mode: the offset ``o = target − pos`` must fit in the box ``[−pos_scale, pos_scale]³``. When it does
    not, its component along ``along`` (M, 3; the reference velocity) is shortened first, since it only changes how
    fast the drone moves along its path, while the cross-track part, which keeps it on the path (and in the gate
    openings), is kept; an axis on which the cross-track part alone does not fit is clipped. Absolute mode: the
    target mapped to the arena box ``[arena_lo, arena_hi]`` and clipped.
    """
    if action.mode != "relative":
        return np.clip(2.0 * (target - arena_lo) / (arena_hi - arena_lo) - 1.0, -1.0, 1.0)
    off = (target - pos) / action.pos_scale
    norm = np.linalg.norm(along, axis=1, keepdims=True)
    u = np.where(norm > 1e-6, along / np.maximum(norm, 1e-12), 0.0)
    par = (off * u).sum(1, keepdims=True) * u
    perp = off - par
    # Largest s ∈ [0, 1] with |perp_i + s·par_i| ≤ 1 on every axis whose cross-track part fits by itself.
    with np.errstate(divide="ignore", invalid="ignore"):
        room = np.where(par > 0, (1.0 - perp) / par, np.where(par < 0, (-1.0 - perp) / par, np.inf))
    room = np.where(np.abs(perp) <= 1.0, room, np.inf)
    scale = np.clip(room.min(axis=1, keepdims=True), 0.0, 1.0)
    return np.clip(perp + scale * par, -1.0, 1.0)
