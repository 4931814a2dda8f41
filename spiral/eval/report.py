"""``spiral report``: the paper's tables, cross-play, the lap-time reference and figures from a pipeline's run folder.

Inputs are what the run's steps declared in their manifests (:class:`spiral.eval.runs.RunRecord`): each training
step's spec (scenario, self-play mode, airframe, simulator, track), best policy and log, each stage evaluation, and
the race caches of the report's own steps. SPIRAL is a self-play (``pool``) stage, PPO without self-play a
``frozen`` stage, each evaluated in its own scenario by self-match. Evaluations the run lacks (a missing stage
evaluation, cross-play, SE-IBR when asked for) are run here with the same races and seed and cached under
``<out>/evals/`` with the checksums of the checkpoints they used, so a second report reuses them. What can be neither
found nor run is marked missing.
"""

from __future__ import annotations

import csv
import json
import subprocess
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from spiral.config.airframe import AirframeCfg
from spiral.config.env import SeparationCfg
from spiral.config.pipeline import RacingCfg
from spiral.config.track import TrackSpec
from spiral.core.device import torch_threads
from spiral.core.errors import UsageError
from spiral.eval.bound import LapBound, lap_time_bound
from spiral.eval.evaluate import SE_IBR, EvalLayout, check_sides
from spiral.eval.headline import headline_figures
from spiral.eval.plots import TradeoffPoint, plot_learning_curves, plot_speed_vs_reliability, plot_track
from spiral.eval.racing_section import Racing, race_planner_duels, race_racing, racing_markdown
from spiral.eval.robustness import Robustness, filter_rows, race_learned, race_se_ibr, robustness_markdown
from spiral.eval.runs import (
    MODE_OF,
    EvalProtocol,
    Evaluations,
    RowResult,
    RunRecord,
    StageRun,
    crosses_in_workers,
    read_train_log,
    run_protocol,
    run_setup,
)

__all__ = ["METHODS", "PAPER", "SCENARIOS", "ReportOptions", "RunRecord", "StageRun", "build_report",
           "race_learned_policies", "race_planner_pairing", "race_planner_racing", "read_train_log"]

METHODS: dict[str, str] = {"spiral": "PPO Selfplay (SPIRAL)", "se-ibr": "SE-IBR (Baseline)",
                           "noselfplay": "PPO No Selfplay"}
"""The methods of the paper's tables, in row order: name -> label."""

SCENARIOS = ("1v1", "2v2")

FILTER_ROW = "+ separation filter"
"""Label of the extra table rows raced with the opt-in separation filter."""

PAPER: dict[str, dict[str, tuple[float, float, str, str]]] = {
    "1v1": {"spiral": (13.7124, 0.69, "13.7124 ± 0.0005", "0.6900 ± 0.0500"),
            "se-ibr": (14.2506, 0.81, "14.2506 ± 0.2986", "0.8100 ± 0.1100"),
            "noselfplay": (16.3134, 0.80, "16.3134 ± 0.0727", "0.8000 ± 0.0200")},
    "2v2": {"spiral": (13.71, 0.56, "13.71 ± 0.01", "0.56 ± 0.01"),
            "se-ibr": (14.39, 0.62, "14.39 ± 0.33", "0.62 ± 0.22"),
            "noselfplay": (17.82, 0.31, "17.82 ± 0.27", "0.31 ± 0.12")},
}
"""The paper's Tables 1 (1v1) and 2 (2v2): lap time, success ratio, and both as printed."""

