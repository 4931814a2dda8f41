"""Lap-time reference: the minimum-time lap of a point mass with the airframe's acceleration limits.

The point mass starts at rest in the centre of the start box and passes every gate opening in racing order, then
gate 0 again (``laps`` times round, as a race ends). Its acceleration is what the airframe's thrust can give under
the controller's tilt limit: thrust acceleration ``f`` with ``‖f‖ ≤ f_max`` (thrust-to-weight times g, capped by
the PID's ``max_accel``) and tilt from the vertical at most ``max_tilt_deg``, net acceleration ``a = f − g·ẑ``.
Drag, attitude dynamics and motor limits other than total thrust are left out, so the reference is optimistic.

Method (direct transcription, one SOCP per step allocation): time is cut into N equal steps h, acceleration is
constant within a step (the nodes are exact samples of a continuous flight). With ``q = h·v`` and ``τ = h²`` the
dynamics ``p⁺ = p + (q + q⁺)/2`` are linear and the thrust set becomes two second-order cones linear in
``(q⁺ − q, τ)``, so for a fixed number of steps per gate-to-gate segment, minimising ``τ`` (hence the lap time
``N·√τ``) is a convex problem solved exactly by Clarabel. Each segment ends at a node that lies in its gate's
plane, inside the opening shrunk by the drone radius, moving forwards; every node stays in the arena shrunk by
the radius. The steps per segment are then chosen by a local search (move one step from one segment to another
while the lap gets faster), coarse to fine. Details and measurements: ``docs/evaluation.md``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Literal

import clarabel
import numpy as np
import scipy.sparse as sp

from spiral.config.airframe import AirframeCfg
from spiral.config.generate import TrackGenCfg, generate_track
from spiral.config.track import TrackSpec
from spiral.core.errors import UsageError

__all__ = ["AccelLimits", "LapBound", "format_bound", "generate_flyable_track", "lap_time_bound"]

Model = Literal["thrust", "ball"]
"""Acceleration set: ``thrust`` (thrust ball ∩ tilt cone − g) or ``ball`` (‖a‖ ≤ level-flight maximum)."""

_SOLVED = ("Solved", "AlmostSolved")


@dataclass(frozen=True)
class AccelLimits:
    """Acceleration limits of an airframe flown through the cascaded PID."""

    thrust: float
    """Largest thrust acceleration f_max = min(thrust_to_weight·g, pid.max_accel) [m/s²]."""
    tilt_deg: float
    """Largest tilt of the thrust from the vertical [deg]."""
    gravity: float
    """Gravitational acceleration [m/s²]."""

    @classmethod
    def from_airframe(cls, airframe: AirframeCfg, *, gravity: float = 9.81) -> AccelLimits:
        """Limits of ``airframe``: its thrust-to-weight ratio and its controller's tilt and acceleration caps."""
        thrust = min(airframe.thrust_to_weight * gravity, airframe.pid.max_accel)
        return cls(thrust=thrust, tilt_deg=airframe.pid.max_tilt_deg, gravity=gravity)

    @property
    def level(self) -> float:
        """Largest horizontal acceleration at constant height: min(g·tan θ, √(f_max² − g²)) [m/s²]."""
        g = self.gravity
        return min(g * math.tan(math.radians(self.tilt_deg)), math.sqrt(max(self.thrust**2 - g * g, 0.0)))

    @property
    def up(self) -> float:
        """Largest upward acceleration f_max − g [m/s²]."""
        return self.thrust - self.gravity

    def to_json(self) -> dict[str, float]:
        """The limits and the derived accelerations."""
        return {"thrust": self.thrust, "tilt_deg": self.tilt_deg, "gravity": self.gravity, "a_max_level": self.level,
                "a_max_up": self.up, "a_max_down": self.gravity}


