"""One player's best response as a second-order-cone QP solved by Clarabel, with a soft-constraint fallback.

Variables are the waypoints ``p_1 … p_N`` (stacked, 3N); ``p_0`` (position now) and ``p_{−1} = p_0 − v_0·Δt``
are constants. Constraints (Clarabel form ``A·x + s = b``, ``s`` in a cone):

- arena         ``lo ≤ p_k ≤ hi``                                   (non-negative cone)
- gate          ``g_{k,j}·p_k ≤ b_{k,j}``, up to four per waypoint  (non-negative cone)
- frame         up to four more per waypoint: other gates' frames  (non-negative cone)
- collision     ``β_{k,o}·p_k ≤ b_{k,o}``, one per other player     (non-negative cone)
- guard         the same against drones flown by another planner, extrapolated at constant velocity
- speed         ``‖p_k − p_{k−1}‖ ≤ max(v_max, ‖v_0‖ − k·a_max·Δt)·Δt`` (second-order cones)
- acceleration  ``‖p_k − 2p_{k−1} + p_{k−2}‖ ≤ a_max·Δt²``          (second-order cones)

The objective is ``½xᵀPx + qᵀx``: P is the smoothness term ``smooth·Σ‖a_k‖²·Δt`` and q is supplied per solve
(progress and sensitivity terms) plus the smoothness term's linear part.

Fallback: when the hard problem is not solved (infeasible, or the solver stops early), the same problem is solved
with a non-negative slack on every arena, gate and collision row and on every speed cone, each penalised linearly
by ``soft_penalty`` times a weight per kind (an exact penalty: where a feasible point exists the soft problem
returns it). Acceleration
cones stay hard; a constant-velocity plan satisfies them, so the fallback always has a solution.
"""

from __future__ import annotations

from dataclasses import dataclass

import clarabel
import numpy as np
import scipy.sparse as sp

__all__ = ["BestResponseQP", "RowData", "Solution"]

_SOLVED = ("Solved", "AlmostSolved")
_SLACK_WEIGHT = {"geometry": 5.0, "separation": 2.0, "speed": 1.0}
"""Fallback penalty per metre of slack, relative to ``soft_penalty``: violating the arena or a gate opening costs
most (the margin to a crash is a few cm), the drone separation less (its margin is larger), the speed bound least."""


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


@dataclass
class Solution:
    """A best response."""

    plan: np.ndarray
    """Waypoints p_1 … p_N (N, 3)."""
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


