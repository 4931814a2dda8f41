"""``spiral report``: the paper's tables, cross-play, the lap-time reference and figures from a pipeline's run folder.

Inputs are read from ``runs/<pipeline>/``: each ``train-<stage>/spec.json`` (scenario, self-play mode, airframe,
simulator, track), ``train-<stage>/best.pt``, ``train-<stage>/train_log.jsonl`` and ``eval-<stage>/eval.json``.
SPIRAL is a self-play (``pool``) stage, PPO without self-play a ``frozen`` stage, each evaluated in its own
scenario by self-match. Evaluations the run folder lacks (a missing eval.json, cross-play, SE-IBR when asked for)
are run here with the same races and seed and cached under ``<out>/evals/`` with the checksums of the checkpoints
they used, so a second report reuses them. What can be neither found nor run is marked missing.
"""

from __future__ import annotations

import csv
import json
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from spiral.config.airframe import AIRFRAMES, AirframeCfg
from spiral.config.sim import SimCfg
from spiral.config.track import TrackSpec
from spiral.eval.bound import LapBound, lap_time_bound
from spiral.eval.evaluate import SE_IBR, check_sides, evaluate_methods
from spiral.eval.plots import TradeoffPoint, plot_learning_curves, plot_speed_vs_reliability, plot_track
from spiral.train.checkpoint import file_sha256

__all__ = ["APPROACHES", "PAPER", "StageRun", "build_report", "find_stages", "read_train_log", "track_of_run"]

APPROACHES: dict[str, str] = {"spiral": "PPO Selfplay (SPIRAL)", "se-ibr": "SE-IBR (Baseline)",
                              "noselfplay": "PPO No Selfplay"}
"""Rows of the paper's tables, by key."""

SCENARIOS = ("1v1", "2v2")

PAPER: dict[str, dict[str, tuple[float, float, str, str]]] = {
    "1v1": {"spiral": (13.7124, 0.69, "13.7124 ± 0.0005", "0.6900 ± 0.0500"),
            "se-ibr": (14.2506, 0.81, "14.2506 ± 0.2986", "0.8100 ± 0.1100"),
            "noselfplay": (16.3134, 0.80, "16.3134 ± 0.0727", "0.8000 ± 0.0200")},
    "2v2": {"spiral": (13.71, 0.56, "13.71 ± 0.01", "0.56 ± 0.01"),
            "se-ibr": (14.39, 0.62, "14.39 ± 0.33", "0.62 ± 0.22"),
            "noselfplay": (17.82, 0.31, "17.82 ± 0.27", "0.31 ± 0.12")},
}
"""The paper's Tables 1 (1v1) and 2 (2v2): lap time, success ratio, and both as printed."""

_MODE_OF = {"spiral": "pool", "noselfplay": "frozen"}


@dataclass
class StageRun:
    """One training stage found in a run folder."""

    name: str
    scenario: str
    mode: str
    """Self-play mode: ``pool`` (SPIRAL) or ``frozen`` (PPO without self-play)."""
    train_dir: Path
    eval_path: Path
    spec: dict[str, Any]

    @property
    def best(self) -> Path:
        """The stage's best policy."""
        return self.train_dir / "best.pt"


@dataclass
class _Result:
    """One cell row of a table: an approach in a scenario."""

    scenario: str
    key: str
    agent: str | None = None
    """Checkpoint path or ``se-ibr`` that produced (or can produce) the numbers."""
    metrics: dict[str, Any] | None = None
    source: str = ""
    note: str = ""


def find_stages(run_root: Path) -> list[StageRun]:
    """Stages with a ``train-<stage>/spec.json`` under ``run_root``, in name order."""
    out = []
    for spec_path in sorted(Path(run_root).glob("train-*/spec.json")):
        spec = json.loads(spec_path.read_text())
        stage = spec["stage"]
        out.append(StageRun(stage["name"], stage["scenario"], stage["selfplay"]["mode"], spec_path.parent,
                            Path(run_root) / f"eval-{stage['name']}" / "eval.json", spec))
    return out


