"""The racing game of one world: linearised constraints and objective of each player, and the IBR loop."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from spiral.baselines.best_response import BestResponseQP, RowData, Solution
from spiral.baselines.centreline import Centreline

__all__ = ["GameParams", "Player", "gate_rows", "iterate_best_responses", "plan_phases", "player_rows",
           "progress_directions"]

_INF = 1e30
_SIGNS = np.array([1.0, -1.0, 1.0, -1.0])


@dataclass(frozen=True)
class GameParams:
    """Numbers the linearisation needs (derived from :class:`~spiral.baselines.se_ibr.SEIBRCfg` and the env)."""

    steps: int
    """Waypoints per plan N."""
    dt: float
    """Time between waypoints [s]."""
    gate_half: np.ndarray
    """Half side of each gate's usable opening: opening/2 − radius − margin (G,) [m]."""
    tube: float
    """Depth either side of a gate plane inside which the opening's tube applies (no widening) [m]."""
    slope: float
    """Widening of the approach/exit funnel per metre of depth beyond the tube."""
    reach: float
    """Distance from a gate's centre within which its approach funnel is enforced [m]."""
    exit_reach: float
    """Distance from a passed gate's centre within which its exit funnel is enforced [m]."""
    capture: float
    """Lateral distance beyond the usable opening, at the gate's plane, within which a waypoint of the previous
    iterate gets the next gate's approach rows [m]; it grows by ``capture_slope`` per metre in front of the plane."""
    capture_slope: float
    """Growth of ``capture`` per metre in front of the gate's plane."""
    separation: float
    """Minimum centre distance between two drones in a plan: 2·radius + margin [m]."""
    progress_weight: float
    """Weight of the terminal progress along the centreline [1/m]."""
    alpha: float
    """Weight of the sensitivity term; 0 gives plain iterated best response."""
    running_weight: float = 0.0
    """Weight of the progress of the first waypoint along the centreline [1/m]."""
    discount: float = 1.0
    """Factor of that weight from one waypoint to the next."""
    guard_steps: int = 3
    """Waypoints over which an owned drone also avoids the constant-velocity extrapolation of drones it does not
    fly (their own planner may not do what this game predicts)."""
    frame_clear: float = 0.49
    """Lateral distance from a gate's centre beyond which a drone clears its frame: outer/2 + radius + margin [m]."""
    sensitivity: bool = True
    """Compute the sensitivity term at all (False skips that code path; α = 0 must give the same plans)."""


@dataclass
class Player:
    """One drone in the game: its state now and its latest plan."""

    slot: int
    p0: np.ndarray
    """Position now (3,)."""
    v0: np.ndarray
    """Velocity now (3,)."""
    next_gate: int
    """Index of the next gate to pass (env's ``next_gate``)."""
    passed_any: bool
    """Whether it has passed a gate in this race (so the previous gate's exit funnel applies)."""
    plan: np.ndarray
    """Latest plan p_0 … p_N (N + 1, 3), p_0 = position now."""
    duals: np.ndarray
    """Duals of its collision rows against every slot (D, N); zero for itself and absent slots."""
    qp: BestResponseQP
    a0: np.ndarray | None = None
    """Acceleration its previous plan commands now, A_0 (3,); None = zero (no previous plan)."""
    acc: np.ndarray | None = None
    """Node accelerations A_0 … A_N of ``plan`` (N + 1, 3), once it has a best response."""
    owned: bool = True
    """Whether this planner flies the drone (else it is only predicted, e.g. an opponent with its own planner)."""
    solve_ms: float = 0.0
    """Wall time spent on this player's best responses in the current planning step [ms]."""
    solve_cpu_ms: float = 0.0
    """Processor time of the same [ms] (what the wall time would be on a core of its own)."""
    last: Solution | None = None
    """Its most recent best response."""
    soft_count: int = 0
    """Best responses in the current planning step that needed the soft fallback."""


