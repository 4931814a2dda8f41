"""Statistics of ended learner episodes: sums a race env keeps on its device, and the means training logs.

The sums stay on the env's device as it steps (no value is read on the host per step); training reads them once per
iteration.
"""

from __future__ import annotations

import torch

from spiral.env.rewards import REWARD_TERMS
from spiral.sim import COLLISION_KINDS

__all__ = ["add_ended_episodes", "empty_stats", "read_stats", "summarize_stats"]


def empty_stats(device: torch.device) -> dict[str, torch.Tensor]:
    """Zero sums on ``device``: episodes, successes, laps and their times, non-finite resets, crashes by kind, reward
    terms."""
    names = ["episodes", "successes", "lap_time_sum", "laps", "nonfinite_resets",
             *(f"crash_{kind}" for kind in COLLISION_KINDS), *(f"term_{name}" for name in REWARD_TERMS)]
    return {name: torch.zeros((), dtype=torch.float64, device=device) for name in names}


def add_ended_episodes(stats: dict[str, torch.Tensor], ended: torch.Tensor, *, finished: torch.Tensor,
                       lap_time: torch.Tensor, crash_kind: torch.Tensor, term_sums: dict[str, torch.Tensor]) -> None:
    """Add to ``stats`` the episodes of the rows where ``ended`` (a bool mask over the rows of every other
    argument): counts and sums by masks, so the number of ended episodes is never read."""
    won = ended & finished
    s = stats
    s["episodes"] += ended.sum()
    s["successes"] += won.sum()
    s["laps"] += won.sum()
    s["lap_time_sum"] += torch.where(won, lap_time, 0.0).sum(dtype=torch.float64)
    for kind, bit in COLLISION_KINDS.items():
        s[f"crash_{kind}"] += (ended & ((crash_kind & bit) != 0)).sum()
    for name in REWARD_TERMS:
        s[f"term_{name}"] += torch.where(ended, term_sums[name], 0.0).sum(dtype=torch.float64)


def read_stats(stats: dict[str, torch.Tensor]) -> dict[str, float]:
    """The sums as numbers, read from the device at once."""
    return dict(zip(stats, torch.stack(list(stats.values())).tolist(), strict=True))


def summarize_stats(s: dict[str, float]) -> dict[str, float]:
    """Means per ended learner episode from sums read by :func:`read_stats` (sums of several envs add)."""
    n = max(s["episodes"], 1.0)
    out = {"episodes": s["episodes"], "success": s["successes"] / n,
           "lap_time": s["lap_time_sum"] / s["laps"] if s["laps"] else float("nan"),
           "health/nonfinite_resets": s["nonfinite_resets"]}
    out.update({f"crash/{k}": s[f"crash_{k}"] / n for k in COLLISION_KINDS})
    out.update({f"Episode_Reward/{k}": s[f"term_{k}"] / n for k in REWARD_TERMS})
    return out