def track_of_run(run_root: Path) -> TrackSpec:
    """The track recorded in the run folder's stage specs."""
    stages = find_stages(run_root)
    if not stages:
        raise FileNotFoundError(f"{run_root}: no train-<stage>/spec.json (is this runs/<pipeline>?)")
    return TrackSpec.model_validate(stages[0].spec["track"])


def read_train_log(path: Path) -> list[dict[str, Any]]:
    """Rows of a ``train_log.jsonl`` (a half-written last line is skipped)."""
    if not path.is_file():
        return []
    rows = []
    for line in path.read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return rows


class _Evaluations:
    """Finds evaluation results in the run folder, or runs and caches them under ``<out>/evals``."""

    def __init__(self, run_root: Path, track: TrackSpec, out_dir: Path, stages: list[StageRun], *, runs: int,
                 seed: int, device: str, se_ibr: bool, airframe: AirframeCfg, sim: SimCfg,
                 log: Callable[[str], None], prefix: str = "", sides: str = "both") -> None:
        self.run_root, self.track, self.cache, self.prefix = run_root, track, out_dir / "evals", prefix
        self.sides = sides
        self.stages, self.runs, self.seed, self.device = stages, runs, seed, device
        self.se_ibr, self.airframe, self.sim, self.log = se_ibr, airframe, sim, log

    def stage_for(self, scenario: str, key: str) -> StageRun | None:
        """The stage of approach ``key`` in ``scenario``; one named like the scenario wins a tie."""
        found = [s for s in self.stages if s.scenario == scenario and s.mode == _MODE_OF[key]]
        found.sort(key=lambda s: (s.name not in (scenario, f"{scenario}-noselfplay"), s.name))
        return found[0] if found else None

    def agent(self, scenario: str, key: str) -> str | None:
        """Checkpoint (or ``se-ibr``) of approach ``key`` in ``scenario``, if it exists."""
        if key == "se-ibr":
            return SE_IBR
        stage = self.stage_for(scenario, key)
        return str(stage.best) if stage is not None and stage.best.is_file() else None

    def self_match(self, scenario: str, key: str) -> _Result:
        """Self-match metrics of approach ``key`` in ``scenario``: found, run, or missing with a reason."""
        res = _Result(scenario, key, agent=self.agent(scenario, key))
        if key == "se-ibr":
            found = self._find_se_ibr(scenario)
            if found is not None:
                res.metrics, res.source = found
                return res
            if not self.se_ibr:
                res.note = "not evaluated: pass --se-ibr to run the planner (slow, minutes per scenario)"
                return res
        else:
            stage = self.stage_for(scenario, key)
            if stage is None:
                res.note = f"no {_MODE_OF[key]}-mode {scenario} stage in {self.run_root}"
                return res
            data = _load_json(stage.eval_path)
            if data is not None and (data["runs"], data["seed"]) == (self.runs, self.seed) and data["methods"]:
                res.metrics, res.source = next(iter(data["methods"].values())), str(stage.eval_path)
                return res
            if res.agent is None:
                res.note = f"stage '{stage.name}' has no best.pt"
                return res
        assert res.agent is not None
        data, path = self._run(f"self-{scenario}-{key}", scenario, {key: res.agent}, None)
        res.metrics, res.source = data["methods"][key], str(path)
        return res

    def cross(self, scenario: str, a: tuple[str, str], b: tuple[str, str]) -> dict[str, Any]:
        """Team ``a`` (key, agent) against team ``b``: the method entry of the evaluation JSON."""
        data, _ = self._run(f"cross-{scenario}-{a[0]}-vs-{b[0]}", scenario, {a[0]: a[1]}, b)
        return data["methods"][a[0]]

    def _find_se_ibr(self, scenario: str) -> tuple[dict[str, Any], str] | None:
        paths = [self.cache / f"self-{scenario}-se-ibr.json", *sorted(self.run_root.glob("*/eval*.json"))]
        for path in paths:
            data = _load_json(path)
            if data is None or data.get("scenario") != scenario or "against" in data:
                continue
            if (data.get("runs"), data.get("seed")) != (self.runs, self.seed):
                continue
            for entry in data.get("methods", {}).values():
                if str(entry.get("checkpoint", "")).lower() == SE_IBR:
                    return entry, str(path)
        return None

    def _run(self, tag: str, scenario: str, methods: dict[str, str],
             against: tuple[str, str] | None) -> tuple[dict[str, Any], Path]:
        """Run ``spiral eval`` for ``methods`` (optionally against a team) unless a matching cache exists."""
        agents = [*methods.values(), *([against[1]] if against else [])]
        inputs = {"track": self.track.model_dump(mode="json"), "scenario": scenario, "runs": self.runs,
                  "seed": self.seed, "agents": [a if a == SE_IBR else _checksum(Path(a)) for a in agents],
                  **({"sides": self.sides} if against else {})}
        inputs = json.loads(json.dumps(inputs))  # compare as read back: tuples become lists
        path = self.cache / f"{self.prefix}{tag}.json"
        cached = _load_json(path)
        if cached is not None and cached.get("inputs") == inputs:
            return cached, path
        self.log(f"report: running {self.prefix}{tag} ({self.runs} races, seed {self.seed})")
        data = evaluate_methods(self.track, methods, scenario=scenario, runs=self.runs, seed=self.seed,
                                device=self.device, against=against, airframe=self.airframe, sim=self.sim,
                                sides=self.sides)
        data["inputs"] = inputs
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(data, indent=2) + "\n")
        return data, path