def plan_phases(line: Centreline, plan: np.ndarray, next_gate: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gates passed before each waypoint of ``plan`` (N + 1, 3), and the straddling pairs.

    Returns ``phase`` (N + 1,), ``before`` and ``after`` (N + 1,): the gate index whose plane the segment
    ``k → k+1`` (before) or ``k−1 → k`` (after) crosses forwards, −1 elsewhere. Gates are taken in order.
    """
    n, G = len(plan), line.gate_count
    gates = (next_gate + np.arange(min(n, G + 1))) % G
    depth = ((plan[None, :, :] - line.center[gates][:, None, :]) * line.forward[gates][:, None, :]).sum(-1).tolist()
    phase = np.zeros(n, dtype=np.int64)
    before = np.full(n, -1, dtype=np.int64)
    after = np.full(n, -1, dtype=np.int64)
    m = 0
    for k in range(1, n):
        if m < len(gates) and depth[m][k - 1] < 0.0 <= depth[m][k]:
            before[k - 1], after[k] = gates[m], gates[m]
            m += 1
        phase[k] = m
    return phase, before, after


def gate_rows(line: Centreline, gate: int, half: float, *, slope: float, tube: float, side: int
              ) -> tuple[np.ndarray, np.ndarray]:
    """Four rows ``a·p ≤ b`` of gate ``gate``'s opening: ``|y|, |z| ≤ half + slope·(side·depth − tube)``.

    ``side`` = −1 is the approach funnel (widening in front of the plane), +1 the exit funnel, 0 the tube
    ``|y|, |z| ≤ half`` with y, z the gate's in-plane axes. Returns normals (4, 3) and bounds (4,).
    """
    c, f = line.center[gate], line.forward[gate]
    axes = np.stack([line.axis_y[gate], line.axis_y[gate], line.axis_z[gate], line.axis_z[gate]]) * _SIGNS[:, None]
    if side == 0:
        a, b = axes, np.full(4, half)
    else:
        a = axes - side * slope * f[None, :]
        b = np.full(4, half - slope * tube)
    return a, b + a @ c


_TUBE, _APPROACH, _EXIT = 0, 1, 2


def gate_row_table(line: Centreline, gp: GameParams) -> tuple[np.ndarray, np.ndarray]:
    """Rows of every gate in each form (tube, approach funnel, exit funnel): normals (3, G, 4, 3), bounds (3, G, 4)."""
    rows = [[gate_rows(line, g, gp.gate_half[g], slope=gp.slope, tube=gp.tube, side=side) for g in
             range(line.gate_count)] for side in (0, -1, 1)]
    return (np.array([[r[0] for r in kind] for kind in rows]), np.array([[r[1] for r in kind] for kind in rows]))


def _gate_constraints(line: Centreline, table: tuple[np.ndarray, np.ndarray], pl: Player, gp: GameParams
                      ) -> tuple[np.ndarray, ...]:
    """Gate rows (N, 4, 3), (N, 4) of player ``pl``'s next plan, the phase of each waypoint and the straddles.

    Per waypoint (linearised at the previous plan): both ends of a segment that crosses a gate plane get that
    gate's tube; else, within ``exit_reach`` of the gate just passed and past its plane, its exit funnel (tube up to
    ``tube`` deep); else, within ``reach`` of the next gate, nearer to it than to the gate before, and inside its
    capture cone (lateral offset ≤ half opening + ``capture`` + ``capture_slope``·depth in front), its approach
    funnel (tube within ``tube`` of the plane); else no gate row. A waypoint far beside the gate for its depth
    (flying past the gate to come back to it, or beside a gate that shares its plane with the one just passed) gets
    no row it could not meet.
    """
    N, G = gp.steps, line.gate_count
    phase, before, after = plan_phases(line, pl.plan, pl.next_gate)
    p = pl.plan[1:]
    target = (pl.next_gate + phase[1:]) % G
    prev = (target - 1) % G
    d_prev = ((p - line.center[prev]) * line.forward[prev]).sum(-1)
    d_next = ((p - line.center[target]) * line.forward[target]).sum(-1)
    straddle = np.maximum(before[1:], after[1:])
    passed_prev = (phase[1:] > 0) | pl.passed_any
    exit_ok = (straddle < 0) & passed_prev & (d_prev >= 0.0) & (
        np.linalg.norm(p - line.center[prev], axis=1) <= gp.exit_reach)
    rel = p - line.center[target]
    lateral = np.maximum(np.abs((rel * line.axis_y[target]).sum(-1)), np.abs((rel * line.axis_z[target]).sum(-1)))
    capture = gp.gate_half[target] + gp.capture + gp.capture_slope * np.maximum(-d_next, 0.0)
    dist = np.linalg.norm(rel, axis=1)
    nearer = dist <= np.linalg.norm(p - line.center[prev], axis=1)
    approach_ok = (straddle < 0) & ~exit_ok & (dist <= gp.reach) & nearer & (lateral <= capture)
    gate = np.where(straddle >= 0, straddle, np.where(exit_ok, prev, target))
    kind = np.where(straddle >= 0, _TUBE, np.where(exit_ok, np.where(d_prev <= gp.tube, _TUBE, _EXIT),
                                                  np.where(-d_next <= gp.tube, _TUBE, _APPROACH)))
    active = (straddle >= 0) | exit_ok | approach_ok
    ga, gb = np.zeros((N, 4, 3)), np.full((N, 4), _INF)
    ga[active], gb[active] = table[0][kind[active], gate[active]], table[1][kind[active], gate[active]]
    return ga, gb, phase, before, after


def _frame_constraints(line: Centreline, table: tuple[np.ndarray, np.ndarray], pl: Player, gp: GameParams,
                       before: np.ndarray, after: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows (N, 4, 3), (N, 4) for segments of the previous plan that cross a gate plane other than as a pass.

    A drone may cross a gate's plane backwards or beside the opening (turning back behind a passed gate, or
    flying past a later one), but not through its frame. Both ends of such a segment get that gate's tube when
    the crossing point is nearer the opening than the outside of the frame, else one row keeping them beyond
    ``frame_clear`` on the side of the crossing's larger in-plane offset.
    """
    N = gp.steps
    fa, fb = np.zeros((N, 4, 3)), np.full((N, 4), _INF)
    rel = pl.plan[None, :, :] - line.center[:, None, :]  # (G, N + 1, 3)
    depth = (rel * line.forward[:, None, :]).sum(-1)
    side = np.sign(depth)
    g_idx, k_idx = np.nonzero(side[:, 1:] != side[:, :-1])
    for g, k in zip(g_idx.tolist(), (k_idx + 1).tolist(), strict=True):
        if after[k] == g and before[k - 1] == g:
            continue  # the pass itself: handled by the gate rows
        t = depth[g, k - 1] / (depth[g, k - 1] - depth[g, k])
        hit = rel[g, k - 1] + t * (rel[g, k] - rel[g, k - 1])
        y, z = float(hit @ line.axis_y[g]), float(hit @ line.axis_z[g])
        if max(abs(y), abs(z)) < 0.5 * (gp.gate_half[g] + gp.frame_clear):
            a, b = table[0][_TUBE, g], table[1][_TUBE, g]
        else:
            axis = line.axis_y[g] if abs(y) >= abs(z) else line.axis_z[g]
            s = np.sign(y if abs(y) >= abs(z) else z)
            a = np.zeros((4, 3))
            b = np.full(4, _INF)
            a[0], b[0] = -s * axis, -gp.frame_clear - s * axis @ line.center[g]
        for j in (k - 1, k):
            if j >= 1 and (fb[j - 1] >= 1e20).all():  # first crossing found keeps the slot
                fa[j - 1], fb[j - 1] = a, b
    return fa, fb


