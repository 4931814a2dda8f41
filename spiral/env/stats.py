"""Statistics of ended learner episodes: sums a race env keeps on its device, and the means training logs.

The sums stay on the env's device as it steps (no value is read on the host per step); training reads them once per
iteration.
"""

from __future__ import annotations

import torch

from spiral.env.records import RaceRecords
from spiral.env.rewards import REWARD_TERMS
from spiral.sim import COLLISION_KINDS

__all__ = ["EpisodeStats", "add_ended_episodes", "empty_stats", "read_stats", "summarize_stats"]


class EpisodeStats:
    """The sums of a race env's ended learner episodes, on its device."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.sums = empty_stats(device)

    def add(self, ended: torch.Tensor, records: RaceRecords, rows: torch.Tensor) -> None:
        """Add the episodes of the drones ``rows`` of ``records`` that end where ``ended`` (a bool mask over
        ``rows``)."""
        add_ended_episodes(self.sums, ended, finished=records.finished.index_select(0, rows),
                           lap_time=records.lap_time.index_select(0, rows),
                           crash_kind=records.crash_kind.index_select(0, rows),
                           term_sums={k: v.index_select(0, rows) for k, v in records.term_sums.items()})

    def take(self) -> dict[str, float]:
        """The sums since the last call, read from the device; counting restarts."""
        s, self.sums = self.sums, empty_stats(self.device)
        return read_stats(s)

    def pop(self) -> dict[str, float]:
        """Means over the episodes ended since the last call (:func:`summarize_stats`); counting restarts."""
        return summarize_stats(self.take())


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