def _load_json(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _checksum(path: Path) -> str:
    side = _load_json(path.with_suffix(".json"))
    return side["sha256"] if side and "sha256" in side else file_sha256(path)


def _protocol(stages: list[StageRun], runs: int | None, seed: int | None) -> tuple[int, int]:
    """Races and seed: as given, else those of the pipeline's stage evaluations, else 50 and 0."""
    for stage in stages:
        data = _load_json(stage.eval_path)
        if data is not None:
            return runs or data["runs"], data["seed"] if seed is None else seed
    return runs or 50, 0 if seed is None else seed


def _setup(stages: list[StageRun]) -> tuple[AirframeCfg, SimCfg]:
    for stage in stages:
        if "airframe" in stage.spec and "sim" in stage.spec:
            return AirframeCfg.model_validate(stage.spec["airframe"]), SimCfg.model_validate(stage.spec["sim"])
    return AIRFRAMES["cf2x"], SimCfg()


def build_report(run_root: Path, track: TrackSpec, out_dir: Path, *, runs: int | None = None,
                 seed: int | None = None, device: str = "cpu", se_ibr: bool = False, cross_play: bool = True,
                 airframe: AirframeCfg | None = None, bound_steps: int = 24, command: str | None = None,
                 holdout: tuple[int, int] | None = None, sides: str = "both",
                 log: Callable[[str], None] = print) -> Path:
    """Write ``results.md``, ``results.csv``, ``bound.json`` and the figures for ``run_root`` into ``out_dir``.

    Args:
        run_root: A pipeline's run folder, ``runs/<pipeline>``.
        track: The pipeline's track.
        out_dir: Folder for the report (created); evaluations run here are cached in ``out_dir/evals``.
        runs: Races per evaluation; the pipeline's (from its eval.json files) when None.
        seed: Seed of the start placements; the pipeline's when None.
        device: Device of evaluations run by the report.
        se_ibr: Run the SE-IBR planner where no evaluation of it exists (minutes per scenario on a CPU).
        cross_play: Compute the cross-play win-rate matrices (running what is missing).
        airframe: Airframe of the lap-time reference; the pipeline's when None.
        bound_steps: Mean time steps per segment of the lap-time reference.
        command: Command line quoted in results.md.
        holdout: ``(runs, seed)`` of a held-out check: the learned approaches' self-matches and their head-to-head
            raced again from other placements (cached under ``out_dir/evals/holdout-*``); None: no check.
        sides: Head-to-head races: ``both`` races every placement from both sides, ``a`` with the row method on team
            A only (see :func:`spiral.eval.evaluate.cross_play`).
        log: Progress messages.

    Returns:
        The path of ``results.md``.
    """
    check_sides(sides)
    run_root, out_dir = Path(run_root), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stages = find_stages(run_root)
    runs, seed = _protocol(stages, runs, seed)
    if holdout is not None and holdout[1] == seed:
        raise ValueError(f"holdout seed {seed} is the evaluation's own seed: held-out placements need another")
    stage_airframe, sim = _setup(stages)
    airframe = airframe or stage_airframe
    ev = _Evaluations(run_root, track, out_dir, stages, runs=runs, seed=seed, device=device, se_ibr=se_ibr,
                      airframe=airframe, sim=sim, log=log, sides=sides)
    table = {s: [ev.self_match(s, key) for key in APPROACHES] for s in SCENARIOS}
    matrices = {s: _cross_matrix(ev, s, table[s]) for s in SCENARIOS} if cross_play else {}
    held = None
    if holdout is not None:
        held = _held_out(_Evaluations(run_root, track, out_dir, stages, runs=holdout[0], seed=holdout[1],
                                      device=device, se_ibr=False, airframe=airframe, sim=sim, log=log,
                                      prefix="holdout-", sides=sides))
    bound = lap_time_bound(track, airframe, steps_per_segment=bound_steps)
    (out_dir / "bound.json").write_text(json.dumps(bound.to_json(trajectory=True), indent=2) + "\n")
    _write_figures(out_dir, track, stages, table, bound)
    _write_csv(out_dir / "results.csv", table, bound)
    text = _markdown(run_root, track, stages, table, matrices, bound, runs=runs, seed=seed, command=command,
                     held=held, sides=sides)
    (out_dir / "results.md").write_text(text)
    return out_dir / "results.md"


def _held_out(ev: _Evaluations) -> dict[str, Any]:
    """The learned approaches' self-matches in each scenario and SPIRAL's head-to-head against PPO without
    self-play, raced with ``ev``'s races, seed and sides."""
    out: dict[str, Any] = {"runs": ev.runs, "seed": ev.seed}
    for scenario in SCENARIOS:
        rows = {key: ev.self_match(scenario, key) for key in _MODE_OF}
        a, b = rows["spiral"].agent, rows["noselfplay"].agent
        duel = ev.cross(scenario, ("spiral", a), ("noselfplay", b)) if a is not None and b is not None else None
        out[scenario] = {"rows": rows, "duel": duel}
    return out


def _cross_matrix(ev: _Evaluations, scenario: str, rows: list[_Result]) -> dict[str, Any]:
    """Win rate (and draws) of each row team against each column team; None where not run."""
    agents = [(r.key, r.agent) for r in rows if r.agent is not None and (r.key != "se-ibr" or ev.se_ibr)]
    cells: dict[str, dict[str, Any]] = {}
    for ka, a in agents:
        cells[ka] = {}
        for kb, b in agents:
            if a == SE_IBR and b == SE_IBR:
                cells[ka][kb] = None  # two planners: minutes of solving for a number nobody asked for
                continue
            mirror = cells.get(kb, {}).get(ka)
            if ev.sides == "both" and mirror is not None:  # the same races, seen from the other team
                cells[ka][kb] = mirror if "error" in mirror else {
                    "win_rate": mirror["loss_rate"], "draws": mirror["draws"], "loss_rate": mirror["win_rate"]}
                continue
            try:
                entry = ev.cross(scenario, (ka, a), (kb, b))
            except ValueError as exc:  # e.g. policies with different observation layouts
                cells[ka][kb] = {"error": str(exc)}
                continue
            cells[ka][kb] = {"win_rate": entry["win_rate"], "draws": entry["draws"], "loss_rate": entry["loss_rate"]}
    return {"keys": [k for k, _ in agents], "cells": cells}


def _write_figures(out_dir: Path, track: TrackSpec, stages: list[StageRun], table: dict[str, list[_Result]],
                   bound: LapBound) -> None:
    points = []
    for scenario, rows in table.items():
        for r in rows:
            paper = PAPER[scenario][r.key]
            points.append(TradeoffPoint(APPROACHES[r.key], scenario, paper[0], paper[1], paper=True))
            m = r.metrics
            if m is not None and m["lap_time_mean"] is not None:
                points.append(TradeoffPoint(APPROACHES[r.key], scenario, m["lap_time_mean"], m["success_ratio"],
                                            lap_std=m["lap_time_std"] or 0.0, success_ci=tuple(m["success_ci95"])))
    plot_speed_vs_reliability(points, out_dir / "speed_vs_reliability.png", bound=bound.lap_time)
    logs = {s.name: read_train_log(s.train_dir / "train_log.jsonl") for s in stages}
    plot_learning_curves({k: v for k, v in logs.items() if v}, out_dir / "learning_curves.png")
    plot_track(track, out_dir / "track.png", path=bound.positions,
               path_label=f"point-mass bound ({bound.lap_time:.2f} s)")


_CSV_FIELDS = ("scenario", "approach", "lap_time_mean", "lap_time_std", "success_ratio", "success_ci95_lo",
               "success_ci95_hi", "drones", "mean_speed", "lap_over_bound", "paper_lap_time", "paper_success_ratio",
               "source", "note")


def _write_csv(path: Path, table: dict[str, list[_Result]], bound: LapBound) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=_CSV_FIELDS)
        writer.writeheader()
        for scenario, rows in table.items():
            for r in rows:
                m = r.metrics or {}
                lap = m.get("lap_time_mean")
                ci = m.get("success_ci95", [None, None])
                writer.writerow({
                    "scenario": scenario, "approach": APPROACHES[r.key], "lap_time_mean": lap,
                    "lap_time_std": m.get("lap_time_std"), "success_ratio": m.get("success_ratio"),
                    "success_ci95_lo": ci[0], "success_ci95_hi": ci[1], "drones": m.get("drones"),
                    "mean_speed": m.get("mean_speed"), "lap_over_bound": lap / bound.lap_time if lap else None,
                    "paper_lap_time": PAPER[scenario][r.key][0], "paper_success_ratio": PAPER[scenario][r.key][1],
                    "source": r.source, "note": r.note,
                })