def _unit(v: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 1e-6, v / np.maximum(n, 1e-12), fallback)


def progress_directions(line: Centreline, points: np.ndarray, gates: np.ndarray, gp: GameParams) -> np.ndarray:
    """Direction of progress (N, 3) at ``points`` (N, 3) whose next gate is ``gates`` (N,): the reference line's tangent
    at the point's projection, except behind the gate's plane, or at it beside the opening (the drone flew past the
    gate), where it points back to the gate's approach point, ``tube`` in front of its centre."""
    tangent = line.tangent[line.project(points, gates)]
    rel = points - line.center[gates]
    depth = (rel * line.forward[gates]).sum(-1)
    lateral = np.maximum(np.abs((rel * line.axis_y[gates]).sum(-1)), np.abs((rel * line.axis_z[gates]).sum(-1)))
    past = (depth > gp.tube) | ((depth > -gp.tube) & (lateral > gp.gate_half[gates] + gp.capture))
    back = _unit(line.center[gates] - gp.tube * line.forward[gates] - points, tangent)
    return np.where(past[:, None], back, tangent)


def player_rows(line: Centreline, table: tuple[np.ndarray, np.ndarray], pl: Player, players: list[Player], slots: int,
                gp: GameParams) -> RowData:
    """The linearised best-response problem of ``pl`` against the latest plans of ``players`` (D = ``slots``)."""
    N = gp.steps
    ga, gb, phase, before, after = _gate_constraints(line, table, pl, gp)
    fa, fb = _frame_constraints(line, table, pl, gp, before, after)
    q = np.zeros((N, 3))
    tangent = progress_directions(line, pl.plan[1:], (pl.next_gate + phase[1:]) % line.gate_count, gp)
    q -= gp.running_weight * gp.discount ** np.arange(N)[:, None] * tangent
    q[N - 1] -= gp.progress_weight * tangent[N - 1]
    others = [s for s in range(slots) if s != pl.slot]
    ca, cb = np.zeros((N, len(others), 3)), np.full((N, len(others)), _INF)
    ga2, gb2 = np.zeros((N, len(others), 3)), np.full((N, len(others)), _INF)
    by_slot = {o.slot: o for o in players}
    up = np.array([0.0, 0.0, 1.0])
    for col, s in enumerate(others):
        other = by_slot.get(s)
        if other is None:
            continue
        fallback = _unit(other.p0 - pl.p0, up)
        beta = _unit(other.plan[1:] - pl.plan[1:], fallback)  # unit vectors from pl towards the other (N, 3)
        ca[:, col] = beta
        cb[:, col] = (beta * other.plan[1:]).sum(-1) - gp.separation
        if gp.sensitivity:
            mu = other.duals[pl.slot]  # the other's multipliers of its rows against pl (N,)
            q -= gp.alpha * mu[:, None] * beta
        if pl.owned and not other.owned and gp.guard_steps > 0:
            k = min(gp.guard_steps, N)
            cv = other.p0 + other.v0 * gp.dt * np.arange(1, k + 1)[:, None]
            g_beta = _unit(cv - pl.plan[1:k + 1], fallback)
            ga2[:k, col] = g_beta
            gb2[:k, col] = (g_beta * cv).sum(-1) - gp.separation
    return RowData(p0=pl.p0, v0=pl.v0, a0=pl.a0, q=q, gate_a=ga, gate_b=gb, coll_a=ca, coll_b=cb, guard_a=ga2,
                   guard_b=gb2, frame_a=fa, frame_b=fb)


