"""One player's best response as a second-order-cone QP solved by Clarabel, with a soft-constraint fallback.

The plan is flown with an acceleration that changes linearly between nodes ``t_k = kΔt`` (the attitude loop turns
the thrust gradually, so the acceleration cannot jump). The variables are the node positions (the waypoints),
velocities and accelerations ``p_k, v_k, A_k``, k = 1 … N (stacked, 9N); ``p_0``, ``v_0`` (measured) and ``A_0``
(the acceleration being commanded now) are constants. Equality rows tie them by the exact motion
``v_{k+1} = v_k + Δt(A_k + A_{k+1})/2``, ``p_{k+1} = p_k + v_kΔt + Δt²(A_k/3 + A_{k+1}/6)``. At each node the
thrust acceleration is ``f_k = A_k + g·ẑ + c∘v_k`` (c = drag / mass) and the PID target offset
``o_k = (A_k + K_d∘v_k)/K_p``. Constraints (Clarabel form ``A·x + s = b``, ``s`` in a cone), k = 1 … N:

- motion        the equality rows above                             (zero cone)
- arena         ``lo ≤ p_k ≤ hi``                                   (non-negative cone)
- gate          ``g_{k,j}·p_k ≤ b_{k,j}``, up to four per waypoint  (non-negative cone)
- frame         up to four more per waypoint: other gates' frames  (non-negative cone)
- collision     ``β_{k,o}·p_k ≤ b_{k,o}``, one per other player     (non-negative cone)
- guard         the same against drones flown by another planner, extrapolated at constant velocity
- floor         ``f_z ≥ floor``                                      (non-negative cone)
- reach         ``|o_k,i| ≤ reach_i`` per axis (relative action), or ``lo ≤ p_k + o_k ≤ hi`` (absolute)
- thrust        ``‖f_k‖ ≤ thrust``                                   (second-order cones)
- tilt          ``‖f_k,xy‖ ≤ tan θ·f_k,z``                           (second-order cones)
- jerk          ``‖A_k − A_{k−1}‖ ≤ jerk·Δt``                        (second-order cones)

The objective is ``½xᵀPx + qᵀx``: P is the smoothness term ``smooth·Σ‖A_k‖²·Δt`` and q is the linear objective
on the waypoints supplied per solve (progress and sensitivity terms).

Fallback: when the hard problem is not solved (infeasible, or the solver stops early), the same problem is solved
with a non-negative slack on the geometry rows (gates, frames, collisions, guards: the rows laid out from the
previous iterate and the other drones, which is where the hard problem turns infeasible), each penalised linearly by
``soft_penalty`` times a weight per kind (an exact penalty: where a feasible point exists the soft problem returns
it). When that is not solved either, every linear row (arena, floor, reach besides) and the jerk bounds get a slack
too. The thrust and tilt cones stay hard; coasting (thrust = weight, drag slowing the drone) satisfies them, so the
last fallback always has a solution.
"""

from __future__ import annotations

from dataclasses import dataclass

import clarabel
import numpy as np
import scipy.sparse as sp

from spiral.baselines.tracking import integrate_plan

__all__ = ["BestResponseQP", "PlanLimits", "RowData", "Solution", "SolverSettings"]

_SOLVED = ("Solved", "AlmostSolved")
_SLACK_WEIGHT = {"geometry": 5.0, "separation": 2.0, "dynamics": 1.0}
"""Fallback penalty per metre of slack, relative to ``soft_penalty``: violating the arena or a gate opening costs
most (the margin to a crash is a few cm), the drone separation less (its margin is larger), the flight stack's
reach, thrust floor and jerk bound least (the PID saturates and the next plan starts from where the drone is)."""


@dataclass(frozen=True)
class PlanLimits:
    """What a plan may ask of the drone (see :mod:`spiral.baselines.limits`), already scaled by the planner's shares."""

    thrust: float
    """Bound on the thrust acceleration ‖f‖ [m/s²]."""
    tan_tilt: float
    """Bound on ‖f_xy‖ / f_z."""
    floor: float
    """Lower bound on f_z [m/s²]."""
    gravity: float
    """Gravitational acceleration [m/s²]."""
    drag: np.ndarray
    """Drag over mass per axis c (3,) [1/s]."""
    kp: np.ndarray
    """PID position gain (3,) [1/s²]."""
    kd: np.ndarray
    """PID velocity gain (3,) [1/s]."""
    target_lo: np.ndarray
    """Lower bound of the PID target (3,) [m]: of its offset from the drone (relative), or of the target itself."""
    target_hi: np.ndarray
    """Upper bound of the PID target (3,) [m], as ``target_lo``."""
    absolute: bool = False
    """Whether the target bounds are absolute positions (absolute action mode) rather than offsets."""
    jerk: float = float("inf")
    """Bound on the rate of change of the acceleration [m/s³] (the attitude loop turns the thrust gradually)."""