@dataclass
class LapBound:
    """A minimum-time point-mass race and how it was found."""

    track: str
    airframe: str
    model: str
    limits: AccelLimits
    lap_time: float
    """Time of the final crossing of gate 0 [s]."""
    gate_sequence: list[int]
    """Gates in the order they are passed."""
    pass_times: list[float]
    """Time of each gate pass [s]."""
    steps: list[int]
    """Time steps per segment (start → first gate, then gate to gate)."""
    step_time: float
    """Length h of one time step [s]."""
    positions: np.ndarray
    """Node positions (N + 1, 3) [m]."""
    velocities: np.ndarray
    """Node velocities (N + 1, 3) [m/s]."""
    solves: int = 0
    """SOCPs solved in the allocation search."""
    solve_s: float = 0.0
    """Wall time of the search [s]."""
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def path_length(self) -> float:
        """Length of the flown path (piecewise parabolas, sampled 8 times per step) [m]."""
        p, v = self.positions, self.velocities
        a = np.diff(v, axis=0) / self.step_time
        s = np.linspace(0.0, self.step_time, 9)[:, None, None]
        pts = p[None, :-1] + v[None, :-1] * s + 0.5 * a[None] * s * s
        return float(np.linalg.norm(np.diff(pts, axis=0), axis=-1).sum())

    def to_json(self, *, trajectory: bool = False) -> dict[str, Any]:
        """JSON-ready summary; ``trajectory`` adds the node positions and velocities."""
        speed = np.linalg.norm(self.velocities, axis=1)
        out: dict[str, Any] = {
            "track": self.track, "airframe": self.airframe, "model": self.model, "lap_time": self.lap_time,
            "limits": self.limits.to_json(), "gate_sequence": self.gate_sequence, "pass_times": self.pass_times,
            "steps": self.steps, "step_time": self.step_time, "path_length": self.path_length,
            "mean_speed": self.path_length / self.lap_time, "max_speed": float(speed.max()),
            "solves": self.solves, "solve_s": self.solve_s,
        }
        if trajectory:
            out["positions"] = self.positions.tolist()
            out["velocities"] = self.velocities.tolist()
        return out


@dataclass
class _Course:
    """Start point, gate frames in passing order and the arena, shrunk by the drone radius."""

    start: np.ndarray
    centre: np.ndarray
    forward: np.ndarray
    axis_y: np.ndarray
    axis_z: np.ndarray
    half: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    @classmethod
    def of(cls, track: TrackSpec, radius: float) -> tuple[_Course, list[int]]:
        seq = list(range(len(track.gates))) * track.laps + [0]
        rot, fwd = track.gate_rotations(), track.gate_forward()
        half = np.array([track.gate_opening(i) / 2 - radius for i in seq])
        if (half <= 0).any():
            raise UsageError(f"track {track.name!r}: a gate opening is narrower than the drone")
        course = cls(start=np.asarray(track.start.center, float), centre=track.gate_centers()[seq], forward=fwd[seq],
                     axis_y=rot[seq, :, 1], axis_z=rot[seq, :, 2], half=half,
                     lo=np.asarray(track.bounds.min, float) + radius, hi=np.asarray(track.bounds.max, float) - radius)
        return course, seq

    def lengths(self) -> np.ndarray:
        """Straight-line length of each segment [m]."""
        pts = np.concatenate([self.start[None], self.centre])
        return np.linalg.norm(np.diff(pts, axis=0), axis=1)


