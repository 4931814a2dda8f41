"""The figures a run is judged by, flat and machine-readable: the report's ``headline.json``, and what ``spiral sweep``
tables across pipeline draws.

Names are ``/``-joined paths, each with one value (None where the run has no such race):

- ``protocol/<scenario>/<method>/success`` and ``.../lap_time`` (None without a finished lap): the paper's one-lap
  protocol (the report's tables);
- ``held_out/<scenario>/<method>/success``, ``held_out/<scenario>/duel/win_rate``: the same self-matches and SPIRAL's
  head to head with PPO without self-play, from the held-out placements;
- ``racing/<starts>/<scenario>/<method>/success``, ``.../all_home`` and ``.../flying_lap``: the racing section's
  multi-lap self-matches of each final policy; ``racing/<starts>/<scenario>/vs-<opponent>/win_rate`` and
  ``.../home``: SPIRAL's duels (its wins, and the share of its drones home).
"""

from __future__ import annotations

import math
from typing import Any

from spiral.eval.racing_section import Racing
from spiral.eval.runs import RowResult

__all__ = ["headline_figures"]


def headline_figures(table: dict[str, list[RowResult]], held: dict[str, Any] | None,
                     racing: Racing | None) -> dict[str, float | None]:
    """The headline figures of a report: its protocol ``table`` (scenario -> rows), its held-out races (``held``, as
    the report computes them; None without) and its racing section (None without)."""
    out: dict[str, float | None] = {}
    for scenario, rows in table.items():
        for row in rows:
            metrics = row.metrics or {}
            out[f"protocol/{scenario}/{row.method}/success"] = metrics.get("success_ratio")
            out[f"protocol/{scenario}/{row.method}/lap_time"] = metrics.get("lap_time_mean")
    for scenario, entry in (held or {}).items():
        if not isinstance(entry, dict):  # the held-out set's runs and seed
            continue
        for method, row in entry["rows"].items():
            out[f"held_out/{scenario}/{method}/success"] = (row.metrics or {}).get("success_ratio")
        out[f"held_out/{scenario}/duel/win_rate"] = (entry["duel"] or {}).get("win_rate")
    if racing is not None:
        out.update(_racing_figures(racing))
    return {name: _finite(value) for name, value in out.items()}


def _finite(value: float | None) -> float | None:
    """``value`` as a float, None when missing or not finite (a lap time without a finished lap)."""
    return None if value is None or not math.isfinite(value) else float(value)


def _racing_figures(racing: Racing) -> dict[str, float | None]:
    out: dict[str, float | None] = {}
    for starts, by_scenario in racing.self_matches.items():
        for scenario, by_method in by_scenario.items():
            for method, row in by_method.items():
                metrics = row.metrics or {}
                key = f"racing/{starts}/{scenario}/{method}"
                out[f"{key}/success"] = metrics.get("success_ratio")
                out[f"{key}/all_home"] = metrics.get("race_success_ratio")
                out[f"{key}/flying_lap"] = (metrics.get("racing") or {}).get("flying_lap")
    for starts, by_scenario in racing.duels.items():
        for scenario, by_opponent in by_scenario.items():
            for opponent, duel in by_opponent.items():
                key = f"racing/{starts}/{scenario}/vs-{opponent}"
                out[f"{key}/win_rate"] = (duel or {}).get("win_rate")
                out[f"{key}/home"] = (duel or {}).get("success_ratio")
    return out
