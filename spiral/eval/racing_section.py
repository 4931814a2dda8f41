"""The report's racing section: each learned method's final policy in races of several laps, from the start box and
from points along the track, with the racing metrics (docs/evaluation.md, "Racing metrics"), and SPIRAL's duels
against PPO without self-play and against SE-IBR."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from spiral.config.pipeline import RacingCfg
from spiral.eval.evaluate import SE_IBR, FlightOverride
from spiral.eval.robustness import ALL_SCENARIOS, SHORT_LABELS, final_stages
from spiral.eval.runs import Evaluations, RowResult, StageRun

__all__ = ["Racing", "race_planner_duels", "race_racing", "racing_markdown"]

DUEL_SCENARIOS = ("1v1", "2v2")
"""Scenarios of the duels (a team against a team)."""

START_NAMES = {"box": "start box", "track": "track starts"}


@dataclass
class Racing:
    """What the racing section measured (None where a method or its pairing is missing)."""

    laps: int
    runs: int
    seed: int
    final_names: dict[str, str] = field(default_factory=dict)
    """Method -> the stage whose best is its final policy."""
    self_matches: dict[str, dict[str, dict[str, RowResult]]] = field(default_factory=dict)
    """Starts -> scenario -> method -> self-match of its final policy."""
    duels: dict[str, dict[str, dict[str, dict[str, Any]]]] = field(default_factory=dict)
    """Starts -> scenario -> opponent method -> SPIRAL's entry against it (the opponent's under ``opponent``)."""
    planner_runs: int = 0

    def add_planner_duels(self, duels: dict[str, dict[str, dict[str, Any]]], runs: int) -> None:
        """Add SPIRAL's duels against SE-IBR (starts -> scenario -> entry, :func:`race_planner_duels`), raced from
        ``runs`` placements."""
        for starts, by_scenario in duels.items():
            for scenario, entry in by_scenario.items():
                self.duels.setdefault(starts, {}).setdefault(scenario, {})["se-ibr"] = entry
        self.planner_runs = runs


def _variants(held: Evaluations, cfg: RacingCfg, runs: int | None = None) -> dict[str, Evaluations]:
    p = held.protocol
    return {starts: held.racing(runs or p.runs, p.seed, cfg.laps, starts) for starts in cfg.starts}


def race_racing(held: Evaluations, stages: list[StageRun], cfg: RacingCfg) -> Racing:
    """The section's races among learned policies, from ``held``'s placements: each final policy's self-matches in
    every scenario and SPIRAL's duel with PPO without self-play, from every start of ``cfg``."""
    out = Racing(cfg.laps, held.protocol.runs, held.protocol.seed)
    final = final_stages(stages)
    finals = {method: str(stage.best) for method, stage in final.items()}
    out.final_names = {method: stage.name for method, stage in final.items()}
    for starts, ev in _variants(held, cfg).items():
        out.self_matches[starts] = {
            scenario: {method: ev.flown(scenario, method, checkpoint, FlightOverride(), "final")
                       for method, checkpoint in finals.items()} for scenario in ALL_SCENARIOS}
        out.duels[starts] = {scenario: {} for scenario in DUEL_SCENARIOS}
        if "spiral" in finals and "noselfplay" in finals:
            for scenario in DUEL_SCENARIOS:
                out.duels[starts][scenario]["noselfplay"] = ev.cross(
                    scenario, ("spiral", finals["spiral"]), ("noselfplay", finals["noselfplay"]))
    return out


def race_planner_duels(held: Evaluations, stages: list[StageRun], cfg: RacingCfg
                       ) -> dict[str, dict[str, dict[str, Any]]]:
    """SPIRAL's final policy against SE-IBR in ``cfg.planner_scenarios``, from ``cfg.planner_runs`` placements of
    ``held``'s seed and every start of ``cfg``: starts -> scenario -> SPIRAL's entry."""
    final = final_stages(stages).get("spiral")
    out: dict[str, dict[str, dict[str, Any]]] = {}
    if final is None or cfg.planner_runs == 0:
        return out
    for starts, ev in _variants(held, cfg, cfg.planner_runs).items():
        out[starts] = {s: ev.cross(s, ("spiral", str(final.best)), ("se-ibr", SE_IBR)) for s in cfg.planner_scenarios}
    return out