@dataclass(frozen=True)
class ReportOptions:
    """What a report races and how: ``spiral report``'s options, or a pipeline's ``evaluation`` and ``report``."""

    runs: int | None = None
    """Races per evaluation; the pipeline's (from its eval.json files) when None."""
    seed: int | None = None
    """Seed of the start placements; the pipeline's when None."""
    device: str = "cpu"
    """Device of the evaluations the report runs."""
    se_ibr: bool = False
    """Run the SE-IBR planner where no evaluation of it exists (minutes per scenario on a CPU)."""
    cross_play: bool = True
    """Compute the cross-play win-rate matrices (running what is missing)."""
    airframe: AirframeCfg | None = None
    """Airframe of the lap-time reference and of planner-only races; the pipeline's when None."""
    holdout: tuple[int, int] | None = None
    """``(runs, seed)`` of a held-out check: the learned methods' self-matches and their head-to-head raced again
    from other placements (cached under ``evals/holdout-*``); None: no check."""
    sides: str = "both"
    """Head-to-head races: ``both`` races every placement from both sides, ``a`` with the row method on team A only
    (see :func:`spiral.eval.evaluate.cross_play`)."""
    separation: SeparationCfg | None = None
    """A separation filter raced as an extra row under each table, with the same checkpoints (an opt-in deployment
    layer, not part of the methods); None: no such rows."""
    robustness: bool = True
    """Add the sections of :mod:`spiral.eval.robustness` (final policy in every scenario, racing strangers, downwash),
    raced from the held-out placements when given, else the protocol's."""
    racing: RacingCfg | None = None
    """Add the racing section (:mod:`spiral.eval.racing_section`), raced from the held-out placements (needs
    ``holdout``); with ``se_ibr`` also SPIRAL's duels against the planner."""
    bound_steps: int = 24
    """Mean time steps per segment of the lap-time reference."""
    command: str | None = None
    """Command line quoted in results.md."""
    jobs: int = 1
    """Processes that race SE-IBR's head-to-head pairings side by side (with ``se_ibr``) while the report's own
    process races the learned policies."""

    def __post_init__(self) -> None:
        check_sides(self.sides)
        if self.racing is not None and self.holdout is None:
            raise UsageError("the racing section races the held-out placements: give holdout (runs, seed)")


def build_report(run: RunRecord, track: TrackSpec, out_dir: Path, options: ReportOptions = ReportOptions(), *,
                 log: Callable[[str], None] = print) -> Path:
    """Write ``results.md``, ``results.csv``, ``headline.json`` (:mod:`spiral.eval.headline`), ``bound.json`` and the
    figures for ``run`` (a pipeline's run, as its
    steps declared it; ``track`` its track) into ``out_dir`` (created; the evaluations run here are cached in
    ``out_dir/evals``), as ``options`` say; ``log`` takes progress messages. Returns the path of ``results.md``."""
    out_dir, o = Path(out_dir), options
    ev = _protocol(run, track, out_dir, o, se_ibr=o.se_ibr, log=log)
    stages, runs, seed, airframe = ev.stages, ev.protocol.runs, ev.protocol.seed, ev.protocol.layout.airframe
    table = {s: [ev.self_match(s, method) for method in METHODS] for s in SCENARIOS}
    held_ev = None if o.holdout is None else ev.held_out(*o.holdout)
    planner_pairings = _se_ibr_pairings(table) if o.se_ibr and (o.cross_play or o.robustness) else []
    with crosses_in_workers(ev, planner_pairings, jobs=o.jobs):  # everything else meanwhile, in this process
        held, filtered, rb, raced = _race_learned(ev, held_ev, table, o)
        bound = _write_files(out_dir, track, airframe, stages, table, o.bound_steps)
    matrices = {s: _cross_matrix(ev, s, table[s]) for s in SCENARIOS} if o.cross_play else {}
    if rb is not None and o.se_ibr:
        race_se_ibr(rb, ev)
    if raced is not None and held_ev is not None and o.racing is not None and o.se_ibr:
        raced.add_planner_duels(race_planner_duels(held_ev, stages, o.racing), o.racing.planner_runs)
    text = _markdown(run.root, track, stages, _Tables(table, matrices, held, filtered), bound,
                     replace(o, runs=runs, seed=seed))
    text = _with_racing(_with_robustness(text, rb, o.sides), raced, o.sides)
    (out_dir / "results.md").write_text(text)
    headline = headline_figures(table, held, raced)
    (out_dir / "headline.json").write_text(json.dumps(headline, indent=1, sort_keys=True) + "\n")
    return out_dir / "results.md"


def race_learned_policies(run: RunRecord, track: TrackSpec, out_dir: Path, options: ReportOptions = ReportOptions(),
                          *, log: Callable[[str], None] = print) -> Path:
    """Race, on one torch thread, what :func:`build_report` races among the learned policies (cross-play, held-out,
    filter, robustness and racing races), caching it under ``out_dir/evals``, where a later report of ``run`` finds
    it once declared. A pipeline runs it as a step of its own, beside the planner's pairings. Returns that cache
    folder."""
    ev = _protocol(run, track, Path(out_dir), options, se_ibr=False, log=log)
    with torch_threads(1):
        table = {s: [ev.self_match(s, method) for method in METHODS if method in MODE_OF] for s in SCENARIOS}
        holdout = options.holdout
        _race_learned(ev, None if holdout is None else ev.held_out(*holdout), table, options)
    return ev.cache