def _triplets(mat: sp.spmatrix, row0: int = 0, col0: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    coo = sp.coo_matrix(mat)
    return coo.row + row0, coo.col + col0, coo.data


class BestResponseQP:
    """Builds and solves one player's best response (a new Clarabel instance per solve: setup is ~0.1 ms)."""

    def __init__(self, *, steps: int, others: int, dt: float, v_max: float, a_max: float, smooth: float,
                 lo: np.ndarray, hi: np.ndarray, soft_penalty: float = 1e3, tol: float = 1e-7) -> None:
        self.N, self.O, self.dt = steps, others, dt
        self.v_max, self.a_max = v_max, a_max
        self.lo, self.hi = np.asarray(lo, float), np.asarray(hi, float)
        self.soft_penalty = soft_penalty
        self.settings = clarabel.DefaultSettings()
        self.settings.verbose = False
        self.settings.presolve_enable = False
        for name in ("tol_gap_abs", "tol_gap_rel", "tol_feas"):
            setattr(self.settings, name, tol)
        N, n = steps, 3 * steps
        self.smooth_c = smooth / dt**3
        d2 = sp.diags([np.ones(N), -2.0 * np.ones(N - 1), np.ones(N - 2)], [0, -1, -2], shape=(N, N))
        self.D2 = sp.kron(d2, sp.eye(3)).tocsr()
        self.P = sp.triu(2.0 * self.smooth_c * (self.D2.T @ self.D2)).tocsc()
        d1 = sp.kron(sp.diags([np.ones(N), -np.ones(N - 1)], [0, -1], shape=(N, N)), sp.eye(3)).tocsr()
        # Cone rows of waypoint k: [t, v] with t = bound, v = −A x + b; rows 4k .. 4k+3 in each cone block.
        soc_rows = (4 * np.arange(N)[:, None] + 1 + np.arange(3)).ravel()
        sel = sp.csr_matrix((np.ones(n), (soc_rows, np.arange(n))), shape=(4 * N, n))
        self.soc = sp.vstack([-sel @ d1, -sel @ self.D2]).tocoo()
        self.box = sp.vstack([sp.eye(n), -sp.eye(n)]).tocoo()
        self.box_b = np.concatenate([np.tile(self.hi, N), -np.tile(self.lo, N)])
        self.cones_soc = [clarabel.SecondOrderConeT(4)] * (2 * N)

    # Assembly

    def _linear(self, d: RowData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Smoothness constant e (the second differences' fixed part is −e), speed constant c1, and q."""
        p0, pm1 = d.p0, d.p0 - d.v0 * self.dt
        e = np.zeros(3 * self.N)
        e[0:3] = 2.0 * p0 - pm1
        e[3:6] = -p0
        c1 = np.zeros(3 * self.N)
        c1[0:3] = -p0
        q = -2.0 * self.smooth_c * (self.D2.T @ e) + d.q.ravel()
        return e, c1, q

    def _rows(self, d: RowData) -> tuple[tuple[np.ndarray, ...], np.ndarray, np.ndarray, np.ndarray]:
        """Non-negative-cone rows (triplets and bounds) and the positions of the active collision rows."""
        gb, cb = d.gate_b.ravel(), d.coll_b.ravel()
        ub = d.guard_b.ravel() if d.guard_b is not None else np.zeros(0)
        ua = d.guard_a.reshape(-1, 3) if d.guard_a is not None else np.zeros((0, 3))
        fb = d.frame_b.ravel() if d.frame_b is not None else np.zeros(0)
        fa = d.frame_a.reshape(-1, 3) if d.frame_a is not None else np.zeros((0, 3))
        g_act, c_act, u_act, f_act = (np.nonzero(np.isfinite(x) & (x < 1e20))[0] for x in (gb, cb, ub, fb))
        n_box = self.box.shape[0]
        coef = np.concatenate([d.gate_a.reshape(-1, 3)[g_act], fa[f_act], d.coll_a.reshape(-1, 3)[c_act], ua[u_act]])
        wp = np.concatenate([g_act // 4, f_act // 4, c_act // self.O, u_act // self.O])
        r = n_box + np.repeat(np.arange(len(wp)), 3)
        c = (3 * wp[:, None] + np.arange(3)).ravel()
        rows = np.concatenate([self.box.row, r])
        cols = np.concatenate([self.box.col, c])
        vals = np.concatenate([self.box.data, coef.ravel()])
        b = np.concatenate([self.box_b, gb[g_act], fb[f_act], cb[c_act], ub[u_act]])
        w = _SLACK_WEIGHT
        n_geo, n_sep = n_box + len(g_act) + len(f_act), len(c_act) + len(u_act)
        weight = np.concatenate([np.full(n_geo, w["geometry"]), np.full(n_sep, w["separation"])])
        self._weight = weight
        return (rows, cols, vals), b, c_act, n_box + len(g_act) + len(f_act) + np.arange(len(c_act))

    def solve(self, d: RowData) -> Solution:
        """Best response for ``d``: the hard problem, or the soft fallback when that is not solved."""
        e, c1, q = self._linear(d)
        (rows, cols, vals), b_lin, c_act, c_rows = self._rows(d)
        m = len(b_lin)
        n = 3 * self.N
        soc_b = np.zeros(8 * self.N)
        # A drone already faster than v_max may slow down at a_max: step k's bound is never below that.
        steps = np.arange(1, self.N + 1)
        soc_b[0:4 * self.N:4] = np.maximum(self.v_max * self.dt, np.linalg.norm(d.v0) * self.dt
                                           - steps * self.a_max * self.dt**2)
        soc_b[4 * self.N::4] = self.a_max * self.dt**2
        sv = soc_b[:4 * self.N].reshape(self.N, 4)
        sv[:, 1:] = c1.reshape(self.N, 3)
        sa = soc_b[4 * self.N:].reshape(self.N, 4)
        sa[:, 1:] = -e.reshape(self.N, 3)
        trip = (np.concatenate([rows, self.soc.row + m]), np.concatenate([cols, self.soc.col]),
                np.concatenate([vals, self.soc.data]))
        A = sp.csc_matrix((trip[2], (trip[0], trip[1])), shape=(m + 8 * self.N, n))
        b = np.concatenate([b_lin, soc_b])
        cones = [clarabel.NonnegativeConeT(m), *self.cones_soc]
        sol = clarabel.DefaultSolver(self.P, q, A, b, cones, self.settings).solve()
        iters = int(sol.iterations)
        if str(sol.status) in _SOLVED:
            return self._solution(sol.x, sol.z, c_act, c_rows, str(sol.status), soft=False, iterations=iters)
        soft = self._solve_soft(q, trip, b, m)
        x = np.asarray(soft.x)[:n]
        if str(soft.status) not in _SOLVED or not np.all(np.isfinite(x)):
            x = np.tile(d.p0, self.N)  # never hand NaN to the controller: hold the current position
        return self._solution(x, np.nan_to_num(np.asarray(soft.z)), c_act, c_rows, str(soft.status), soft=True,
                              iterations=iters + int(soft.iterations))

    def _solve_soft(self, q: np.ndarray, trip: tuple[np.ndarray, ...], b: np.ndarray, m: int):
        """Slack s ≥ 0 on the m linear rows and the N speed cones, cost soft_penalty·Σ weight·s (exact penalty)."""
        n, N = 3 * self.N, self.N
        ns, rows_hard = m + N, m + 8 * N
        slack = n + np.arange(ns)
        # Slack σ enters each linear row as a·x − σ ≤ b, each speed cone's bound as t = v_max·Δt + σ, and σ ≥ 0.
        r = np.concatenate([trip[0], np.arange(m), m + 4 * np.arange(N), rows_hard + np.arange(ns)])
        c = np.concatenate([trip[1], slack, slack])
        v = np.concatenate([trip[2], -np.ones(2 * ns)])
        A = sp.csc_matrix((v, (r, c)), shape=(rows_hard + ns, n + ns))
        P = sp.csc_matrix((self.P.data, self.P.indices, np.concatenate([self.P.indptr, np.full(ns, self.P.nnz)])),
                          shape=(n + ns, n + ns))
        weight = np.concatenate([self._weight, np.full(N, _SLACK_WEIGHT["speed"])])
        q_soft = np.concatenate([q, self.soft_penalty * weight])
        cones = [clarabel.NonnegativeConeT(m), *self.cones_soc, clarabel.NonnegativeConeT(ns)]
        return clarabel.DefaultSolver(P, q_soft, A, np.concatenate([b, np.zeros(ns)]), cones, self.settings).solve()

    def _solution(self, x, z, c_act: np.ndarray, c_rows: np.ndarray, status: str, *, soft: bool,
                  iterations: int) -> Solution:
        raw = np.zeros(self.N * self.O)
        raw[c_act] = np.asarray(z, float)[c_rows]
        raw = raw.reshape(self.N, self.O)
        return Solution(plan=np.asarray(x, float)[: 3 * self.N].reshape(self.N, 3).copy(),
                        coll_dual=np.maximum(raw, 0.0), raw_coll_dual=raw, status=status, soft=soft,
                        iterations=iterations)