def _git_commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=10,
                             cwd=Path(__file__).resolve().parent)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return out.stdout.strip() if out.returncode == 0 else "unknown"


def _markdown(run_root: Path, track: TrackSpec, stages: list[StageRun], table: dict[str, list[_Result]],
              matrices: dict[str, Any], bound: LapBound, *, runs: int, seed: int, command: str | None,
              held: dict[str, Any] | None = None, sides: str = "both") -> str:
    lines = [f"# Results: `{run_root.name}` on {track.name}", ""]
    lines += [f"Generated by `{command or f'spiral report {run_root}'}` at commit `{_git_commit()}` from "
              f"`{run_root}` (stages: {', '.join(s.name for s in stages) or 'none'}).",
              f"Every method raced {runs} times per scenario from seeded random start placements (seed {seed}), "
              "identical for every method. Lap time: mean ± std over drones that finished without a collision; "
              "success ratio with its 95% Wilson interval; lap / bound: lap time over the point-mass reference.",
              _flight_stack(stages), _sides_text(sides, runs), ""]
    titles = {"1v1": "Two-drone (1v1) race", "2v2": "Four-drone (2v2) team race"}
    notes: list[str] = []
    for scenario in SCENARIOS:
        lines += [f"## {titles[scenario]}", "",
                  "| Approach | Lap Time (s) | Success Ratio | Lap / bound | Paper: Lap Time (s) "
                  "| Paper: Success Ratio |",
                  "|---|---|---|---|---|---|"]
        for r in table[scenario]:
            paper = PAPER[scenario][r.key]
            lap, success, ratio = _cells(r, bound)
            if r.note:
                notes.append(f"- {APPROACHES[r.key]}, {scenario}: {r.note}")
            lines.append(f"| {APPROACHES[r.key]} | {lap} | {success} | {ratio} | {paper[2]} | {paper[3]} |")
        lines.append("")
    if matrices:
        lines += _cross_section(matrices)
    if held is not None:
        lines += _held_out_section(held, seed, sides)
    lim = bound.limits
    lines += ["## Lap-time reference", "",
              f"Minimum-time lap of a point mass ({bound.airframe}: thrust ≤ {lim.thrust:.2f} m/s², tilt ≤ "
              f"{lim.tilt_deg:.0f}°, i.e. up to {lim.level:.2f} m/s² horizontally in level flight) from rest in the "
              f"start box through every gate opening and gate 0 again: **{bound.lap_time:.2f} s** "
              f"({bound.path_length:.1f} m, top speed {bound.to_json()['max_speed']:.1f} m/s). It ignores drag and "
              "attitude dynamics, so it is optimistic: a measure of how far from the physical limit a method flies. "
              "`bound.json` has the trajectory and `docs/evaluation.md` the method.", ""]
    lines += ["## Figures", "", "![Speed vs. reliability](speed_vs_reliability.png)", "",
              "Lap time against success ratio, 1v1 circles, 2v2 squares; filled: this run (error bars: lap-time "
              "std, 95% interval), hollow: the paper.", "", "![Learning curves](learning_curves.png)", "",
              "![Track](track.png)", ""]
    if notes:
        lines += ["## Missing", "", *notes, ""]
    sources = sorted({r.source for rows in table.values() for r in rows if r.source})
    if sources:
        lines += ["## Sources", "", *[f"- `{s}`" for s in sources], ""]
    return "\n".join(lines)


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