def race_planner_pairing(run: RunRecord, track: TrackSpec, out_dir: Path, scenario: str, method: str,
                         options: ReportOptions = ReportOptions(), *,
                         log: Callable[[str], None] = print) -> dict[str, Any]:
    """Race, on one torch thread, learned ``method``'s head-to-head pairing with SE-IBR in ``scenario`` as
    :func:`build_report` races it, caching it under ``out_dir/evals``. A pipeline runs each pairing as a step of its
    own as soon as the stage it races has trained. Returns the method's entry (with SE-IBR's under ``opponent``)."""
    ev = _protocol(run, track, Path(out_dir), replace(options, holdout=None, racing=None), se_ibr=True, log=log)
    checkpoint = ev.checkpoint(scenario, method)
    if checkpoint is None:
        raise FileNotFoundError(f"{run.root}: no best.pt of a {MODE_OF[method]}-mode {scenario} stage")
    with torch_threads(1):
        return ev.cross(scenario, (method, checkpoint), ("se-ibr", SE_IBR))


def race_planner_racing(run: RunRecord, track: TrackSpec, out_dir: Path, options: ReportOptions, *,
                        log: Callable[[str], None] = print) -> dict[str, Any]:
    """Race, on one torch thread, SPIRAL's duels against SE-IBR of the racing section (``options.racing``) as
    :func:`build_report` races them, caching them under ``out_dir/evals``. A pipeline runs them as a step of its own
    once SPIRAL's final stage has trained. Returns starts -> scenario -> SPIRAL's entry."""
    if options.racing is None or options.holdout is None:
        raise UsageError("race_planner_racing: options without a racing section")
    ev = _protocol(run, track, Path(out_dir), options, se_ibr=True, log=log)
    with torch_threads(1):
        return race_planner_duels(ev.held_out(*options.holdout), ev.stages, options.racing)


def _protocol(run: RunRecord, track: TrackSpec, out_dir: Path, options: ReportOptions, *, se_ibr: bool,
              log: Callable[[str], None]) -> Evaluations:
    """The run's evaluations with the report's races, seed, airframe and simulator, cached in ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    stages = run.stages
    runs, seed = run_protocol(stages, options.runs, options.seed)
    if options.holdout is not None and options.holdout[1] == seed:
        raise UsageError(f"holdout seed {seed} is the evaluation's own seed: held-out placements need another")
    stage_airframe, sim = run_setup(stages)
    layout = EvalLayout.default(airframe=options.airframe or stage_airframe, sim=sim)
    protocol = EvalProtocol(track, runs, seed, layout, sides=options.sides)
    return Evaluations(run, out_dir, protocol, device=options.device, se_ibr=se_ibr, log=log)


def _race_learned(ev: Evaluations, held_ev: Evaluations | None, table: dict, o: ReportOptions
                  ) -> tuple[dict[str, Any] | None, dict[str, list[RowResult]], Robustness | None, Racing | None]:
    """What the report races without the planner: the cross-play pairings among learned methods (into the cache),
    the held-out races, the filter rows, the robustness races and the racing section's races among learned
    methods."""
    if o.cross_play:
        for s in SCENARIOS:
            _cross_matrix(ev, s, table[s], planner=False)
    held = None if held_ev is None else _held_out(held_ev)
    filtered = filter_rows(ev, o.separation) if o.separation is not None else {}
    rb = race_learned(held_ev or ev, ev.stages, o.separation) if o.robustness else None
    raced = race_racing(held_ev, ev.stages, o.racing) if o.racing is not None and held_ev is not None else None
    return held, filtered, rb, raced


def _write_files(out_dir: Path, track: TrackSpec, airframe: AirframeCfg, stages: list[StageRun], table: dict,
                 bound_steps: int) -> LapBound:
    """``bound.json``, the figures and ``results.csv``; the lap-time reference they use."""
    bound = _write_bound(out_dir / "bound.json", track, airframe, bound_steps)
    _write_figures(out_dir, track, stages, table, bound)
    _write_csv(out_dir / "results.csv", table, bound)
    return bound


def _se_ibr_pairings(table: dict) -> list[tuple[str, tuple[str, str], tuple[str, str]]]:
    """Each learned method's head-to-head pairing with SE-IBR, in every scenario (minutes of planning each)."""
    return [(s, (r.method, r.checkpoint), ("se-ibr", SE_IBR)) for s in SCENARIOS for r in table[s]
            if r.method in MODE_OF and r.checkpoint is not None]