class _Transcription:
    """The SOCP of one step allocation: variables [P (N+1)·3, Q (N+1)·3, u] with τ = τ_ref·u."""

    def __init__(self, course: _Course, limits: AccelLimits, model: Model, tau_ref: float) -> None:
        self.course, self.limits, self.model, self.tau_ref = course, limits, model, tau_ref
        self.settings = clarabel.DefaultSettings()
        self.settings.verbose = False
        for name in ("tol_gap_abs", "tol_gap_rel", "tol_feas"):
            setattr(self.settings, name, 1e-9)

    def solve(self, steps: np.ndarray) -> tuple[float, np.ndarray | None]:
        """Minimum lap time and solution vector for ``steps`` per segment (inf, None when not solved)."""
        n_nodes = int(steps.sum()) + 1
        rows = _ConstraintRows()
        self._equalities(rows, steps, n_nodes)
        n_eq = rows.count
        self._inequalities(rows, steps, n_nodes)
        n_ineq = rows.count - n_eq
        cones = self._cones(rows, n_nodes)
        n_var = 6 * n_nodes + 1
        A, b = rows.matrix(n_var)
        q = np.zeros(n_var)
        q[-1] = 1.0
        solver = clarabel.DefaultSolver(sp.csc_matrix((n_var, n_var)), q, A, b,
                                        [clarabel.ZeroConeT(n_eq), clarabel.NonnegativeConeT(n_ineq), *cones],
                                        self.settings)
        sol = solver.solve()
        if str(sol.status) not in _SOLVED:
            return math.inf, None
        x = np.asarray(sol.x)
        return (n_nodes - 1) * math.sqrt(max(x[-1], 0.0) * self.tau_ref), x

    def _equalities(self, rows: _ConstraintRows, steps: np.ndarray, n_nodes: int) -> None:
        c, qo = self.course, 3 * n_nodes
        for i in range(3):
            rows.add({i: 1.0}, c.start[i])
            rows.add({qo + i: 1.0}, 0.0)  # at rest
        for k in range(n_nodes - 1):  # p⁺ − p − (q + q⁺)/2 = 0
            for i in range(3):
                rows.add({3 * (k + 1) + i: 1.0, 3 * k + i: -1.0, qo + 3 * k + i: -0.5, qo + 3 * (k + 1) + i: -0.5}, 0.0)
        for j, k in enumerate(np.cumsum(steps)):
            rows.add({3 * k + i: c.forward[j, i] for i in range(3)}, float(c.forward[j] @ c.centre[j]))

    def _inequalities(self, rows: _ConstraintRows, steps: np.ndarray, n_nodes: int) -> None:
        c, qo = self.course, 3 * n_nodes
        for j, k in enumerate(np.cumsum(steps)):
            for axis in (c.axis_y[j], c.axis_z[j]):
                for sign in (1.0, -1.0):  # |axis·(p − c)| ≤ half
                    rhs = sign * float(axis @ c.centre[j]) + c.half[j]
                    rows.add({3 * k + i: sign * axis[i] for i in range(3)}, rhs)
            rows.add({qo + 3 * k + i: -c.forward[j, i] for i in range(3)}, 0.0)  # crossing forwards
        for k in range(1, n_nodes):
            for i in range(3):
                rows.add({3 * k + i: 1.0}, c.hi[i])
                rows.add({3 * k + i: -1.0}, -c.lo[i])

    def _cones(self, rows: _ConstraintRows, n_nodes: int) -> list[Any]:
        """Per step: s = [bound; Δq + τ·g·ẑ] (thrust) and its tilt cone, or s = [τ·a; Δq] (ball)."""
        lim, qo, u, tr = self.limits, 3 * n_nodes, 6 * n_nodes, self.tau_ref
        g = lim.gravity if self.model == "thrust" else 0.0
        bound = lim.thrust if self.model == "thrust" else lim.level
        cos_tilt = math.cos(math.radians(lim.tilt_deg))
        cones = []
        for k in range(n_nodes - 1):
            lo, hi = qo + 3 * k, qo + 3 * (k + 1)

            def vector(rows: _ConstraintRows = rows, lo: int = lo, hi: int = hi) -> None:
                for i in range(3):
                    rows.add({hi + i: -1.0, lo + i: 1.0, **({u: -g * tr} if i == 2 and g else {})}, 0.0)

            rows.add({u: -bound * tr}, 0.0)
            vector()
            cones.append(clarabel.SecondOrderConeT(4))
            if self.model == "thrust":
                rows.add({hi + 2: -1.0 / cos_tilt, lo + 2: 1.0 / cos_tilt, u: -g * tr / cos_tilt}, 0.0)
                vector()
                cones.append(clarabel.SecondOrderConeT(4))
        return cones


class _ConstraintRows:
    """Constraint rows ``A x + s = b`` collected as triplets."""

    def __init__(self) -> None:
        self.r: list[int] = []
        self.c: list[int] = []
        self.v: list[float] = []
        self.b: list[float] = []

    @property
    def count(self) -> int:
        return len(self.b)

    def add(self, coef: dict[int, float], rhs: float) -> None:
        row = len(self.b)
        for col, val in coef.items():
            self.r.append(row)
            self.c.append(col)
            self.v.append(val)
        self.b.append(rhs)

    def matrix(self, n_var: int) -> tuple[sp.csc_matrix, np.ndarray]:
        return sp.csc_matrix((self.v, (self.r, self.c)), shape=(len(self.b), n_var)), np.asarray(self.b)


def lap_time_bound(track: TrackSpec, airframe: AirframeCfg, *, model: Model = "thrust",
                   steps_per_segment: int = 24, gravity: float = 9.81) -> LapBound:
    """Minimum-time race of a point mass through ``track`` with ``airframe``'s acceleration limits.

    Args:
        track: Track whose gates are passed in order, ``laps`` times round, then gate 0 again.
        airframe: Airframe giving thrust-to-weight, tilt and acceleration caps, and the radius that shrinks
            gate openings and the arena.
        model: ``thrust`` (the achievable set) or ``ball`` (‖a‖ ≤ the level-flight maximum in every direction).
        steps_per_segment: Mean time steps per segment at the finest level of the search.
        gravity: Gravitational acceleration [m/s²].

    Returns:
        The lap, its pass times, the node trajectory and search statistics.
    """
    t0 = time.perf_counter()
    limits = AccelLimits.from_airframe(airframe, gravity=gravity)
    course, seq = _Course.of(track, airframe.radius)
    lengths = course.lengths()
    guess = lengths.sum() / (0.5 * math.sqrt(limits.level * lengths.sum()))  # ~ a rest-to-rest sprint
    cache: dict[tuple[int, ...], tuple[float, np.ndarray | None]] = {}
    steps = np.maximum(2, np.round(lengths / lengths.sum() * 4 * len(lengths))).astype(int)
    level_totals = _levels(len(lengths), steps_per_segment)
    for total in level_totals:
        steps = _rescale(steps, total)
        problem = _Transcription(course, limits, model, (guess / total) ** 2)
        steps = _local_search(problem, steps, cache)
    lap, x = cache[tuple(steps)]
    if x is None:
        raise UsageError(f"track {track.name!r}: no feasible point-mass lap found")
    n_nodes = int(steps.sum()) + 1
    h = lap / (n_nodes - 1)
    pos = x[: 3 * n_nodes].reshape(n_nodes, 3)
    vel = x[3 * n_nodes: 6 * n_nodes].reshape(n_nodes, 3) / h
    return LapBound(track=track.name, airframe=airframe.name, model=model, limits=limits, lap_time=lap,
                    gate_sequence=seq, pass_times=[float(k * h) for k in np.cumsum(steps)],
                    steps=[int(s) for s in steps], step_time=h, positions=pos, velocities=vel, solves=len(cache),
                    solve_s=time.perf_counter() - t0)