def racing_markdown(r: Racing, sides: str) -> list[str]:
    """The section's markdown lines."""
    finals = ", ".join(f"{SHORT_LABELS[m]}: stage {n}" for m, n in r.final_names.items())
    lines = [f"## Racing: {r.laps}-lap races", "",
             f"Each method's final policy ({finals}) in races of {r.laps} laps from {r.runs} held-out placements "
             f"(seed {r.seed}), from the start box and from track starts (every drone at a random point between two "
             "gates, heading for the next at up to 1 m/s). Success: drones home, with its 95% interval (a race as the "
             "unit); first lap from the start, flying laps the later ones; overtakes: order changes between two "
             "drones from one gate passage to the next; won from behind: races won by a team other than the one "
             "first through the first gate; contacts: drone–drone crashes per lap flown (docs/evaluation.md, "
             "\"Racing metrics\").", "",
             "### Self-matches", "",
             "| Starts | Scenario | Method | Success | All home | Race [s] | First lap [s] | Flying lap [s] "
             "| Overtakes / race | Lead changes / race | Won from behind | Contacts / lap "
             "| Crashes gate / drone / other |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for starts, by_scenario in r.self_matches.items():
        for scenario, rows in by_scenario.items():
            for method, row in rows.items():
                lines.append(f"| {START_NAMES[starts]} | {scenario} | {SHORT_LABELS[method]} | "
                             f"{_self_cells(row.metrics, scenario)} |")
    side = "each placement raced from both sides" if sides == "both" else "SPIRAL on team A"
    planner = f"; against SE-IBR from the first {r.planner_runs} of the placements" if r.planner_runs else ""
    lines += ["", "### Duels", "",
              f"SPIRAL's final policy against the other methods' ({side}{planner}). Where a duel is decided: the "
              "share of races SPIRAL's team led through the first gate, how often the team first there won, and "
              "SPIRAL's win rate in the races it led there and in those it trailed there.", "",
              "| Starts | Scenario | SPIRAL vs | Races | Win / loss / draw | SPIRAL home | Other home | Led first gate "
              "| First-gate leader won | SPIRAL wins: led / trailed | Overtakes / race | Flying lap: SPIRAL / "
              "other [s] |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for starts, by_scenario in r.duels.items():
        for scenario, by_opponent in by_scenario.items():
            for method, entry in by_opponent.items():
                lines.append(f"| {START_NAMES[starts]} | {scenario} | {SHORT_LABELS[method]} | {_duel_cells(entry)} |")
    return [*lines, ""]


def _num(x: float | None, digits: int = 2) -> str:
    return "–" if x is None else f"{x:.{digits}f}"


def _self_cells(m: dict[str, Any] | None, scenario: str) -> str:
    """A self-match's cells; the metrics between drones are left out of a solo race."""
    if m is None:
        return " | ".join(["missing"] + ["–"] * 9)
    lo, hi = m["success_ci95"]
    rc, crashes = dict(m.get("racing") or {}), m["crashes"]
    if scenario == "solo":
        rc.update(overtakes_per_race=None, lead_changes_per_race=None, won_from_behind=None)
    other = sum(v for k, v in crashes.items() if k not in ("gate", "drone"))
    return (f"{m['success_ratio']:.3f} [{lo:.2f}, {hi:.2f}] | {_num(m.get('race_success_ratio'), 3)} | "
            f"{_num(m['lap_time_mean'])} | {_num(rc.get('first_lap'))} | {_num(rc.get('flying_lap'))} | "
            f"{_num(rc.get('overtakes_per_race'))} | {_num(rc.get('lead_changes_per_race'))} | "
            f"{_num(rc.get('won_from_behind'))} | {_num(rc.get('drone_contacts_per_lap'), 3)} | "
            f"{crashes['gate']} / {crashes['drone']} / {other}")


def _duel_cells(d: dict[str, Any]) -> str:
    gate, rc, opp = d.get("first_gate") or {}, d.get("racing") or {}, d["opponent"]
    return (f"{d.get('races', '–')} | {d['win_rate']:.2f} / {d['loss_rate']:.2f} / {d['draws']:.2f} | "
            f"{d['success_ratio']:.3f} | {opp['success_ratio']:.3f} | {_num(gate.get('led'))} | "
            f"{_num(gate.get('leader_won'))} | "
            f"{_num(gate.get('won_when_led'))} / {_num(gate.get('won_when_behind'))} | "
            f"{_num(rc.get('overtakes_per_race'))} | "
            f"{_num(rc.get('flying_lap'))} / {_num((opp.get('racing') or {}).get('flying_lap'))}")
