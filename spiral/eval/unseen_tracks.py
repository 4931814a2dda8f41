"""Learned policies on tracks no training step flew: self-matches of every scenario on each track, with the lap beside
the point-mass reference of the track and beside a specialist trained on it, and the first method's duels against the
others (the report's "Unseen tracks" section)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from spiral.config.airframe import AirframeCfg
from spiral.config.pipeline import UnseenTracksCfg
from spiral.config.track import TrackSpec
from spiral.eval.bound import lap_time_bound
from spiral.eval.evaluate import RaceSet, evaluate_methods
from spiral.eval.report import METHODS

__all__ = ["DUEL_SCENARIOS", "REFERENCE_STEPS", "SCENARIOS", "SPECIALIST", "UnseenRaces", "race_unseen_tracks",
           "unseen_tracks_markdown"]

SCENARIOS = ("solo", "1v1", "2v2")
"""The self-matches raced on every track."""
DUEL_SCENARIOS = ("1v1", "2v2")
"""The duels of the first method against each other one."""
REFERENCE_STEPS = 4
"""Steps per gate-to-gate segment of the point-mass reference lap (coarse: a few % above the finest)."""
SPECIALIST = "specialist"
"""The method name of a track's specialist in the rows."""


@dataclass
class UnseenRaces:
    """The section's races: one self-match row per track, method and scenario, one duel row per track, opponent and
    scenario."""

    self_matches: list[dict[str, Any]] = field(default_factory=list)
    duels: list[dict[str, Any]] = field(default_factory=list)


def race_unseen_tracks(tracks: Sequence[tuple[str, TrackSpec]], methods: dict[str, Path], cfg: UnseenTracksCfg,
                       airframe: AirframeCfg, *, specialists: dict[str, Path] | None = None, device: str = "cpu",
                       log: Callable[[str], None] = print) -> UnseenRaces:
    """Race ``methods`` (name -> final policy) on ``tracks`` (given as ``(kind, track)``, kind e.g. ``held out``):
    each method's self-match of ``cfg.races`` races of ``cfg.laps`` laps from the start box (placements of
    ``cfg.seed``) in every scenario, also a track's specialist (``specialists``: track name -> policy) on its track;
    with ``cfg.head_to_head``, the first method's duels against each other one, from both sides."""
    out = UnseenRaces()
    for kind, track in tracks:
        reference = lap_time_bound(track, airframe, steps_per_segment=REFERENCE_STEPS).lap_time
        here = dict(methods)
        if specialists and track.name in specialists:
            here[SPECIALIST] = specialists[track.name]
        out.self_matches += _self_matches(track, kind, reference, here, cfg, device)
        if cfg.head_to_head and len(methods) > 1:
            out.duels += _duels(track, kind, methods, cfg, device)
        log(f"unseen tracks: {track.name} ({kind}) raced, reference lap {reference:.2f} s")
    return out


def _self_matches(track: TrackSpec, kind: str, reference: float, methods: dict[str, Path], cfg: UnseenTracksCfg,
                  device: str) -> list[dict[str, Any]]:
    rows = []
    for scenario in SCENARIOS:
        races = RaceSet(track.with_laps(cfg.laps), scenario, cfg.races, cfg.seed)
        for method, m in evaluate_methods(races, methods, device=device)["methods"].items():
            race_time = m["lap_time_mean"]
            rows.append({"track": track.name, "kind": kind, "reference_lap_s": reference, "method": method,
                         "scenario": scenario, "success": m["success_ratio"],
                         "mean_lap_s": race_time / cfg.laps if race_time is not None else None,
                         "first_lap_s": m["racing"].get("first_lap"), "flying_lap_s": m["racing"].get("flying_lap")})
    return rows


def _duels(track: TrackSpec, kind: str, methods: dict[str, Path], cfg: UnseenTracksCfg,
           device: str) -> list[dict[str, Any]]:
    (first, policy), *others = methods.items()
    rows = []
    for scenario in DUEL_SCENARIOS:
        races = RaceSet(track.with_laps(cfg.laps), scenario, cfg.races, cfg.seed)
        for other, opponent in others:
            m = evaluate_methods(races, {first: policy}, against=(other, opponent), device=device)["methods"][first]
            rows.append({"track": track.name, "kind": kind, "method": first, "against": other, "scenario": scenario,
                         "races": 2 * cfg.races, "win_rate": m["win_rate"], "loss_rate": m["loss_rate"],
                         "success": m["success_ratio"], "opponent_success": m["opponent"]["success_ratio"]})
    return rows


def _ratio(lap: float | None, reference: float) -> str:
    return "–" if lap is None or not math.isfinite(lap) else f"{lap:.2f} ({lap / reference:.2f}×)"


def _finite(lap: float | None) -> bool:
    return lap is not None and math.isfinite(lap)