def _cells(r: _Result, bound: LapBound) -> tuple[str, str, str]:
    m = r.metrics
    if m is None:
        return "missing", "missing", "–"
    lo, hi = m["success_ci95"]
    success = f"{m['success_ratio']:.2f} [{lo:.2f}, {hi:.2f}]"
    if m["lap_time_mean"] is None:
        return "– (no finished lap)", success, "–"
    return (f"{m['lap_time_mean']:.2f} ± {m['lap_time_std']:.2f}", success,
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
             f"(seed {held['seed']}): self-match success with its 95% interval and lap time, and SPIRAL ({side}) "
             "against PPO No Selfplay: win / loss / draw.", "",
             "| Scenario | PPO Selfplay (SPIRAL) | PPO No Selfplay | SPIRAL vs No Selfplay |", "|---|---|---|---|"]
    for scenario in SCENARIOS:
        cells = []
        for key in _MODE_OF:
            r = held[scenario]["rows"][key]
            if r.metrics is None:
                cells.append("missing")
                continue
            lo, hi = r.metrics["success_ci95"]
            lap = r.metrics["lap_time_mean"]
            cells.append(f"{r.metrics['success_ratio']:.3f} [{lo:.2f}, {hi:.2f}], "
                         + ("no finished lap" if lap is None else f"{lap:.2f} s"))
        d = held[scenario]["duel"]
        cells.append("–" if d is None else f"{d['win_rate']:.2f} / {d['loss_rate']:.2f} / {d['draws']:.2f}")
        lines.append(f"| {scenario} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def _cross_section(matrices: dict[str, Any]) -> list[str]:
    lines = ["## Cross-play", "",
             "Win rate of the row team against the column team (a race is won by the team whose first drone "
             "finishes first; draws: nobody finished). Same races and start placements as above.", ""]
    for scenario, mat in matrices.items():
        keys = mat["keys"]
        if not keys:
            lines += [f"{scenario}: no methods to pair.", ""]
            continue
        lines += [f"### {scenario}", "", "| row vs column | " + " | ".join(APPROACHES[k] for k in keys) + " |",
                  "|---" * (len(keys) + 1) + "|"]
        for ka in keys:
            cells = []
            for kb in keys:
                c = mat["cells"][ka][kb]
                cells.append("–" if c is None else "n/a" if "error" in c
                             else f"{c['win_rate']:.2f} (draws {c['draws']:.2f})")
            lines.append(f"| {APPROACHES[ka]} | " + " | ".join(cells) + " |")
        lines.append("")
    return lines