def _write_bound(path: Path, track: TrackSpec, airframe: AirframeCfg, steps: int) -> LapBound:
    """The lap-time reference, also written to ``path`` with its trajectory."""
    bound = lap_time_bound(track, airframe, steps_per_segment=steps)
    path.write_text(json.dumps(bound.to_json(trajectory=True), indent=2) + "\n")
    return bound


def _with_robustness(text: str, rb: Robustness | None, sides: str) -> str:
    """``results.md`` with the robustness sections (when measured) before the figures."""
    if rb is None:
        return text
    return text.replace(_FIGURES_HEADING, "\n".join(robustness_markdown(rb, sides)) + "\n" + _FIGURES_HEADING)


def _with_racing(text: str, racing: Racing | None, sides: str) -> str:
    """``results.md`` with the racing section (when measured) ahead of the paper's one-lap tables."""
    if racing is None:
        return text
    head = text.index("\n## ") + 1
    return text[:head] + "\n".join(racing_markdown(racing, sides)) + "\n" + text[head:]


def _held_out(ev: Evaluations) -> dict[str, Any]:
    """The learned methods' self-matches in each scenario and SPIRAL's head-to-head against PPO without
    self-play, raced with ``ev``'s races, seed and sides."""
    out: dict[str, Any] = {"runs": ev.protocol.runs, "seed": ev.protocol.seed}
    for scenario in SCENARIOS:
        rows = {method: ev.self_match(scenario, method) for method in MODE_OF}
        a, b = rows["spiral"].checkpoint, rows["noselfplay"].checkpoint
        duel = ev.cross(scenario, ("spiral", a), ("noselfplay", b)) if a is not None and b is not None else None
        out[scenario] = {"rows": rows, "duel": duel}
    return out


def _cross_matrix(ev: Evaluations, scenario: str, rows: list[RowResult], *, planner: bool = True) -> dict[str, Any]:
    """Win rate (and draws) of each row team against each column team; None where not run.

    Pairings are raced with the learned methods as the row team and SE-IBR as the column (from both sides, the
    planner's row is their mirror), the same races as the robustness section's. ``planner`` False leaves SE-IBR
    out (the learned methods' pairings only)."""
    methods = [(r.method, r.checkpoint) for r in rows
               if r.checkpoint is not None and (r.method != "se-ibr" or (ev.se_ibr and planner))]
    cells: dict[str, dict[str, Any]] = {}
    for row, a in sorted(methods, key=lambda item: item[1] == SE_IBR):
        cells[row] = {}
        for column, b in methods:
            if a == SE_IBR and b == SE_IBR:
                cells[row][column] = None  # two planners: minutes of solving for a number nobody asked for
                continue
            mirror = cells.get(column, {}).get(row)
            if ev.protocol.sides == "both" and mirror is not None:  # the same races, seen from the other team
                cells[row][column] = mirror if "error" in mirror else {
                    "win_rate": mirror["loss_rate"], "draws": mirror["draws"], "loss_rate": mirror["win_rate"]}
                continue
            try:
                entry = ev.cross(scenario, (row, a), (column, b))
            except ValueError as exc:  # e.g. policies with different observation layouts
                cells[row][column] = {"error": str(exc)}
                continue
            cells[row][column] = {"win_rate": entry["win_rate"], "draws": entry["draws"],
                                  "loss_rate": entry["loss_rate"]}
    return {"methods": [m for m, _ in methods], "cells": {m: cells[m] for m, _ in methods}}


def _write_figures(out_dir: Path, track: TrackSpec, stages: list[StageRun], table: dict[str, list[RowResult]],
                   bound: LapBound) -> None:
    points = []
    for scenario, rows in table.items():
        for r in rows:
            paper = PAPER[scenario][r.method]
            points.append(TradeoffPoint(METHODS[r.method], scenario, paper[0], paper[1], paper=True))
            m = r.metrics
            if m is not None and m["lap_time_mean"] is not None:
                points.append(TradeoffPoint(METHODS[r.method], scenario, m["lap_time_mean"], m["success_ratio"],
                                            lap_std=m["lap_time_std"] or 0.0, success_ci=tuple(m["success_ci95"])))
    plot_speed_vs_reliability(points, out_dir / "speed_vs_reliability.png", bound=bound.lap_time)
    logs = {s.name: read_train_log(s.train_log) if s.train_log is not None else [] for s in stages}
    plot_learning_curves({k: v for k, v in logs.items() if v}, out_dir / "learning_curves.png")
    plot_track(track, out_dir / "track.png", path=bound.positions,
               path_label=f"point-mass bound ({bound.lap_time:.2f} s)")


