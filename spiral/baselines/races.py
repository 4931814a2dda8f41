"""Seeded SE-IBR races: self-matches and head-to-head duels, with the statistics ``docs/se_ibr.md`` reports.

Library functions return :class:`~spiral.env.RaceResults`; the command line that runs and summarises them is
``python -m spiral.eval.se_ibr_races`` (evaluation's metrics sit above the baselines).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from spiral.baselines.centreline import Centreline
from spiral.baselines.se_ibr import PlannerPolicy, opponent_policy, se_ibr_policy
from spiral.config import AIRFRAMES, EnvCfg, SimCfg, TrackSpec
from spiral.config.env import EVAL_REWARD
from spiral.core.outcome import race_winner
from spiral.env import RaceEnv, RaceResults, RaceSetting, run_races

__all__ = ["duel_statistics", "head_to_head", "paired_duel", "race_progress", "self_match", "winners"]


def _env(track: TrackSpec, drones: int, runs: int, seed: int, learners: list[int]) -> RaceEnv:
    return RaceEnv(RaceSetting(track, AIRFRAMES["cf2x"], SimCfg()), EnvCfg(reward=EVAL_REWARD), world_count=runs,
                   drones_per_world=drones, learner_slots=learners, seed=seed, training=False)


def self_match(track: TrackSpec, drones: int, *, runs: int = 50, seed: int = 0, **kw: Any
               ) -> tuple[RaceResults, PlannerPolicy]:
    """``runs`` seeded races in which one SE-IBR planner (``kw``: SEIBRCfg fields) flies every drone."""
    env = _env(track, drones, runs, seed, list(range(drones)))
    policy = se_ibr_policy(env, **kw)
    return run_races(env, policy, record=True), policy


def head_to_head(track: TrackSpec, *, learner: dict[str, Any], opponent: dict[str, Any], runs: int = 50,
                 seed: int = 0) -> tuple[RaceResults, PlannerPolicy, PlannerPolicy]:
    """1v1 races: slot 0 flown by a planner with ``learner`` settings, slot 1 by one with ``opponent`` settings."""
    env = _env(track, 2, runs, seed, [0])
    opp = opponent_policy(env, **opponent)
    env.set_opponent_policy(opp)
    policy = se_ibr_policy(env, **learner)
    return run_races(env, policy, record=True), policy, opp


def race_progress(track: TrackSpec, traj: torch.Tensor) -> np.ndarray:
    """Progress along the track [m] of every drone at every recorded step, shape (T, W, D).

    Gates passed (replayed from the trajectory with the simulator's crossing rule, on the centre points)
    times the lap length over the gate count, plus the arc length of the projection onto the reference line
    inside the next gate's window. Frozen drones keep their last value.
    """
    line = Centreline(track)
    p = traj.numpy().astype(float)
    T, W, D, _ = p.shape
    flat = p.reshape(T, W * D, 3)
    nxt = np.zeros(W * D, dtype=np.int64)
    passed = np.zeros(W * D)
    out = np.zeros((T, W * D))
    half = line.half_opening
    per_gate = line.length / line.gate_count
    for t in range(T):
        if t > 0:
            d0, d1 = line.depth(flat[t - 1], nxt), line.depth(flat[t], nxt)
            cross = (d0 < 0) & (d1 >= 0)
            frac = np.where(cross, d0 / np.where(cross, d0 - d1, 1.0), 0.0)[:, None]
            hit = flat[t - 1] + frac * (flat[t] - flat[t - 1]) - line.center[nxt]
            inside = (np.abs((hit * line.axis_y[nxt]).sum(-1)) < half[nxt]) & (
                np.abs((hit * line.axis_z[nxt]).sum(-1)) < half[nxt])
            ok = cross & inside
            passed += ok
            nxt = np.where(ok, (nxt + 1) % line.gate_count, nxt)
        idx = line.project(flat[t], nxt)
        start = line.gate_sample[(nxt - 1) % line.gate_count]
        arc = (line.arc[idx] - line.arc[start]) % line.length
        out[t] = (passed - 1) * per_gate + np.minimum(arc, 1.5 * per_gate)
    return out.reshape(T, W, D)


def duel_statistics(track: TrackSpec, res: RaceResults, *, a: int = 0, b: int = 1, close_m: float = 0.5
                    ) -> dict[str, Any]:
    """Who won each 1v1 race between slots ``a`` and ``b`` and how they raced.

    A win is finishing first (a finisher beats a crashed or timed-out drone; no winner when neither finishes).
    Also: the closest approach of the two drones in each race while both fly, the lap times, how often the lead changed
    (progress order, ignoring swings under 0.1 m), the share of steps with both flying in which ``a`` led, the
    share of those steps the two spent closer than ``close_m``, and who led during them.
    """
    fin, lap = res.finished.numpy(), res.lap_time.numpy()
    runs = fin.shape[0]
    won = winners(res, a=a, b=b)
    a_wins, b_wins = won == a, won == b
    traj = res.trajectory
    assert traj is not None, "duel statistics need recorded trajectories"
    step = (traj[1:] - traj[:-1]).norm(dim=-1).numpy()  # frozen (crashed or finished) drones do not move
    both = np.concatenate([np.ones((1, runs), bool), (step[:, :, a] > 0) & (step[:, :, b] > 0)])
    gap = np.where(both, (traj[:, :, a] - traj[:, :, b]).norm(dim=-1).numpy(), np.inf)  # (T, W), inf unless both fly
    sep = gap.min(axis=0)
    prog = race_progress(track, traj)
    lead = prog[:, :, a] - prog[:, :, b]
    changes = _lead_changes(lead)
    close = both & (gap < close_m)
    lap_a, lap_b = lap[fin[:, a], a], lap[fin[:, b], b]
    return {
        "races": runs, "a_wins": int(a_wins.sum()), "b_wins": int(b_wins.sum()),
        "no_winner": int(runs - a_wins.sum() - b_wins.sum()),
        "a_win_rate": float(a_wins.mean()), "b_win_rate": float(b_wins.mean()),
        "min_separation_median": float(np.median(sep)),
        "min_separation_p10": float(np.percentile(sep, 10)),
        "a_success": float(fin[:, a].mean()), "b_success": float(fin[:, b].mean()),
        "a_lap_mean": float(lap_a.mean()) if lap_a.size else None,
        "b_lap_mean": float(lap_b.mean()) if lap_b.size else None,
        "lead_changes_mean": float(np.mean(changes)),
        "a_ahead_share": float((lead[both] > 0).mean()),
        "close_share": float(close.sum() / max(both.sum(), 1)),
        "a_ahead_when_close": float((lead[close] > 0).mean()) if close.any() else None,
    }


def _lead_changes(lead: np.ndarray) -> list[int]:
    """How often the lead changed in each race, from ``lead`` (T, W), the progress of one drone over the other's:
    changes of its sign, ignoring swings under 0.1 m."""
    sign = np.sign(np.where(np.abs(lead) < 0.1, 0.0, lead))
    changes = []
    for w in range(lead.shape[1]):
        s = sign[:, w][sign[:, w] != 0]
        changes.append(int((s[1:] != s[:-1]).sum()))
    return changes


def winners(res: RaceResults, *, a: int = 0, b: int = 1) -> np.ndarray:
    """Winning slot of each race between slots ``a`` and ``b`` (:func:`~spiral.core.outcome.race_winner`), −1 if
    none."""
    team = race_winner(res.finished, res.lap_time, [[a], [b]]).numpy()
    return np.where(team == 0, a, np.where(team == 1, b, -1))


def paired_duel(res: RaceResults, control: RaceResults, *, slot: int) -> dict[str, Any]:
    """How the drone in ``slot`` of ``res`` did against the same slot of ``control`` over the same start placements.

    Races whose winner changed, how many the slot gained or lost, and the mean lap-time change of each slot over
    the races both runs finished.
    """
    w, wc = winners(res), winners(control)
    fin, finc = res.finished.numpy(), control.finished.numpy()
    lap, lapc = res.lap_time.numpy(), control.lap_time.numpy()
    other = 1 - slot

    def lap_change(s: int) -> float:
        both = fin[:, s] & finc[:, s]
        return float((lap[both, s] - lapc[both, s]).mean()) if both.any() else float("nan")

    return {"races": len(w), "wins": int((w == slot).sum()), "control_wins": int((wc == slot).sum()),
            "winner_changed": int((w != wc).sum()), "gained": int(((w == slot) & (wc != slot)).sum()),
            "lost": int(((w != slot) & (wc == slot)).sum()), "lap_change": lap_change(slot),
            "other_lap_change": lap_change(other)}
