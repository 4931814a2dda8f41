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
        **_crash_details(res, mask),
        **({"split_times": _split_times(res, mask)} if res.split_time is not None else {}),
    }


def _split_times(res: RaceResults, mask: torch.Tensor) -> list[float] | None:
    """Mean race time at each gate passage of the lap over the ``mask`` drones that finished (None if none did)."""
    done = res.finished & mask
    return res.split_time[done].mean(dim=0).tolist() if done.any() else None


def _crash_details(res: RaceResults, mask: torch.Tensor) -> dict[str, Any]:
    """Where and when the ``mask`` drones crashed, and whom they touched (when the results record it).

    ``crash_gates`` counts crashes by the gate of the lap the drone was flying to (0 = the first gate after the
    start, in passing order); ``drone_contacts`` splits drone–drone crashes by the other drone's team.
    """
    crashed = res.crashed & mask
    gates = res.gates_passed[crashed].tolist()
    out: dict[str, Any] = {"crash_gates": {str(g): gates.count(g) for g in sorted(set(gates))}}
    if res.crash_time is not None:
        times = res.crash_time[crashed]
        out["crash_time_median"] = float(times.median()) if times.numel() else None
    if res.crash_partner is not None and res.team is not None:
        w, d = crashed.shape
        partner = res.crash_partner[crashed]
        own = res.team.expand(w, d)[crashed]
        touched = partner >= 0
        same = res.team[partner.clamp(min=0)] == own
        out["drone_contacts"] = {"teammate": int((touched & same).sum()), "opponent": int((touched & ~same).sum())}
    return out