_CSV_FIELDS = ("scenario", "method", "lap_time_mean", "lap_time_std", "success_ratio", "success_ci95_lo",
               "success_ci95_hi", "drones", "mean_speed", "lap_over_bound", "paper_lap_time", "paper_success_ratio",
               "source", "note")


def _write_csv(path: Path, table: dict[str, list[RowResult]], bound: LapBound) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=_CSV_FIELDS)
        writer.writeheader()
        for scenario, rows in table.items():
            for r in rows:
                m = r.metrics or {}
                lap = m.get("lap_time_mean")
                ci = m.get("success_ci95", [None, None])
                writer.writerow({
                    "scenario": scenario, "method": METHODS[r.method], "lap_time_mean": lap,
                    "lap_time_std": m.get("lap_time_std"), "success_ratio": m.get("success_ratio"),
                    "success_ci95_lo": ci[0], "success_ci95_hi": ci[1], "drones": m.get("drones"),
                    "mean_speed": m.get("mean_speed"), "lap_over_bound": lap / bound.lap_time if lap else None,
                    "paper_lap_time": PAPER[scenario][r.method][0],
                    "paper_success_ratio": PAPER[scenario][r.method][1],
                    "source": r.source, "note": r.note,
                })


def _git_commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=10,
                             cwd=Path(__file__).resolve().parent)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return out.stdout.strip() if out.returncode == 0 else "unknown"


_FIGURES_HEADING = "## Lap-time reference"
"""The robustness sections go before this heading."""


@dataclass
class _Tables:
    """What the report's own sections show."""

    table: dict[str, list[RowResult]]
    """Scenario -> the paper's rows."""
    matrices: dict[str, Any]
    """Scenario -> cross-play matrix (empty without cross-play)."""
    held: dict[str, Any] | None
    """The held-out check, when raced."""
    filtered: dict[str, list[RowResult]]
    """Scenario -> the rows raced with the separation filter."""


def _markdown(run_root: Path, track: TrackSpec, stages: list[StageRun], tables: _Tables, bound: LapBound,
              o: ReportOptions) -> str:
    """``results.md`` without the robustness and racing sections; ``o`` with the races and seed actually used."""
    assert o.runs is not None and o.seed is not None
    lines = _intro(run_root, track, stages, o)
    for scenario in SCENARIOS:
        lines += _scenario_section(scenario, tables, bound, o.separation)
    if tables.matrices:
        lines += _cross_section(tables.matrices)
    if tables.held is not None:
        lines += _held_out_section(tables.held, o.seed, o.sides)
    lines += [*_bound_section(bound), *_FIGURES]
    notes = [f"- {METHODS[r.method]}, {scenario}: {r.note}" for scenario in SCENARIOS for r in tables.table[scenario]
             if r.note]
    if notes:
        lines += ["## Missing", "", *notes, ""]
    sources = sorted({r.source for rows in tables.table.values() for r in rows if r.source})
    if sources:
        lines += ["## Sources", "", *[f"- `{s}`" for s in sources], ""]
    return "\n".join(lines)


def _intro(run_root: Path, track: TrackSpec, stages: list[StageRun], o: ReportOptions) -> list[str]:
    """Title, where the results come from and how every method raced."""
    assert o.runs is not None and o.seed is not None
    return [f"# Results: `{run_root.name}` on {track.name}", "",
            f"Generated by `{o.command or f'spiral report {run_root}'}` at commit `{_git_commit()}` from "
            f"`{run_root}` (stages: {', '.join(s.name for s in stages) or 'none'}).",
            f"Every method raced {o.runs} times per scenario from seeded random start placements (seed {o.seed}), "
            f"identical for every method and on any device; learned policies raced on `{o.device}`, SE-IBR on the "
            "CPU. Lap time: mean ± std over drones that finished without a collision; "
            "success ratio: drones that finished, with its 95% interval taking a race (not a drone) as the unit; "
            "races all home: share of races in which every drone finished; lap / bound: lap time over the "
            "point-mass reference.",
            _flight_stack(stages), _sides_text(o.sides, o.runs), ""]


