"""Statistics of ended learner episodes: sums a race env keeps, and the means training logs."""

from __future__ import annotations

import torch

from spiral.env.rewards import REWARD_TERMS
from spiral.sim import COLLISION_KINDS

__all__ = ["empty_stats", "log_episodes", "summarize_stats"]


def empty_stats() -> dict[str, float]:
    """Zero sums: episodes, successes, laps and their times, non-finite resets, crashes by kind, reward terms."""
    stats = {"episodes": 0.0, "successes": 0.0, "lap_time_sum": 0.0, "laps": 0.0, "nonfinite_resets": 0.0}
    stats.update({f"crash_{kind}": 0.0 for kind in COLLISION_KINDS})
    stats.update({f"term_{name}": 0.0 for name in REWARD_TERMS})
    return stats


def log_episodes(stats: dict[str, float], *, finished: torch.Tensor, crashed: torch.Tensor, lap_time: torch.Tensor,
                 crash_kind: torch.Tensor, term_sums: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Add the ended episodes (one row per drone of each argument) to ``stats``; return their means for rsl-rl's
    log."""
    s = stats
    s["episodes"] += finished.numel()
    s["successes"] += float(finished.sum())
    s["laps"] += float(finished.sum())
    s["lap_time_sum"] += float(lap_time[finished].sum())
    for kind, bit in COLLISION_KINDS.items():
        s[f"crash_{kind}"] += float(((crash_kind & bit) != 0).sum())
    log = {f"Episode_Reward/{name}": term_sums[name].mean() for name in REWARD_TERMS}
    for name in REWARD_TERMS:
        s[f"term_{name}"] += float(term_sums[name].sum())
    log["Episode/success"] = finished.float().mean()
    log["Episode/crash"] = crashed.float().mean()
    return log


def summarize_stats(s: dict[str, float]) -> dict[str, float]:
    """Means per ended learner episode from sums of :func:`log_episodes` (sums of several envs add)."""
    n = max(s["episodes"], 1.0)
    out = {"episodes": s["episodes"], "success": s["successes"] / n,
           "lap_time": s["lap_time_sum"] / s["laps"] if s["laps"] else float("nan"),
           "health/nonfinite_resets": s["nonfinite_resets"]}
    out.update({f"crash/{k}": s[f"crash_{k}"] / n for k in COLLISION_KINDS})
    out.update({f"Episode_Reward/{k}": s[f"term_{k}"] / n for k in REWARD_TERMS})
    return out
