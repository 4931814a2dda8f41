"""Learned policies on tracks no training step flew: self-matches of every scenario on each track, with the lap beside
the point-mass reference of the track (the report's "Unseen tracks" section)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from spiral.config.airframe import AirframeCfg
from spiral.config.pipeline import UnseenTracksCfg
from spiral.config.track import TrackSpec
from spiral.eval.bound import lap_time_bound
from spiral.eval.evaluate import RaceSet, evaluate_methods
from spiral.eval.report import METHODS

__all__ = ["REFERENCE_STEPS", "SCENARIOS", "race_unseen_tracks", "unseen_tracks_markdown"]

SCENARIOS = ("solo", "1v1", "2v2")
"""The self-matches raced on every track."""
REFERENCE_STEPS = 4
"""Steps per gate-to-gate segment of the point-mass reference lap (coarse: a few % above the finest)."""


def race_unseen_tracks(tracks: Sequence[tuple[str, TrackSpec]], methods: dict[str, Path], cfg: UnseenTracksCfg,
                       airframe: AirframeCfg, *, device: str = "cpu",
                       log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """One row per track (given as ``(kind, track)``, kind e.g. ``held out``), method and scenario: the method's
    self-match of ``cfg.races`` races of ``cfg.laps`` laps from the start box (placements of ``cfg.seed``), its
    success, mean lap (race time / laps), first and flying lap, and the track's point-mass reference lap."""
    rows = []
    for kind, track in tracks:
        reference = lap_time_bound(track, airframe, steps_per_segment=REFERENCE_STEPS).lap_time
        for scenario in SCENARIOS:
            races = RaceSet(track.with_laps(cfg.laps), scenario, cfg.races, cfg.seed)
            result = evaluate_methods(races, methods, device=device)
            for method, m in result["methods"].items():
                race_time = m["lap_time_mean"]
                rows.append({"track": track.name, "kind": kind, "reference_lap_s": reference, "method": method,
                             "scenario": scenario, "success": m["success_ratio"],
                             "mean_lap_s": race_time / cfg.laps if race_time is not None else None,
                             "first_lap_s": m["racing"].get("first_lap"),
                             "flying_lap_s": m["racing"].get("flying_lap")})
        log(f"unseen tracks: {track.name} ({kind}) raced, reference lap {reference:.2f} s")
    return rows


def _ratio(lap: float | None, reference: float) -> str:
    return "–" if lap is None or not math.isfinite(lap) else f"{lap:.2f} ({lap / reference:.2f}×)"


def unseen_tracks_markdown(rows: list[dict[str, Any]], cfg: UnseenTracksCfg, command: str) -> str:
    """The report's section on unseen tracks from :func:`race_unseen_tracks`' rows: per method, one line per track
    with the success of each scenario and the mean lap of the solo and 2v2 races against the reference."""
    lines = ["## Unseen tracks", "",
             f"Each learned method's final policy in self-matches of {cfg.laps} lap{'s' if cfg.laps > 1 else ''} "
             f"from the start box on tracks no "
             f"training step flew, {cfg.races} races per track and scenario (placements of seed {cfg.seed}); mean "
             f"lap = race time / laps, beside the point-mass reference lap (coarse, {REFERENCE_STEPS} steps per "
             f"segment, `spiral track bound`). `{command}`", ""]
    for method in dict.fromkeys(r["method"] for r in rows):
        lines += [f"**{METHODS.get(method, method)}**", "",
                  "| track | kind | reference lap [s] | success solo / 1v1 / 2v2 | mean lap solo [s] "
                  "| mean lap 2v2 [s] |",
                  "|---|---|---|---|---|---|"]
        for track in dict.fromkeys(r["track"] for r in rows):
            by = {r["scenario"]: r for r in rows if r["method"] == method and r["track"] == track}
            first = next(iter(by.values()))
            success = " / ".join(f"{by[s]['success']:.2f}" for s in SCENARIOS)
            lines.append(f"| {track} | {first['kind']} | {first['reference_lap_s']:.2f} | {success} | "
                         f"{_ratio(by['solo']['mean_lap_s'], first['reference_lap_s'])} | "
                         f"{_ratio(by['2v2']['mean_lap_s'], first['reference_lap_s'])} |")
        lines.append("")
    return "\n".join(lines)