_TITLES = {"1v1": "Two-drone (1v1) race: the paper's protocol",
           "2v2": "Four-drone (2v2) team race: the paper's protocol"}
"""Heading of each scenario's table."""


def _scenario_section(scenario: str, tables: _Tables, bound: LapBound, separation: SeparationCfg | None) -> list[str]:
    """One scenario's table: the paper's rows beside ours, the rows raced with the separation filter and the
    planner's cost."""
    lines = [f"## {_TITLES[scenario]}", "",
             "| Method | Lap Time (s) | Success Ratio | Races all home | Lap / bound | Paper: Lap Time (s) "
             "| Paper: Success Ratio |",
             "|---|---|---|---|---|---|---|"]
    for r in tables.table[scenario]:
        paper = PAPER[scenario][r.method]
        lap, success, races, ratio = _cells(r, bound)
        lines.append(f"| {METHODS[r.method]} | {lap} | {success} | {races} | {ratio} | {paper[2]} | {paper[3]} |")
    for r in (tables.filtered or {}).get(scenario, []):
        lap, success, races, ratio = _cells(r, bound)
        lines.append(f"| {METHODS[r.method]} {FILTER_ROW} | {lap} | {success} | {races} | {ratio} | – | – |")
    if tables.filtered and separation is not None:
        lines += ["", f"{FILTER_ROW}: the same checkpoints with a separation filter between policy and PID on "
                  f"every drone (targets shifted away from drones predicted within {separation.distance} m in "
                  f"the next {separation.horizon_s} s, by up to {separation.gain} m): an opt-in deployment "
                  "layer, not what the methods learned (docs/training.md)."]
    return [*lines, *_planning_note(tables.table[scenario]), ""]


def _bound_section(bound: LapBound) -> list[str]:
    """The lap-time reference: the point-mass bound and what it ignores."""
    lim = bound.limits
    return [_FIGURES_HEADING, "",
            f"Minimum-time lap of a point mass ({bound.airframe}: thrust ≤ {lim.thrust:.2f} m/s², tilt ≤ "
            f"{lim.tilt_deg:.0f}°, i.e. up to {lim.level:.2f} m/s² horizontally in level flight) from rest in the "
            f"start box through every gate opening and gate 0 again: **{bound.lap_time:.2f} s** "
            f"({bound.path_length:.1f} m, top speed {bound.to_json()['max_speed']:.1f} m/s). It ignores drag and "
            "attitude dynamics, so it is optimistic: a measure of how far from the physical limit a method flies. "
            "`bound.json` has the trajectory and `docs/evaluation.md` the method.", ""]


_FIGURES = ["## Figures", "", "![Speed vs. reliability](speed_vs_reliability.png)", "",
            "Lap time against success ratio, 1v1 circles, 2v2 squares; filled: this run (error bars: lap-time "
            "std, 95% interval), hollow: the paper.", "", "![Learning curves](learning_curves.png)", "",
            "![Track](track.png)", ""]
"""The figures section of ``results.md``."""


def _planning_note(rows: list[RowResult]) -> list[str]:
    """The planner's cost in this table's self-match, when its evaluation recorded one."""
    cost = next((r.metrics.get("planning") for r in rows if r.method == "se-ibr" and r.metrics), None)
    if not cost or cost.get("plan_ms_median") is None:
        return []
    return ["", f"SE-IBR planning cost: {cost['plan_ms_median']:.1f} ms median, {cost['plan_ms_p95']:.1f} ms p95 per "
            f"plan per drone (wall clock; processor time {cost['plan_cpu_ms_median']:.1f} / "
            f"{cost['plan_cpu_ms_p95']:.1f} ms) over {cost['plans']} plans."]


def _flight_stack(stages: list[StageRun]) -> str:
    """How the run's drones flew: with its stages' separation filter, or the paper's stack."""
    settings = {s.name: s.spec["stage"]["env"]["action"].get("separation") for s in stages}

    def describe(sep: dict[str, Any] | None) -> str:
        if sep is None:
            return "the paper's flight stack (no separation filter)"
        return (f"a separation filter (position targets shifted away from drones predicted within {sep['distance']} m "
                f"in the next {sep['horizon_s']} s, by up to {sep['gain']} m; docs/training.md)")

    distinct = {json.dumps(v, sort_keys=True) for v in settings.values()}
    if len(distinct) <= 1:
        return f"Every drone flew with {describe(next(iter(settings.values()), None))}."
    return "Drones flew, by stage: " + "; ".join(f"{name}: {describe(v)}" for name, v in settings.items()) + "."


