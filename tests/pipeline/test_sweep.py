"""Sweeps: a pipeline run once per seed, and one table of the draws' headline figures."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from spiral.core.errors import UsageError
from spiral.eval.headline import headline_figures
from spiral.eval.racing_section import Racing
from spiral.eval.runs import RowResult
from spiral.pipeline.sweep import SweepDraw, parse_seeds, run_sweep, sweep_markdown

ROOT = Path(__file__).resolve().parents[2]


def test_the_table_gives_each_seeds_figure_their_mean_and_spread():
    """Mean and spread over the seeds that have a figure; a figure missing or not finite in one seed is a dash there."""
    draws = [SweepDraw(0, Path("runs/a"), {"x/success": 0.9, "x/lap": 4.0, "y": None}),
             SweepDraw(1, Path("runs/b"), {"x/success": 0.7, "x/lap": float("nan")})]
    rows = {line.split(" | ")[0].strip("| "): line for line in sweep_markdown("full", draws, ["a.b=1"]).splitlines()
            if line.startswith("| x") or line.startswith("| y")}
    assert rows["x/success"] == "| x/success | 0.900 | 0.700 | 0.800 | 0.200 |"
    assert rows["x/lap"] == "| x/lap | 4.000 | – | 4.000 | – |"
    assert rows["y"] == "| y | – | – | – | – |"


def test_headline_figures_name_the_protocol_held_out_and_racing_figures():
    row = RowResult("1v1", "spiral", metrics={"success_ratio": 0.96, "lap_time_mean": 4.28})
    none = RowResult("1v1", "se-ibr")
    held = {"runs": 1024, "seed": 1, "1v1": {"rows": {"spiral": row}, "duel": {"win_rate": 0.8}}}
    racing = Racing(3, 1024, 1)
    racing.self_matches = {"box": {"2v2": {"spiral": RowResult("2v2", "spiral", metrics={
        "success_ratio": 0.9, "race_success_ratio": 0.75, "racing": {"flying_lap": 3.5}})}}}
    racing.duels = {"track": {"1v1": {"noselfplay": {"win_rate": 0.6, "success_ratio": 0.95}}}}
    figures = headline_figures({"1v1": [row, none]}, held, racing)
    assert {name for name, value in figures.items() if value is None} == {
        "protocol/1v1/se-ibr/success", "protocol/1v1/se-ibr/lap_time"}
    assert {name: value for name, value in figures.items() if value is not None} == pytest.approx({
        "protocol/1v1/spiral/success": 0.96, "protocol/1v1/spiral/lap_time": 4.28,
        "held_out/1v1/spiral/success": 0.96, "held_out/1v1/duel/win_rate": 0.8,
        "racing/box/2v2/spiral/success": 0.9, "racing/box/2v2/spiral/all_home": 0.75,
        "racing/box/2v2/spiral/flying_lap": 3.5,
        "racing/track/1v1/vs-noselfplay/win_rate": 0.6, "racing/track/1v1/vs-noselfplay/home": 0.95})


def test_seeds_are_integers_given_once_and_a_sweep_sets_them_itself(tmp_path):
    assert parse_seeds("0,1,7") == [0, 1, 7]
    for bad in ("0,x", "1,1"):
        with pytest.raises(UsageError, match="--seeds"):
            parse_seeds(bad)
    with pytest.raises(UsageError, match="--set seed"):
        run_sweep(ROOT / "pipelines" / "smoke.yaml", [0], ["seed=3"], runs_dir=tmp_path)


def test_a_sweep_of_two_seeds_runs_two_folders_and_tables_both(smoke_run, tmp_path, monkeypatch):
    """The smoke pipeline on seeds 0 and 1: a run folder each (named for the seed), each with its report's headline
    figures, and one summary of both. Seed 0 is the plain file's run, found finished beside it: its steps are reused
    but publishing, which writes into the draw's own folder."""
    smoke_run.copy_to(tmp_path)
    monkeypatch.chdir(tmp_path)
    logs: list[str] = []
    summary = run_sweep(ROOT / "pipelines" / "smoke.yaml", [0, 1], runs_dir=tmp_path / "runs",
                        checkpoints_dir=tmp_path / "ckpt", log=logs.append)
    reused = {line.split("'")[1] for line in logs if "reused from" in line and "/runs/smoke/" in line}
    assert reused == {name for name in smoke_run.ran if not name.startswith("publish:")}  # publishing: own folder
    assert summary == tmp_path / "runs" / "sweeps" / "smoke" / "summary.md"
    data = json.loads(summary.with_name("summary.json").read_text())
    assert [d["seed"] for d in data["draws"]] == [0, 1]
    assert [Path(d["run"]).name for d in data["draws"]] == ["smoke-seed-0", "smoke-seed-1"]
    for draw in data["draws"]:
        assert (Path(draw["run"]) / "report" / "manifest.json").exists()  # its own, or one naming a reused run
        assert 0.0 <= draw["headline"]["protocol/2v2/spiral/success"] <= 1.0
    assert "| protocol/2v2/spiral/success |" in summary.read_text()
