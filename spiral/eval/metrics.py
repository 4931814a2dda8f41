"""Pure functions over race results: success ratios with intervals that take a race as the unit, lap statistics,
crash counts."""

from __future__ import annotations

import math
from typing import Any

import torch

from spiral.core.outcome import race_winner
from spiral.env.actions import ACTION_AXES
from spiral.env.racing import BEARINGS, RaceResults
from spiral.eval.racecraft import racecraft
from spiral.sim import COLLISION_KINDS

__all__ = ["clustered_interval", "first_gate_order", "lap_statistics", "summarize_races", "wilson_interval"]


def wilson_interval(successes: int, trials: int, *, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95% by default); (0, 1) for no trials."""
    if trials == 0:
        return 0.0, 1.0
    return _wilson(successes / trials, trials, z)


def clustered_interval(finished: torch.Tensor, mask: torch.Tensor, *, z: float = 1.959964) -> tuple[float, float]:
    """95% interval of the per-drone success ratio with the race, not the drone, as the sampling unit.

    The drones of one race are not independent (a contact ends two of them), so the ratio p = Σk_r / Σn_r (k_r of
    the n_r ``mask`` drones of race r finished) gets the variance of a ratio over independent races,
    SE² = Σ_r (k_r − p·n_r)² / (Σ_r n_r)², and a Wilson interval with the effective sample size
    p(1 − p)/SE². That size is at least the number of races R and is capped at the number of drones; with
    p ∈ {0, 1} (no spread to measure) it is R. With one drone per race the interval is Wilson's over the races.

    Args:
        finished: Whether each drone finished, shape (R, D).
        mask: Drones to count, shape (R, D); races without any are left out.
    """
    k = (finished & mask).sum(dim=1).double()
    n = mask.sum(dim=1).double()
    races = n > 0
    k, n = k[races], n[races]
    total, count = float(n.sum()), int(races.sum())
    if count == 0:
        return 0.0, 1.0
    p = float(k.sum()) / total
    var = float(((k - p * n) ** 2).sum()) / total**2
    n_eff = float(count)  # p ∈ {0, 1}: no spread to measure
    if 0 < p < 1:  # no spread between races at all (e.g. one drone of two home in every race): as many as drones
        n_eff = min(p * (1 - p) / var, total) if var > 0 else total
    return _wilson(p, max(n_eff, count), z)


def _wilson(p: float, n: float, z: float) -> tuple[float, float]:
    denom = 1.0 + z * z / n
    center = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, center - half), min(1.0, center + half)


def lap_statistics(lap_times: torch.Tensor, finished: torch.Tensor) -> tuple[float | None, float | None]:
    """Mean and standard deviation (population) of the lap times of finished drones only; None when none."""
    laps = lap_times[finished.bool()].double()
    if laps.numel() == 0:
        return None, None
    return float(laps.mean()), float(laps.std(unbiased=False))


def first_gate_order(res: RaceResults, winners: torch.Tensor, teams: tuple[list[int], list[int]]) -> dict[str, Any]:
    """How far the order at the lap's first gate decides a team race: the share of races whose first drone through
    it was team A's (``led``; a race in which no drone passed it counts as not led), of the races with a winner and a
    drone through the gate the share that the team first there won (``leader_won``), and team A's win rate in the
    races it led there and in those the other team led (``won_when_led``, ``won_when_behind``; None without such
    races). ``winners`` as :func:`~spiral.core.outcome.race_winner` gives them (0: team A, 1: team B, −1: none)."""
    assert res.split_time is not None
    first = res.split_time[..., 0]
    leader = race_winner(first > 0, first, teams)

    def share(hit: torch.Tensor, of: torch.Tensor) -> float | None:
        return float(hit[of].float().mean()) if of.any() else None

    decided = (leader >= 0) & (winners >= 0)
    return {"led": float((leader == 0).float().mean()), "leader_won": share(leader == winners, decided),
            "won_when_led": share(winners == 0, leader == 0), "won_when_behind": share(winners == 0, leader == 1)}


def summarize_races(res: RaceResults, slots: list[int] | None = None) -> dict[str, Any]:
    """Metrics of the drones in ``slots`` (all present drones when None) over every race.

    ``success_ratio`` counts drones, with ``success_ci95`` from :func:`clustered_interval` (a race is the unit);
    ``race_success_ratio`` is the share of races in which every counted drone finished, with a Wilson interval over
    races (``race_success_ci95``).
    """
    mask = res.present.clone()
    if slots is not None:
        keep = torch.zeros_like(mask)
        keep[:, slots] = True
        mask &= keep
    finished = res.finished[mask]
    n, k = int(mask.sum()), int(finished.sum())
    raced = mask.any(dim=1)
    races = int(raced.sum())
    all_home = int(((res.finished | ~mask).all(dim=1) & raced).sum())
    mean, std = lap_statistics(res.lap_time[mask], finished)
    kinds = res.crash_kind[mask]
    crashes = {kind: int(((kinds & bit) != 0).sum()) for kind, bit in COLLISION_KINDS.items()}
    crashes["timeout"] = int((~res.finished[mask] & ~res.crashed[mask]).sum())
    speed = res.distance[mask][finished] / res.lap_time[mask][finished]
    return {
        "drones": n,
        "success_ratio": k / n if n else 0.0,
        "success_ci95": list(clustered_interval(res.finished, mask)),
        "races": races,
        "race_success_ratio": all_home / races if races else 0.0,
        "race_success_ci95": list(wilson_interval(all_home, races)),
        "lap_time_mean": mean,
        "lap_time_std": std,
        "mean_speed": float(speed.mean()) if speed.numel() else None,
        "crashes": crashes,
        **_crash_details(res, mask),
        **({"split_times": _split_times(res, mask)} if res.split_time is not None else {}),
        **({"action_beyond_range": _beyond_range(res, mask)} if res.beyond_steps is not None else {}),
        **({"passes": _passes(res, mask, races)} if res.passes is not None else {}),
        **({"racing": racecraft(res, mask)} if res.split_time is not None else {}),
    }


def _passes(res: RaceResults, mask: torch.Tensor, races: int) -> dict[str, float | int]:
    """Passes in flight between the teams: how many drones of the other team the ``mask`` drones passed (``made``),
    how many passed them (``suffered``), and both per race."""
    assert res.passes is not None
    made, suffered = (int(n) for n in res.passes[mask].sum(dim=0).tolist())
    per_race = max(races, 1)
    return {"made": made, "suffered": suffered, "made_per_race": made / per_race,
            "suffered_per_race": suffered / per_race}


def _beyond_range(res: RaceResults, mask: torch.Tensor) -> dict[str, float] | None:
    """Share of the ``mask`` drones' racing control steps in which the commanded action lay beyond the range the env
    clamps it to (|a| > 1), per action axis (None without racing steps).

    A policy whose mean action sits beyond the range on an axis acts at the clamp there: a small change of its mean
    changes nothing that is applied, and in training its Gaussian's samples on that side all act alike.
    """
    assert res.racing_steps is not None and res.beyond_steps is not None
    steps = int(res.racing_steps[mask].sum())
    if steps == 0:
        return None
    beyond = res.beyond_steps[mask].sum(dim=0)
    return {axis: int(n) / steps for axis, n in zip(ACTION_AXES, beyond.tolist(), strict=True)}


def _split_times(res: RaceResults, mask: torch.Tensor) -> list[float] | None:
    """Mean race time at each gate passage of the lap over the ``mask`` drones that finished (None if none did)."""
    done = res.finished & mask
    return res.split_time[done].mean(dim=0).tolist() if done.any() else None


def _crash_details(res: RaceResults, mask: torch.Tensor) -> dict[str, Any]:
    """Where and when the ``mask`` drones crashed, and whom they touched (when the results record it).

    ``crash_gates`` counts crashes by the gate of the lap the drone was flying to (0 = the first gate after the
    start, in passing order); ``drone_contacts`` splits drone–drone crashes by the other drone's team and
    ``contact_bearing`` by where the other drone was one control step before (ahead, beside, behind: see
    :func:`~spiral.env.racing.contact_bearing`) and ``contact_fault`` by who flew into whom: ``own`` counts the
    contacts in which the drone closed in at least twice as fast as the other (its share of
    :func:`~spiral.env.events.fault_share` at least 2/3), ``other`` those in which the other did (at most 1/3),
    ``even`` the rest; ``mean_share`` is the drones' mean share (None without contacts).
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
    if res.contact_bearing is not None:
        codes = res.contact_bearing[crashed]
        out["contact_bearing"] = {name: int((codes == i).sum()) for i, name in enumerate(BEARINGS)}
    if res.contact_fault is not None:
        share = res.contact_fault[crashed]
        share = share[share >= 0]
        mine, theirs = share >= 2 / 3, share <= 1 / 3
        mean = float(share.mean()) if share.numel() else None
        out["contact_fault"] = {"own": int(mine.sum()), "even": int((~mine & ~theirs).sum()),
                                "other": int(theirs.sum()), "mean_share": mean}
    return out