def _cells(r: RowResult, bound: LapBound) -> tuple[str, str, str, str]:
    m = r.metrics
    if m is None:
        return "missing", "missing", "missing", "–"
    lo, hi = m["success_ci95"]
    success = f"{m['success_ratio']:.2f} [{lo:.2f}, {hi:.2f}]"
    races = f"{m['race_success_ratio']:.2f}" if "race_success_ratio" in m else "–"
    if m["lap_time_mean"] is None:
        return "– (no finished lap)", success, races, "–"
    return (f"{m['lap_time_mean']:.2f} ± {m['lap_time_std']:.2f}", success, races,
            f"{m['lap_time_mean'] / bound.lap_time:.2f}")


def _sides_text(sides: str, runs: int) -> str:
    """How the head-to-head races were run."""
    if sides == "both":
        return (f"Head to head (two methods, one team each), every placement is raced twice with the teams' start "
                f"slots swapped: {2 * runs} races per pairing, so neither method keeps the luckier side of the start "
                "box.")
    return f"Head to head, the row method flies team A's start slots in all {runs} races."


def _held_out_section(held: dict[str, Any], seed: int, sides: str) -> list[str]:
    side = "from both sides" if sides == "both" else "on team A"
    lines = ["## Held-out placements", "",
             f"The tables above race from the protocol's placements (seed {seed}); a setting chosen by comparing "
             f"those figures is biased towards them. The same learned policies from {held['runs']} other placements "
             f"(seed {held['seed']}): self-match success with its 95% interval, races all home and lap time; SPIRAL "
             f"({side}) against PPO No Selfplay: win / loss / draw, the share of SPIRAL's drones that finished, and "
             "its win rate in the races the other team led through the lap's first gate (from behind).",
             "", "| Scenario | PPO Selfplay (SPIRAL) | PPO No Selfplay | SPIRAL vs No Selfplay |", "|---|---|---|---|"]
    for scenario in SCENARIOS:
        cells = []
        for method in MODE_OF:
            r = held[scenario]["rows"][method]
            if r.metrics is None:
                cells.append("missing")
                continue
            m = r.metrics
            lo, hi = m["success_ci95"]
            lap = m["lap_time_mean"]
            races = f"{m['race_success_ratio']:.3f}" if "race_success_ratio" in m else "–"
            cells.append(f"{m['success_ratio']:.3f} [{lo:.2f}, {hi:.2f}], {races}, "
                         + ("no finished lap" if lap is None else f"{lap:.2f} s"))
        d = held[scenario]["duel"]
        cells.append("–" if d is None else f"{d['win_rate']:.2f} / {d['loss_rate']:.2f} / {d['draws']:.2f}; "
                     f"home {d['success_ratio']:.3f}" + _from_behind(d))
        lines.append(f"| {scenario} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def _from_behind(duel: dict[str, Any]) -> str:
    won = duel.get("first_gate", {}).get("won_when_behind")
    return "" if won is None else f"; from behind {won:.2f}"


def _cross_section(matrices: dict[str, Any]) -> list[str]:
    lines = ["## Cross-play", "",
             "Win rate of the row team against the column team (a race is won by the team whose first drone "
             "finishes first; draws: nobody finished). Same races and start placements as above.", ""]
    for scenario, mat in matrices.items():
        methods = mat["methods"]
        if not methods:
            lines += [f"{scenario}: no methods to pair.", ""]
            continue
        lines += [f"### {scenario}", "", "| row vs column | " + " | ".join(METHODS[m] for m in methods) + " |",
                  "|---" * (len(methods) + 1) + "|"]
        for row in methods:
            cells = []
            for column in methods:
                c = mat["cells"][row][column]
                cells.append("–" if c is None else "n/a" if "error" in c
                             else f"{c['win_rate']:.2f} (draws {c['draws']:.2f})")
            lines.append(f"| {METHODS[row]} | " + " | ".join(cells) + " |")
        lines.append("")
    return lines