def iterate_best_responses(line: Centreline, table: tuple[np.ndarray, np.ndarray], players: list[Player], slots: int,
                           gp: GameParams, rounds: int) -> None:
    """``rounds`` rounds of iterated best response: each player in turn against the others' latest plans.

    Updates every player's ``plan``, ``acc``, ``duals`` (against each slot), ``solve_ms`` and ``solve_cpu_ms`` in
    place.
    """
    for _ in range(rounds):
        for pl in players:
            t0, c0 = time.perf_counter(), time.process_time()
            rows = player_rows(line, table, pl, players, slots, gp)
            sol = pl.qp.solve(rows)
            pl.plan = np.concatenate([pl.p0[None], sol.plan], axis=0)
            pl.acc = np.concatenate([np.zeros((1, 3)) if pl.a0 is None else pl.a0[None], sol.acc], axis=0)
            others = [s for s in range(slots) if s != pl.slot]
            pl.duals = np.zeros((slots, gp.steps))
            if not sol.soft:  # a fallback's multipliers price the penalty, not the opponent: no sensitivity
                pl.duals[others] = sol.coll_dual.T
            pl.last = sol
            pl.soft_count += int(sol.soft)
            pl.solve_ms += 1e3 * (time.perf_counter() - t0)
            pl.solve_cpu_ms += 1e3 * (time.process_time() - c0)