@dataclass(frozen=True)
class SolverSettings:
    """How a best response is solved: the fallback's slack penalty and Clarabel's tolerance and refinement."""

    soft_penalty: float = 1e3
    """Linear penalty per unit of slack in the soft-constraint fallback."""
    tol: float = 1e-7
    """Clarabel's feasibility and gap tolerances."""
    refine: bool = False
    """Clarabel's iterative refinement."""

    def to_clarabel(self) -> clarabel.DefaultSettings:
        """Clarabel's settings: quiet, no presolve, these tolerances and refinement."""
        settings = clarabel.DefaultSettings()
        settings.verbose = False
        settings.presolve_enable = False
        settings.iterative_refinement_enable = self.refine
        for name in ("tol_gap_abs", "tol_gap_rel", "tol_feas"):
            setattr(settings, name, self.tol)
        return settings


@dataclass
class RowData:
    """The per-solve data of one best response (N waypoints, O other players)."""

    p0: np.ndarray
    """Position now (3,)."""
    v0: np.ndarray
    """Velocity now (3,)."""
    q: np.ndarray
    """Linear objective on the waypoints (N, 3), besides the smoothness term."""
    gate_a: np.ndarray
    """Gate row normals (N, 4, 3)."""
    gate_b: np.ndarray
    """Gate row upper bounds (N, 4); rows with an infinite bound are left out."""
    coll_a: np.ndarray
    """Collision half-plane normals (N, O, 3): unit vectors from this player towards the other one."""
    coll_b: np.ndarray
    """Collision upper bounds (N, O); rows with an infinite bound (absent players) are left out."""
    guard_a: np.ndarray | None = None
    """Extra half-planes against other drones' constant-velocity extrapolation (N, O, 3); no sensitivity."""
    guard_b: np.ndarray | None = None
    """Their upper bounds (N, O); infinite = left out."""
    frame_a: np.ndarray | None = None
    """Rows keeping segments that cross another gate's plane off its frame (N, 4, 3)."""
    frame_b: np.ndarray | None = None
    """Their upper bounds (N, 4); infinite = left out."""
    a0: np.ndarray | None = None
    """Acceleration the drone is being commanded now, A_0 (3,); None = zero."""


@dataclass
class Solution:
    """A best response."""

    plan: np.ndarray
    """Waypoints p_1 … p_N (N, 3)."""
    acc: np.ndarray
    """Node accelerations A_1 … A_N (N, 3)."""
    coll_dual: np.ndarray
    """Dual multipliers of the collision rows (N, O), clipped at zero; zero for rows left out."""
    raw_coll_dual: np.ndarray
    """The solver's dual values of the collision rows before clipping (N, O)."""
    status: str
    """Clarabel status of the solve that produced the plan."""
    soft: bool
    """Whether the plan comes from the soft-constraint fallback."""
    iterations: int
    """Interior-point iterations (hard solve plus fallback)."""