def _levels(segments: int, finest: int) -> list[int]:
    """Total step counts of the coarse-to-fine search: 4, 8, 16, … steps per segment up to ``finest``."""
    per, out = 4, []
    while per < finest:
        out.append(per * segments)
        per *= 2
    return [*out, finest * segments]


def _rescale(steps: np.ndarray, total: int) -> np.ndarray:
    """Scale an allocation to ``total`` steps, keeping proportions (largest remainders), at least 2 each."""
    raw = steps / steps.sum() * total
    out = np.maximum(2, np.floor(raw).astype(int))
    order = np.argsort(-(raw - np.floor(raw)))
    i = 0
    while out.sum() < total:
        out[order[i % len(out)]] += 1
        i += 1
    while out.sum() > total:
        j = int(np.argmax(out))
        out[j] -= 1
    return out


def _local_search(problem: _Transcription, steps: np.ndarray,
                  cache: dict[tuple[int, ...], tuple[float, np.ndarray | None]]) -> np.ndarray:
    """Move single steps between segments while the lap gets faster (best improvement first)."""

    def lap(s: np.ndarray) -> float:
        key = tuple(int(v) for v in s)
        if key not in cache:
            cache[key] = problem.solve(s)
        return cache[key][0]

    best = lap(steps)
    while True:
        moves = []
        for i in range(len(steps)):
            if steps[i] <= 2:
                continue
            for j in range(len(steps)):
                if i != j:
                    cand = steps.copy()
                    cand[i] -= 1
                    cand[j] += 1
                    moves.append((lap(cand), cand))
        if not moves:
            return steps
        value, cand = min(moves, key=lambda m: m[0])
        if value >= best - 1e-9:
            return steps
        best, steps = value, cand


def format_bound(bound: LapBound) -> str:
    """A few lines of text: the lap time, the limits it assumed and the gate pass times."""
    lim, info = bound.limits, bound.to_json()
    passes = ", ".join(f"{g}@{t:.2f}" for g, t in zip(bound.gate_sequence, bound.pass_times, strict=True))
    return "\n".join([
        f"{bound.track} ({bound.airframe}, {bound.model} model): point-mass minimum lap time {bound.lap_time:.3f} s",
        f"  limits: thrust <= {lim.thrust:.2f} m/s^2, tilt <= {lim.tilt_deg:.0f} deg -> a_max {lim.level:.2f} m/s^2 "
        f"level, {lim.up:.2f} up, {lim.gravity:.2f} down",
        f"  path {info['path_length']:.2f} m, mean speed {info['mean_speed']:.2f} m/s, top speed "
        f"{info['max_speed']:.2f} m/s",
        f"  gate passes (gate@s): {passes}",
        f"  {sum(bound.steps)} steps of {bound.step_time * 1e3:.1f} ms, {bound.solves} SOCPs in {bound.solve_s:.1f} s",
    ])


def generate_flyable_track(cfg: TrackGenCfg, seed: int, airframe: AirframeCfg, *,
                           name: str | None = None) -> tuple[TrackSpec, float]:
    """The track the generator draws for ``seed`` that the point-mass reference (coarse: 4 steps per segment) laps
    within its time limit, and that reference lap [s]: the generator keeps the first candidate of its stream this
    accepts (:func:`~spiral.config.generate.generate_track`)."""
    reference: dict[str, float] = {}

    def flyable(track: TrackSpec) -> bool:
        try:
            reference["lap"] = lap_time_bound(track, airframe, steps_per_segment=4).lap_time
        except UsageError:  # no feasible point-mass lap
            return False
        return reference["lap"] * track.laps <= track.time_limit_s

    track = generate_track(cfg, seed, name=name, accept=flyable)
    return track, reference["lap"]
