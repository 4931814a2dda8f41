"""Pure functions over race results: success ratios with Wilson intervals, lap statistics, crash counts."""

from __future__ import annotations

import math
from typing import Any

import torch

from spiral.env.racing import RaceResults
from spiral.sim import COLLISION_KINDS

__all__ = ["lap_statistics", "summarize_races", "wilson_interval"]


def wilson_interval(successes: int, trials: int, *, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95% by default); (0, 1) for no trials."""
    if trials == 0:
        return 0.0, 1.0
    p = successes / trials
    denom = 1.0 + z * z / trials
    center = (p + z * z / (2 * trials)) / denom
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / denom
    return max(0.0, center - half), min(1.0, center + half)


def lap_statistics(lap_times: torch.Tensor, finished: torch.Tensor) -> tuple[float | None, float | None]:
    """Mean and standard deviation (population) of the lap times of finished drones only; None when none."""
    laps = lap_times[finished.bool()].double()
    if laps.numel() == 0:
        return None, None
    return float(laps.mean()), float(laps.std(unbiased=False))


def summarize_races(res: RaceResults, slots: list[int] | None = None) -> dict[str, Any]:
    """Metrics of the drones in ``slots`` (all present drones when None) over every race."""
    mask = res.present.clone()
    if slots is not None:
        keep = torch.zeros_like(mask)
        keep[:, slots] = True
        mask &= keep
    finished = res.finished[mask]
    n, k = int(mask.sum()), int(finished.sum())
    mean, std = lap_statistics(res.lap_time[mask], finished)
    kinds = res.crash_kind[mask]
    crashes = {kind: int(((kinds & bit) != 0).sum()) for kind, bit in COLLISION_KINDS.items()}
    crashes["timeout"] = int((~res.finished[mask] & ~res.crashed[mask]).sum())
    speed = res.distance[mask][finished] / res.lap_time[mask][finished]
    return {
        "drones": n,
        "success_ratio": k / n if n else 0.0,
        "success_ci95": list(wilson_interval(k, n)),
        "lap_time_mean": mean,
        "lap_time_std": std,
        "mean_speed": float(speed.mean()) if speed.numel() else None,
        "crashes": crashes,
    }