class _Rows:
    """Sparse rows ``Σ coef·x ≤ bound`` (or ``= bound``, or cone entries) collected as triplets."""

    def __init__(self) -> None:
        self.r: list[np.ndarray] = []
        self.c: list[np.ndarray] = []
        self.v: list[np.ndarray] = []
        self.count = 0
        self._joined: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def add(self, cols: list[np.ndarray], vals: list[np.ndarray | float], rows: int) -> np.ndarray:
        """Append ``rows`` rows, entry j of row i being ``vals[j][i]`` at column ``cols[j][i]``; returns their ids."""
        ids = self.count + np.arange(rows)
        self.count += rows
        self.extend(ids, cols, vals)
        return ids

    def extend(self, ids: np.ndarray, cols: list[np.ndarray], vals: list[np.ndarray | float]) -> None:
        """Add entries to the existing rows ``ids``, as :meth:`add`."""
        self._joined = None
        for col, val in zip(cols, vals, strict=True):
            self.r.append(np.asarray(ids))
            self.c.append(np.asarray(col))
            self.v.append(np.broadcast_to(np.asarray(val, float), (len(ids),)).copy())

    def triplets(self, row0: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(row, column, value) arrays, rows shifted by ``row0``; joined once per change of the rows."""
        if self._joined is None:
            self._joined = np.concatenate(self.r), np.concatenate(self.c), np.concatenate(self.v)
        r, c, v = self._joined
        return r + row0, c, v


class BestResponseQP:
    """Builds and solves one player's best response (a new Clarabel instance per solve: its setup takes about a fifth
    of the solve's time)."""

    def __init__(self, *, steps: int, others: int, dt: float, limits: PlanLimits, smooth: float, lo: np.ndarray,
                 hi: np.ndarray, solver: SolverSettings = SolverSettings()) -> None:
        self.N, self.O, self.dt, self.limits = steps, others, dt, limits
        self.lo, self.hi = np.asarray(lo, float), np.asarray(hi, float)
        self.soft_penalty = solver.soft_penalty
        self.settings = solver.to_clarabel()
        N = steps
        self.n = 9 * N
        self.ip = np.arange(3 * N).reshape(N, 3)
        """Column of p_{k+1}, axis i: ``ip[k, i]``; velocities and accelerations follow (``iv``, ``ia``)."""
        self.iv, self.ia = self.ip + 3 * N, self.ip + 6 * N
        diag = np.zeros(self.n)
        diag[6 * N:] = 2.0 * smooth * dt
        self.P = sp.csc_matrix(sp.diags(diag))
        self._eq = self._motion_rows()
        self._box, self._box_b = self._arena_rows()
        self._dyn, self._dyn_b = self._flight_rows()
        self._soc, self._soc_b = self._cone_rows()
        self.cones_soc = ([clarabel.SecondOrderConeT(4)] * N + [clarabel.SecondOrderConeT(3)] * N
                          + [clarabel.SecondOrderConeT(4)] * N)

    # Static rows

    def _motion_rows(self) -> _Rows:
        """v_{k+1} − v_k − Δt(A_k + A_{k+1})/2 = 0 and p_{k+1} − p_k − Δt·v_k − Δt²(A_k/3 + A_{k+1}/6) = 0 (3N each);
        the k = 0 terms are constants (:meth:`_motion_b`)."""
        dt, rows = self.dt, _Rows()
        ip, iv, ia = self.ip.ravel(), self.iv.ravel(), self.ia.ravel()
        later = np.arange(3, 3 * self.N)  # entries of nodes k + 1 ≥ 2, whose node-k terms are variables
        v_rows = rows.add([iv, ia], [1.0, -dt / 2.0], 3 * self.N)
        rows.extend(v_rows[later], [iv[later - 3], ia[later - 3]], [-1.0, -dt / 2.0])
        p_rows = rows.add([ip, ia], [1.0, -dt**2 / 6.0], 3 * self.N)
        rows.extend(p_rows[later], [ip[later - 3], iv[later - 3], ia[later - 3]], [-1.0, -dt, -dt**2 / 3.0])
        return rows

    def _motion_b(self, d: RowData) -> np.ndarray:
        dt = self.dt
        a0 = np.zeros(3) if d.a0 is None else np.asarray(d.a0, float)
        b = np.zeros(6 * self.N)
        b[0:3] = d.v0 + dt / 2.0 * a0
        b[3 * self.N:3 * self.N + 3] = d.p0 + dt * d.v0 + dt**2 / 3.0 * a0
        return b

    def _arena_rows(self) -> tuple[_Rows, np.ndarray]:
        rows, ip, n = _Rows(), self.ip.ravel(), 3 * self.N
        rows.add([ip], [1.0], n)
        rows.add([ip], [-1.0], n)
        return rows, np.concatenate([np.tile(self.hi, self.N), -np.tile(self.lo, self.N)])

    def _flight_rows(self) -> tuple[_Rows, np.ndarray]:
        """Floor ``−(A_z + c_z·v_z) ≤ g − floor`` (N) and reach ``±(A + K_d∘v [+ K_p∘p]) ≤ ±K_p∘bound`` (3N each)."""
        lim, N, rows = self.limits, self.N, _Rows()
        ip, iv, ia = self.ip.ravel(), self.iv.ravel(), self.ia.ravel()
        rows.add([self.ia[:, 2], self.iv[:, 2]], [-1.0, -lim.drag[2]], N)
        kd, kp = np.tile(lim.kd, N), np.tile(lim.kp, N)
        for sign in (1.0, -1.0):
            cols, vals = [ia, iv], [sign, sign * kd]
            if lim.absolute:
                cols, vals = [*cols, ip], [*vals, sign * kp]
            rows.add(cols, vals, 3 * N)
        b = np.concatenate([np.full(N, lim.gravity - lim.floor), kp * np.tile(lim.target_hi, N),
                            -kp * np.tile(lim.target_lo, N)])
        return rows, b

    def _cone_rows(self) -> tuple[_Rows, np.ndarray]:
        """Thrust ``[thrust; f]``, tilt ``[tan θ·f_z; f_x; f_y]`` and jerk ``[jerk·Δt; A_k − A_{k−1}]`` per node, with
        ``s = b − A·x`` (so the rows carry −coefficients)."""
        lim, N, rows = self.limits, self.N, _Rows()
        ia, iv = self.ia, self.iv
        blocks = np.zeros((N, 4))
        blocks[:, 0] = lim.thrust
        blocks[:, 3] = lim.gravity
        for k in range(N):  # thrust cone k: rows 4k … 4k + 3, the first (the bound) without entries
            rows.add([], [], 1)
            rows.add([ia[k], iv[k]], [-1.0, -lim.drag], 3)
        tilt = np.zeros((N, 3))
        tilt[:, 0] = lim.tan_tilt * lim.gravity
        for k in range(N):
            rows.add([[ia[k, 2]], [iv[k, 2]]], [-lim.tan_tilt, -lim.tan_tilt * lim.drag[2]], 1)
            rows.add([ia[k, :2], iv[k, :2]], [-1.0, -lim.drag[:2]], 2)
        jerk = np.zeros((N, 4))
        jerk[:, 0] = lim.jerk * self.dt if np.isfinite(lim.jerk) else 1e6
        for k in range(N):
            rows.add([], [], 1)
            cols, vals = [ia[k]], [-1.0]
            if k > 0:
                cols, vals = [*cols, ia[k - 1]], [*vals, 1.0]
            rows.add(cols, vals, 3)
        return rows, np.concatenate([blocks.ravel(), tilt.ravel(), jerk.ravel()])

    # Per solve

    def _geometry(self, d: RowData) -> tuple[_Rows, np.ndarray, np.ndarray, int, int]:
        """Gate, frame, collision and guard rows ``a·p_k ≤ b``; the active collision rows and where they start."""
        gb, cb = d.gate_b.ravel(), d.coll_b.ravel()
        ub = d.guard_b.ravel() if d.guard_b is not None else np.zeros(0)
        ua = d.guard_a.reshape(-1, 3) if d.guard_a is not None else np.zeros((0, 3))
        fb = d.frame_b.ravel() if d.frame_b is not None else np.zeros(0)
        fa = d.frame_a.reshape(-1, 3) if d.frame_a is not None else np.zeros((0, 3))
        g_act, c_act, u_act, f_act = (np.nonzero(np.isfinite(x) & (x < 1e20))[0] for x in (gb, cb, ub, fb))
        coef = np.concatenate([d.gate_a.reshape(-1, 3)[g_act], fa[f_act], d.coll_a.reshape(-1, 3)[c_act], ua[u_act]])
        wp = np.concatenate([g_act // 4, f_act // 4, c_act // self.O, u_act // self.O])
        rows = _Rows()
        rows.add([self.ip[wp, 0], self.ip[wp, 1], self.ip[wp, 2]], [coef[:, 0], coef[:, 1], coef[:, 2]], len(wp))
        b = np.concatenate([gb[g_act], fb[f_act], cb[c_act], ub[u_act]])
        return rows, b, c_act, len(g_act) + len(f_act), len(c_act) + len(u_act)

    def solve(self, d: RowData) -> Solution:
        """Best response for ``d``: the hard problem, or the soft fallback when that is not solved."""
        geo, geo_b, c_act, n_gate, n_sep = self._geometry(d)
        n_eq, n_box = self._eq.count, self._box.count
        blocks = [(self._eq, 0), (self._box, n_eq), (geo, n_eq + n_box), (self._dyn, n_eq + n_box + geo.count)]
        m = n_box + geo.count + self._dyn.count  # non-negative rows
        blocks.append((self._soc, n_eq + m))
        trip = [np.concatenate(x) for x in zip(*(rows.triplets(r0) for rows, r0 in blocks), strict=True)]
        soc_b = self._soc_b.copy()
        if d.a0 is not None:
            soc_b[7 * self.N + 1:7 * self.N + 4] = -np.asarray(d.a0, float)  # first jerk cone: A_1 − A_0
        b = np.concatenate([self._motion_b(d), self._box_b, geo_b, self._dyn_b, soc_b])
        A = sp.csc_matrix((trip[2], (trip[0], trip[1])), shape=(len(b), self.n))
        q = np.zeros(self.n)
        q[: 3 * self.N] = d.q.ravel()
        w = _SLACK_WEIGHT
        weight = np.concatenate([np.full(n_box + n_gate, w["geometry"]), np.full(n_sep, w["separation"]),
                                 np.full(self._dyn.count, w["dynamics"])])  # slack penalty per non-negative row
        c_rows = n_eq + n_box + n_gate + np.arange(len(c_act))
        cones = [clarabel.ZeroConeT(n_eq), clarabel.NonnegativeConeT(m), *self.cones_soc]
        sol = clarabel.DefaultSolver(self.P, q, A, b, cones, self.settings).solve()
        iters = int(sol.iterations)
        if str(sol.status) in _SOLVED:
            return self._solution(sol.x, sol.z, c_act, c_rows, str(sol.status), soft=False, iterations=iters)
        soft = sol  # without geometry rows the first fallback is the hard problem again: straight to the last
        if geo.count:
            geometry = np.arange(n_box, n_box + geo.count)
            soft = self._solve_soft(q, trip, b, n_eq, m, geometry, weight[geometry], jerk=False)
            iters += int(soft.iterations)
        if str(soft.status) not in _SOLVED:  # infeasible in the flight stack's rows too: every row gets a slack
            soft = self._solve_soft(q, trip, b, n_eq, m, np.arange(m), weight, jerk=True)
            iters += int(soft.iterations)
        x = np.asarray(soft.x)[: self.n]
        if str(soft.status) not in _SOLVED or not np.all(np.isfinite(x)):
            x = self._coast(d)  # never hand NaN to the controller
        return self._solution(x, np.nan_to_num(np.asarray(soft.z)), c_act, c_rows, str(soft.status), soft=True,
                              iterations=iters)

    def _solve_soft(self, q: np.ndarray, trip: list[np.ndarray], b: np.ndarray, n_eq: int, m: int,
                    lin: np.ndarray, lin_weight: np.ndarray, *, jerk: bool):
        """Slack σ ≥ 0 on the non-negative rows ``lin`` (a·x − σ ≤ b; indices within the m rows, penalty weights
        ``lin_weight``), with ``jerk`` on the jerk cones' bounds too, cost soft_penalty·Σ weight·σ (an exact
        penalty)."""
        n, N, rows_hard = self.n, self.N, len(b)
        heads = n_eq + m + 7 * N + 4 * np.arange(N) if jerk else np.zeros(0, int)
        weight = np.concatenate([lin_weight, np.full(len(heads), _SLACK_WEIGHT["dynamics"])])
        ns = len(weight)
        slack = n + np.arange(ns)
        r = np.concatenate([trip[0], n_eq + lin, heads, rows_hard + np.arange(ns)])
        c = np.concatenate([trip[1], slack, slack])
        v = np.concatenate([trip[2], -np.ones(2 * ns)])
        A = sp.csc_matrix((v, (r, c)), shape=(rows_hard + ns, n + ns))
        P = sp.block_diag([self.P, sp.csc_matrix((ns, ns))], format="csc")
        q_soft = np.concatenate([q, self.soft_penalty * weight])
        cones = [clarabel.ZeroConeT(n_eq), clarabel.NonnegativeConeT(m), *self.cones_soc,
                 clarabel.NonnegativeConeT(ns)]
        return clarabel.DefaultSolver(P, q_soft, A, np.concatenate([b, np.zeros(ns)]), cones, self.settings).solve()

    def _coast(self, d: RowData) -> np.ndarray:
        """Thrust = weight from the measured state (drag slows the drone; the acceleration goes there at once), as
        variables."""
        v = np.asarray(d.v0, float)
        acc = np.zeros((self.N + 1, 3)) if d.a0 is None else np.tile(np.asarray(d.a0, float), (self.N + 1, 1))
        for _ in range(3):  # A_k = −c∘v_k: a fixed point reached in a few passes (c·Δt ≪ 1)
            acc[1:] = -self.limits.drag * integrate_plan(d.p0, v, acc, self.dt)[1][1:]
        pos, vel = integrate_plan(d.p0, v, acc, self.dt)
        return np.concatenate([pos[1:].ravel(), vel[1:].ravel(), acc[1:].ravel()])

    def _solution(self, x, z, c_act: np.ndarray, c_rows: np.ndarray, status: str, *, soft: bool,
                  iterations: int) -> Solution:
        raw = np.zeros(self.N * self.O)
        raw[c_act] = np.asarray(z, float)[c_rows]
        raw = raw.reshape(self.N, self.O)
        x = np.asarray(x, float)
        return Solution(plan=x[self.ip].copy(), acc=x[self.ia].copy(), coll_dual=np.maximum(raw, 0.0),
                        raw_coll_dual=raw, status=status, soft=soft, iterations=iterations)