def unseen_tracks_markdown(races: UnseenRaces, cfg: UnseenTracksCfg, command: str) -> str:
    """The report's section on unseen tracks from :func:`race_unseen_tracks`' races: per method, one line per track
    with the success of each scenario and the mean lap of the solo and 2v2 races against the reference, and a summary
    over the tracks; then the duels."""
    lines = ["## Unseen tracks", "",
             f"Each learned method's final policy in self-matches of {cfg.laps} lap{'s' if cfg.laps > 1 else ''} "
             f"from the start box on tracks no training step flew, {cfg.races} races per track and scenario "
             f"(placements of seed {cfg.seed}); mean lap = race time / laps, beside the point-mass reference lap "
             f"(coarse, {REFERENCE_STEPS} steps per segment, `spiral track bound`) and, where a specialist trained on "
             f"the track is given, its lap. `{command}`", ""]
    rows = races.self_matches
    for method in dict.fromkeys(r["method"] for r in rows):
        lines += _method_table(rows, method)
    if races.duels:
        lines += _duel_table(races.duels, cfg)
    return "\n".join(lines)


def _method_table(rows: list[dict[str, Any]], method: str) -> list[str]:
    """A method's table: a line per track it raced, then the summary over them."""
    mine = [r for r in rows if r["method"] == method]
    specialist = {r["track"]: r for r in rows if r["method"] == SPECIALIST and r["scenario"] == "solo"}
    lines = [f"**{METHODS.get(method, method)}**", "",
             "| track | kind | reference lap [s] | success solo / 1v1 / 2v2 | mean lap solo [s] | mean lap 2v2 [s] "
             "| solo lap / specialist's |",
             "|---|---|---|---|---|---|---|"]
    for track in dict.fromkeys(r["track"] for r in mine):
        by = {r["scenario"]: r for r in mine if r["track"] == track}
        first, solo = by["solo"], by["solo"]["mean_lap_s"]
        success = " / ".join(f"{by[s]['success']:.2f}" for s in SCENARIOS)
        other = specialist.get(track, {}).get("mean_lap_s") if method != SPECIALIST else None
        versus = f"{solo / other:.2f}×" if _finite(solo) and _finite(other) else "–"
        lines.append(f"| {track} | {first['kind']} | {first['reference_lap_s']:.2f} | {success} | "
                     f"{_ratio(solo, first['reference_lap_s'])} | "
                     f"{_ratio(by['2v2']['mean_lap_s'], first['reference_lap_s'])} | {versus} |")
    return [*lines, "", _summary(mine), ""]


def _summary(rows: list[dict[str, Any]]) -> str:
    """Mean and lowest success of each scenario over the tracks of ``rows`` (one method's), and its slowest mean lap
    against the reference."""
    tracks = list(dict.fromkeys(r["track"] for r in rows))
    parts = []
    for scenario in SCENARIOS:
        success = [r["success"] for r in rows if r["scenario"] == scenario]
        parts.append(f"{scenario} {sum(success) / len(success):.2f} (lowest {min(success):.2f})")
    ratios = [r["mean_lap_s"] / r["reference_lap_s"] for r in rows if _finite(r["mean_lap_s"])]
    slowest = f"{max(ratios):.2f}× the reference" if ratios else "no race finished"
    return (f"Over {len(tracks)} track{'s' if len(tracks) > 1 else ''}: mean success {', '.join(parts)}; slowest mean "
            f"lap {slowest}.")


def _duel_table(duels: list[dict[str, Any]], cfg: UnseenTracksCfg) -> list[str]:
    """The first method's duels: win and loss rate per track and scenario, and their means over the tracks."""
    method, against = duels[0]["method"], list(dict.fromkeys(d["against"] for d in duels))
    lines = [f"**{METHODS.get(method, method)} head to head** ({cfg.races} placements per track and scenario, each "
             "raced from both sides; win / loss, its drones' success / the opponents')", "",
             "| track | kind | against | 1v1 win / loss | 1v1 success | 2v2 win / loss | 2v2 success |",
             "|---|---|---|---|---|---|---|"]
    for other in against:
        mine = [d for d in duels if d["against"] == other]
        for track in dict.fromkeys(d["track"] for d in mine):
            by = {d["scenario"]: d for d in mine if d["track"] == track}
            cells = [f"{by[s]['win_rate']:.2f} / {by[s]['loss_rate']:.2f} | {by[s]['success']:.2f} / "
                     f"{by[s]['opponent_success']:.2f}" for s in DUEL_SCENARIOS]
            lines.append(f"| {track} | {by['1v1']['kind']} | {METHODS.get(other, other)} | {' | '.join(cells)} |")
        tracks = len({d["track"] for d in mine})
        means = [sum(d["win_rate"] for d in mine if d["scenario"] == s) / tracks for s in DUEL_SCENARIOS]
        lines += ["", f"Against {METHODS.get(other, other)}: mean win rate 1v1 {means[0]:.2f}, 2v2 {means[1]:.2f}.",
                  ""]
    return lines
