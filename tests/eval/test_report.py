"""Report: tables with our and the paper's numbers, missing cells, evaluations run and cached, figures, CSV."""

from __future__ import annotations

import csv
import json
import shutil
import time
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from spiral.config import AIRFRAMES, SeparationCfg, SimCfg, TrackSpec
from spiral.config.pipeline import RacingCfg
from spiral.core.files import file_sha256
from spiral.eval.evaluate import EvalLayout
from spiral.eval.report import (
    ReportOptions,
    _flight_stack,
    build_report,
    race_learned_policies,
    race_planner_pairing,
)
from spiral.eval.runs import EvalProtocol, Evaluations, RunRecord, crosses_in_workers, run_setup
from spiral.pipeline.manifest import MANIFEST
from spiral.pipeline.report_steps import read_run
from tests.eval.conftest import tiny_stage

PNG = b"\x89PNG\r\n\x1a\n"

FAKE_EVAL = {"checkpoint": "best.pt", "drones": 4, "success_ratio": 0.75, "success_ci95": [0.3, 0.95],
             "lap_time_mean": 9.87, "lap_time_std": 0.12, "mean_speed": 3.2,
             "crashes": {"ground": 0, "bounds": 0, "gate": 1, "drone": 0, "timeout": 0}}


STAGES = (("1v1", "1v1", "pool"), ("2v2-noselfplay", "2v2", "frozen"))


def declare(step_dir: Path, step: str, outputs: dict[str, Path]) -> None:
    """A manifest for ``step`` in ``step_dir`` declaring ``outputs``, as a pipeline's step writes it."""
    step_dir.mkdir(parents=True, exist_ok=True)
    declared = {key: {"path": str(path), "sha256": file_sha256(path)} for key, path in outputs.items()}
    (step_dir / MANIFEST).write_text(json.dumps({"step": step, "outputs": declared}))


def declare_caches(step_dir: Path, step: str) -> None:
    """Declare the race caches a report step wrote (``<step_dir>/evals/*.json``)."""
    declare(step_dir, step, {path.name: path for path in sorted((step_dir / "evals").glob("*.json"))})


def fake_run(root: Path, track: TrackSpec, checkpoint: Path, stages=STAGES) -> RunRecord:
    """A run folder with a self-play 1v1 stage (evaluated) and a frozen 2v2 stage (trained, not evaluated), its
    steps' outputs declared in their manifests."""
    for name, scenario, mode in stages:
        train = root / f"train-{name}"
        train.mkdir(parents=True)
        spec = {"stage": tiny_stage(scenario, name=name, mode=mode).model_dump(), "track": track.model_dump(),
                "airframe": AIRFRAMES["cf2x"].model_dump(), "sim": SimCfg().model_dump(), "device": "cpu", "seed": 0}
        (train / "spec.json").write_text(json.dumps(spec))
        shutil.copyfile(checkpoint, train / "best.pt")
        shutil.copyfile(checkpoint.with_suffix(".json"), train / "best.json")
        rows = [{"iteration": i, "reward_per_step": 0.01 * i, "success": i / 10,
                 "lap_time": float("nan") if i < 3 else 12.0 - 0.2 * i} for i in range(10)]
        (train / "train_log.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows) + '{"iteration": 1')
        declare(train, f"train:{name}", {"best": train / "best.pt", "spec": train / "spec.json",
                                         "log": train / "train_log.jsonl"})
    (root / "eval-1v1").mkdir()
    (root / "eval-1v1" / "eval.json").write_text(json.dumps(
        {"track": track.name, "scenario": "1v1", "runs": 2, "seed": 0, "methods": {"spiral": FAKE_EVAL}}))
    declare(root / "eval-1v1", "eval:1v1", {"eval": root / "eval-1v1" / "eval.json"})
    return read_run(root)


def test_report_builds_tables_figures_and_csv_from_a_tiny_run(sprint, tiny_checkpoint, tmp_path):
    """Fill found cells, run the missing evaluation, mark absent methods, and reuse cached runs next time."""
    root, out = tmp_path / "runs" / "tiny", tmp_path / "report"
    run = fake_run(root, sprint, tiny_checkpoint)
    logs: list[str] = []
    md_path = build_report(run, sprint, out, ReportOptions(bound_steps=8), log=logs.append)
    md = md_path.read_text()
    bound = json.loads((out / "bound.json").read_text())["lap_time"]

    # an eval.json written before races were counted has no per-race success: "–"
    ratio = f"{9.87 / bound:.2f}"
    assert f"| PPO Selfplay (SPIRAL) | 9.87 ± 0.12 | 0.75 [0.30, 0.95] | – | {ratio} | 13.7124 ± 0.0005 |" in md
    assert "| PPO No Selfplay | missing | missing | missing | – | 16.3134 ± 0.0727 | 0.8000 ± 0.0200 |" in md
    # 2 races of 4 drones, none home: the interval takes the 2 races as the unit, not the 8 drones
    assert "| PPO No Selfplay | – (no finished lap) | 0.00 [0.00, 0.66] | 0.00 | – | 17.82 ± 0.27 | 0.31 ± 0.12 |" in md
    assert "no pool-mode 2v2 stage" in md and "pass --se-ibr" in md
    assert "Every drone flew with the paper's flight stack (no separation filter)." in md
    assert md.count("(draws ") == 2  # one pairing per scenario: each scenario has one learned method
    assert sorted(logs) == sorted(["report: running cross-1v1-spiral-vs-spiral (2 races, seed 0)",
                            "report: running cross-2v2-noselfplay-vs-noselfplay (2 races, seed 0)",
                            *(f"report: running self-{s}-{k}-final (2 races, seed 0)" for s in ("1v1", "2v2")
                              for k in ("noselfplay", "spiral")),
                            "report: running self-1v1-spiral-downwash (2 races, seed 0)",
                            "report: running self-2v2-noselfplay (2 races, seed 0)",
                            "report: running self-2v2-noselfplay-downwash (2 races, seed 0)",
                            *(f"report: running self-solo-{k}-final (2 races, seed 0)"
                              for k in ("noselfplay", "spiral"))])

    with open(out / "results.csv") as f:
        rows = {(r["scenario"], r["method"]): r for r in csv.DictReader(f)}
    assert len(rows) == 6
    spiral = rows[("1v1", "PPO Selfplay (SPIRAL)")]
    assert float(spiral["lap_time_mean"]) == pytest.approx(9.87)  # through the CSV
    assert float(spiral["paper_lap_time"]) == pytest.approx(13.7124)  # the paper's number
    assert float(spiral["lap_over_bound"]) == pytest.approx(9.87 / bound, rel=1e-12)
    frozen = rows[("2v2", "PPO No Selfplay")]
    assert int(frozen["drones"]) == 8 and frozen["source"].endswith("evals/self-2v2-noselfplay.json")
    assert rows[("2v2", "SE-IBR (Baseline)")]["success_ratio"] == ""

    for name in ("speed_vs_reliability.png", "learning_curves.png", "track.png"):
        assert (out / name).read_bytes()[:8] == PNG

    again: list[str] = []
    second = build_report(run, sprint, out, ReportOptions(bound_steps=8), log=again.append).read_text()
    assert second.split("\n")[3:] == md.split("\n")[3:]  # line 3 names the git commit, which others may move
    assert again == []


def test_report_states_the_separation_filter_the_stages_flew_with(sprint, tiny_checkpoint, tmp_path):
    root = tmp_path / "runs" / "tiny"
    fake_run(root, sprint, tiny_checkpoint)
    spec_path = root / "train-1v1" / "spec.json"
    spec = json.loads(spec_path.read_text())
    spec["stage"]["env"]["action"]["separation"] = {"distance": 0.25, "horizon_s": 0.4, "gain": 1.5}
    spec_path.write_text(json.dumps(spec))
    stages = read_run(root).stages
    assert _flight_stack(stages) == (
        "Drones flew, by stage: 1v1: a separation filter (position targets shifted away from drones predicted within "
        "0.25 m in the next 0.4 s, by up to 1.5 m; docs/training.md); 2v2-noselfplay: the paper's flight stack (no "
        "separation filter).")
    assert _flight_stack(stages[:1]).startswith("Every drone flew with a separation filter (")


def test_report_races_the_learned_policies_again_from_held_out_placements(sprint, tiny_checkpoint, tmp_path):
    """Race self-matches and SPIRAL against no-self-play from other placements, cached apart from the protocol's."""
    root, out = tmp_path / "runs" / "tiny", tmp_path / "report"
    run = fake_run(root, sprint, tiny_checkpoint, stages=(*STAGES, ("1v1-noselfplay", "1v1", "frozen")))
    logs: list[str] = []
    md = build_report(run, sprint, out,
                      ReportOptions(bound_steps=8, cross_play=False, holdout=(3, 7)), log=logs.append).read_text()

    assert "report: running holdout-self-1v1-spiral (3 races, seed 7)" in logs  # not the eval.json of seed 0
    self_1v1 = json.loads((out / "evals" / "holdout-self-1v1-spiral.json").read_text())
    assert (self_1v1["runs"], self_1v1["seed"]) == (3, 7)
    spiral = self_1v1["methods"]["spiral"]
    duel = json.loads((out / "evals" / "holdout-cross-1v1-spiral-vs-noselfplay.json").read_text())["methods"]["spiral"]
    section = md[md.index("## Held-out placements"):]
    row = next(line for line in section.splitlines() if line.startswith("| 1v1 |"))
    lo, hi = spiral["success_ci95"]
    assert row.split(" | ")[1].startswith(f"{spiral['success_ratio']:.3f} [{lo:.2f}, {hi:.2f}]")
    behind = duel["first_gate"]["won_when_behind"]  # None when the other team never led through the first gate
    assert row.endswith(f"| {duel['win_rate']:.2f} / {duel['loss_rate']:.2f} / {duel['draws']:.2f}; "
                        f"home {duel['success_ratio']:.3f}{'' if behind is None else f'; from behind {behind:.2f}'} |")
    assert "| 2v2 | missing |" in section and section.split("| 2v2 |")[1].split("\n")[0].endswith("| – |")
    assert "(seed 7)" in section and "protocol's placements (seed 0)" in section

    with pytest.raises(ValueError, match="holdout seed 0"):
        build_report(run, sprint, out, ReportOptions(bound_steps=8, cross_play=False, holdout=(3, 0)))


def test_report_races_each_pairing_once_when_both_sides_are_raced(sprint, tiny_checkpoint, tmp_path):
    """From both sides, B's row against A is A's row against B read from the other team; team-A-only races both."""
    root = tmp_path / "runs" / "tiny"
    run = fake_run(root, sprint, tiny_checkpoint, stages=(*STAGES, ("1v1-noselfplay", "1v1", "frozen")))
    logs: list[str] = []
    md = build_report(run, sprint, tmp_path / "both", ReportOptions(bound_steps=8), log=logs.append).read_text()
    crosses = sorted(line.split("running ")[1].split(" (")[0] for line in logs if "cross-1v1" in line)
    assert crosses == ["cross-1v1-noselfplay-vs-noselfplay", "cross-1v1-spiral-vs-noselfplay",
                       "cross-1v1-spiral-vs-spiral"]
    assert "every placement is raced twice with the teams' start slots swapped: 4 races per pairing" in md
    cached = tmp_path / "both" / "evals" / "cross-1v1-spiral-vs-noselfplay.json"
    duel = json.loads(cached.read_text())
    assert duel["sides"] == "both" and duel["races"] == 4
    duel["methods"]["spiral"].update(win_rate=0.75, loss_rate=0.25, draws=0.0)  # the hovering policies never finish
    cached.write_text(json.dumps(duel))
    md = build_report(run, sprint, tmp_path / "both", ReportOptions(bound_steps=8), log=logs.append).read_text()
    rows = md[md.index("### 1v1"):].splitlines()
    spiral_row = next(r for r in rows if r.startswith("| PPO Selfplay (SPIRAL) |"))
    other_row = next(r for r in rows if r.startswith("| PPO No Selfplay |"))
    assert spiral_row.split(" | ")[2] == "0.75 (draws 0.00) |"
    assert other_row.split(" | ")[1] == "0.25 (draws 0.00)"

    logs.clear()
    md = build_report(run, sprint, tmp_path / "a",
                      ReportOptions(bound_steps=8, sides="a"), log=logs.append).read_text()
    assert sum("cross-1v1" in line for line in logs) == 4
    assert "the row method flies team A's start slots in all 2 races" in md
    with pytest.raises(ValueError, match="sides"):
        build_report(run, sprint, tmp_path / "a", ReportOptions(bound_steps=8, sides="swap"))


def test_report_races_the_filter_rows_final_policies_strangers_and_downwash(sprint, tiny_checkpoint, tmp_path):
    """Filter rows fly the same checkpoints with the filter; each method's final policy races every scenario; a pairing
    of the two methods is raced once and read from both teams; mixed teams split each team between the methods;
    downwash is switched on for every drone. All from the held-out placements, cached with what changed."""
    root, out = tmp_path / "runs" / "tiny", tmp_path / "report"
    run = fake_run(root, sprint, tiny_checkpoint, stages=(*STAGES, ("1v1-noselfplay", "1v1", "frozen"),
                                                    ("2v2", "2v2", "pool")))
    separation = SeparationCfg(distance=0.25, horizon_s=0.4, gain=1.5)
    md = build_report(run, sprint, out,
                      ReportOptions(bound_steps=8, cross_play=False, holdout=(2, 5), separation=separation),
                      log=lambda _: None).read_text()
    evals = out / "evals"
    filtered = json.loads((evals / "self-1v1-spiral-filter.json").read_text())
    assert filtered["flight"] == {"separation": separation.model_dump()} and filtered["runs"] == 2
    assert "| PPO Selfplay (SPIRAL) + separation filter |" in md and "| PPO No Selfplay + separation filter |" in md

    final = json.loads((evals / "holdout-self-solo-spiral-final.json").read_text())
    assert final["methods"]["spiral"]["checkpoint"].endswith("train-2v2/best.pt") and final["seed"] == 5
    every_scenario = md[md.index("## One policy for every scenario"):].splitlines()
    assert "(SPIRAL: stage 2v2, PPO No Selfplay: stage 2v2-noselfplay)" in every_scenario[2]
    assert sum(line.startswith(("| SPIRAL |", "| PPO No Selfplay |")) for line in every_scenario[:9]) == 2

    duel = json.loads((evals / "holdout-cross-1v1-spiral-vs-noselfplay.json").read_text())["methods"]["spiral"]
    assert not (evals / "holdout-cross-1v1-noselfplay-vs-spiral.json").exists()
    strangers = md[md.index("## Racing strangers"):md.index("## Downwash")]
    row = next(r for r in strangers.splitlines() if r.startswith("| 1v1 | PPO No Selfplay | SPIRAL |"))
    assert row.endswith(f"| {duel['loss_rate']:.2f} / {duel['win_rate']:.2f} / {duel['draws']:.2f} |")
    baseline = json.loads((evals / "holdout-cross-1v1-spiral-vs-noselfplay.json").read_text())["methods"]["spiral"][
        "opponent"]  # the baseline's drones, read from the same races
    where, fault, passes = baseline["contact_bearing"], baseline["contact_fault"], baseline["passes"]
    assert (f"| {where['ahead']} / {where['beside']} / {where['behind']} | "
            f"{fault['own']} / {fault['even']} / {fault['other']} | "
            f"{passes['made_per_race']:.2f} / {passes['suffered_per_race']:.2f} |") in row
    # the baseline's passes made are the passes SPIRAL's drones suffered in the same races
    assert passes["made"] == duel["passes"]["suffered"] and passes["suffered"] == duel["passes"]["made"]
    mixed = json.loads((evals / "holdout-mixed-2v2-spiral-noselfplay.json").read_text())
    assert mixed["methods"]["spiral"]["slots"] == [0, 2] and mixed["methods"]["noselfplay"]["slots"] == [1, 3]
    assert "| 2v2 | SPIRAL | mixed teams |" in strangers
    # The filter on one method's drones only: raced once per team it is on, each read from the filtered team.
    for team, key, other in (("a", "SPIRAL", "PPO No Selfplay"), ("b", "PPO No Selfplay", "SPIRAL")):
        one = json.loads((evals / f"holdout-cross-1v1-spiral-vs-noselfplay-filter-{team}.json").read_text())
        assert one["flight"] == {"separation": separation.model_dump(), "separation_team": team}
        entry = one["methods"]["spiral"] if team == "a" else one["methods"]["spiral"]["opponent"]
        row = next(r for r in strangers.splitlines()
                   if r.startswith(f"| 1v1 | {key} | {other}, + separation filter on own drones |"))
        assert f"| {entry['crashes']['gate']} / {entry['crashes']['drone']} |" in row
    assert "+ separation filter on own drones: the method's drones fly with" in strangers

    downwash = json.loads((evals / "holdout-self-2v2-noselfplay-downwash.json").read_text())
    assert downwash["flight"] == {"downwash": True}
    assert md.index("## Downwash (zero-shot)") < md.index("## Lap-time reference")


def test_racing_section_races_final_policies_over_laps_from_box_and_track_ahead_of_the_paper_tables(
        sprint, tiny_checkpoint, tmp_path):
    """The racing section races each final policy in every scenario and SPIRAL's duel with the baseline, over the
    section's laps from the held-out placements, once from the box and once from track starts (cached apart), and
    leads the report; without held-out placements it is refused."""
    root, out = tmp_path / "runs" / "tiny", tmp_path / "report"
    run = fake_run(root, sprint, tiny_checkpoint, stages=(*STAGES, ("1v1-noselfplay", "1v1", "frozen"),
                                                    ("2v2", "2v2", "pool")))
    racing = RacingCfg(laps=2)
    md = build_report(run, sprint, out,
                      ReportOptions(bound_steps=8, cross_play=False, robustness=False, holdout=(2, 5), racing=racing),
                      log=lambda _: None).read_text()
    evals = out / "evals"
    box = json.loads((evals / "racing-2laps-box-self-solo-spiral-final.json").read_text())
    track = json.loads((evals / "racing-2laps-track-self-solo-spiral-final.json").read_text())
    assert (box["laps"], box["runs"], box["seed"], "flight" in box) == (2, 2, 5, False)
    assert track["laps"] == 2 and track["flight"] == {"starts": "track"}
    assert box["methods"]["spiral"]["checkpoint"].endswith("train-2v2/best.pt")
    assert box["methods"]["spiral"]["racing"]["laps"] == 2
    duel = json.loads((evals / "racing-2laps-track-cross-2v2-spiral-vs-noselfplay.json").read_text())
    assert duel["inputs"]["track"]["laps"] == 2 and duel["races"] == 4  # both sides
    section = md[md.index("## Racing: 2-lap races"):md.index("## Two-drone (1v1) race: the paper's protocol")]
    rows = [line for line in section.splitlines() if line.startswith(("| start box |", "| track starts |"))]
    assert len(rows) == 2 * 3 * 2 + 2 * 2  # starts x scenarios x methods self-matches, starts x scenarios duels
    solo = next(r for r in rows if r.startswith("| start box | solo | SPIRAL |"))
    assert solo.split(" | ")[8:11] == ["–", "–", "–"]  # no overtakes, lead changes or winner in a solo race
    d = duel["methods"]["spiral"]
    row = next(r for r in rows if r.startswith("| track starts | 2v2 | PPO No Selfplay | 4 |"))
    assert f"| {d['win_rate']:.2f} / {d['loss_rate']:.2f} / {d['draws']:.2f} | {d['success_ratio']:.3f} |" in row
    assert "against SE-IBR" not in section

    with pytest.raises(ValueError, match="held-out placements"):
        build_report(run, sprint, out, ReportOptions(bound_steps=8, cross_play=False, racing=racing))


def test_racing_section_races_spirals_duels_against_se_ibr_with_the_planner(sprint, tiny_checkpoint, tmp_path):
    """With the planner, SPIRAL's final policy duels SE-IBR over the section's laps from the first ``planner_runs``
    held-out placements, both sides, and the duel is a row of the section."""
    root, out = tmp_path / "runs" / "tiny", tmp_path / "report"
    run = fake_run(root, sprint, tiny_checkpoint, stages=(*STAGES, ("2v2", "2v2", "pool")))
    racing = RacingCfg(laps=2, starts=["box"], planner_runs=1)
    md = build_report(run, sprint, out,
                      ReportOptions(bound_steps=8, cross_play=False, robustness=False, holdout=(2, 5), racing=racing,
                                    se_ibr=True),
                      log=lambda _: None).read_text()
    duel = json.loads((out / "evals" / "racing-2laps-box-cross-1v1-spiral-vs-se-ibr.json").read_text())
    assert (duel["runs"], duel["races"], duel["seed"], duel["laps"]) == (1, 2, 5, 2)
    section = md[md.index("## Racing: 2-lap races"):md.index("## Two-drone (1v1) race")]
    assert "against SE-IBR from the first 1 of the placements" in section
    assert any(line.startswith("| start box | 1v1 | SE-IBR | 2 |") for line in section.splitlines())
    assert not any(line.startswith("| start box | 2v2 | SE-IBR |") for line in section.splitlines())


def test_report_races_se_ibr_in_both_tables_and_prints_its_planning_cost(sprint, tiny_checkpoint, tmp_path):
    """With ``se_ibr`` the planner is a row of both tables, paired with every learned method, with its cost per plan."""
    root = tmp_path / "runs" / "tiny"
    run = fake_run(root, sprint, tiny_checkpoint)
    logs: list[str] = []
    md = build_report(run, sprint, tmp_path / "out",
                      ReportOptions(bound_steps=8, se_ibr=True, robustness=False, jobs=2), log=logs.append).read_text()
    for scenario in ("1v1", "2v2"):
        table = md[md.index(f"({scenario}) "):md.index("## ", md.index(f"({scenario}) "))]
        row = next(r for r in table.splitlines() if r.startswith("| SE-IBR (Baseline) |"))
        assert "missing" not in row and "n/a" not in row
        assert "SE-IBR planning cost:" in table and " ms median, " in table
    cross = md[md.index("## Cross-play"):md.index("## Lap-time reference")].splitlines()
    assert sum(line.startswith("| SE-IBR (Baseline) |") for line in cross) == 2  # a row of each scenario's matrix
    assert any("cross-1v1-spiral-vs-se-ibr" in line for line in logs)
    cached = json.loads((tmp_path / "out" / "evals" / "self-2v2-se-ibr.json").read_text())
    cost = cached["methods"]["se-ibr"]["planning"]
    assert cost["plans"] > 0 and 0 < cost["plan_ms_median"] <= cost["plan_ms_p95"]


@pytest.mark.bitwise
def test_a_report_finds_what_steps_raced_ahead_in_the_run_folder_and_writes_the_same(sprint, tiny_checkpoint,
                                                                                      tmp_path):
    """The races among learned policies and each planner pairing, raced ahead into folders of their own in the run
    folder (as a pipeline's steps race them), are found by the report: it races nothing and writes the results.md of
    a report that raced everything itself."""
    stages = (*STAGES, ("1v1-noselfplay", "1v1", "frozen"), ("2v2", "2v2", "pool"))
    options = ReportOptions(bound_steps=8, holdout=(2, 5), separation=SeparationCfg(distance=0.25, horizon_s=0.4,
                                                                                      gain=1.5))
    reference_root, root = tmp_path / "alone" / "tiny", tmp_path / "runs" / "tiny"
    reference_run, run = (fake_run(folder, sprint, tiny_checkpoint, stages=stages) for folder in (reference_root, root))
    reference = build_report(reference_run, sprint, reference_root / "report", replace(options, se_ibr=True, jobs=2),
                             log=lambda _: None).read_text()
    planner = root / "eval-se-ibr"
    planner.mkdir()
    for scenario in ("1v1", "2v2"):  # the planner's self-matches, as the pipeline's eval:se-ibr step writes them
        shutil.copyfile(reference_root / "report" / "evals" / f"self-{scenario}-se-ibr.json",
                        planner / f"eval-{scenario}.json")
    declare(planner, "eval:se-ibr", {f"eval_{s}": planner / f"eval-{s}.json" for s in ("1v1", "2v2")})
    race_learned_policies(run, sprint, root / "eval-report", ReportOptions(holdout=(2, 5),
                                                                         separation=options.separation),
                          log=lambda _: None)
    declare_caches(root / "eval-report", "eval:report")
    for name, scenario, mode in stages:
        key = "spiral" if mode == "pool" else "noselfplay"
        entry = race_planner_pairing(run, sprint, root / f"eval-se-ibr-vs-{name}", scenario, key, log=lambda _: None)
        assert {"win_rate", "opponent"} <= set(entry)
        declare_caches(root / f"eval-se-ibr-vs-{name}", f"eval:se-ibr-vs-{name}")
    logs: list[str] = []
    md = build_report(read_run(root), sprint, root / "report", replace(options, se_ibr=True, jobs=2),
                      log=logs.append).read_text()
    assert not [line for line in logs if line.startswith("report: running")]
    # the same report but for its list of sources: each number now read from the folder it was raced in
    head, sources = md.split("## Sources")
    assert head.replace(str(root), "RUN") == reference.split("## Sources")[0].replace(str(reference_root), "RUN")
    found = [Path(line.strip("- `")) for line in sources.strip().splitlines()]
    assert {path.parent.parent.name for path in found if path.parent.name == "evals"} == {"eval-report"}
    assert all(path.is_file() and root in path.parents for path in found)
    # a step's caches are read only when its manifest declares them
    (root / "eval-report" / MANIFEST).unlink()
    assert not [path for path in read_run(root).evaluations if "eval-report" in path.parts]
    with pytest.raises(FileNotFoundError, match=r"no best\.pt of a pool-mode 1v1 stage"):
        race_planner_pairing(RunRecord(tmp_path / "alone", []), sprint, tmp_path / "x", "1v1", "spiral",
                             log=lambda _: None)


def _evaluations(run: RunRecord, track: TrackSpec, out: Path, logs: list[str]) -> Evaluations:
    airframe, sim = run_setup(run.stages)
    protocol = EvalProtocol(track, 2, 0, EvalLayout.default(airframe=airframe, sim=sim))
    return Evaluations(run, out, protocol, device="cpu", se_ibr=False, log=logs.append)


def test_pairings_race_in_workers_while_the_body_of_the_with_runs(sprint, tiny_checkpoint, tmp_path):
    """The workers' pairings are cached when the ``with`` ends, and the body ran (on one torch thread) before any of
    them was done, so the report's own races overlap the planner's."""
    root = tmp_path / "runs" / "tiny"
    run = fake_run(root, sprint, tiny_checkpoint)
    logs: list[str] = []
    ev = _evaluations(run, sprint, tmp_path / "out", logs)
    ckpt = ev.checkpoint("1v1", "spiral")
    pairings = [("1v1", ("spiral", ckpt), ("noselfplay", ckpt)), ("2v2", ("spiral", ckpt), ("noselfplay", ckpt))]
    threads = torch.get_num_threads()
    with crosses_in_workers(ev, pairings, jobs=2):
        body_started = time.time()
        assert torch.get_num_threads() == 1  # the workers have the cores
        ev.self_match("1v1", "spiral")
    assert torch.get_num_threads() == threads
    cached = [tmp_path / "out" / "evals" / f"cross-{s}-spiral-vs-noselfplay.json" for s in ("1v1", "2v2")]
    assert all(path.is_file() for path in cached)
    assert body_started < min(path.stat().st_mtime for path in cached)
    logs.clear()
    assert "win_rate" in ev.cross("2v2", ("spiral", ckpt), ("noselfplay", ckpt))
    assert not any(line.startswith("report: running") for line in logs)  # read from the workers' cache


def test_a_pairing_that_fails_in_a_worker_fails_the_with(sprint, tiny_checkpoint, tmp_path):
    root = tmp_path / "runs" / "tiny"
    run = fake_run(root, sprint, tiny_checkpoint)
    ev = _evaluations(run, sprint, tmp_path / "out", [])
    missing = str(tmp_path / "absent.pt")
    pairings = [("1v1", ("spiral", missing), ("noselfplay", missing))] * 2
    with pytest.raises(Exception, match=r"absent\.pt"), crosses_in_workers(ev, pairings, jobs=2):
        pass


def test_a_race_cache_from_another_device_is_raced_again_and_the_planners_races_are_on_the_cpu(
        sprint, tiny_checkpoint, tmp_path):
    """Races on another device give other floats: a cache records the device it raced on and is reused only for
    that device. A race with SE-IBR runs on the CPU whatever the report's device."""
    from spiral.eval.evaluate import SE_IBR, race_device

    root = tmp_path / "runs" / "tiny"
    run = fake_run(root, sprint, tiny_checkpoint)
    ev = _evaluations(run, sprint, tmp_path / "out", [])
    ckpt = ev.checkpoint("1v1", "spiral")
    ev.cross("1v1", ("spiral", ckpt), ("noselfplay", ckpt))
    cache = json.loads((tmp_path / "out" / "evals" / "cross-1v1-spiral-vs-noselfplay.json").read_text())
    assert cache["device"] == "cpu" and cache["inputs"]["device"] == "cpu"
    gpu = Evaluations(run, tmp_path / "out", ev.protocol, device="cuda:0", se_ibr=False, log=lambda _: None)
    assert ev.has_cross("1v1", ("spiral", ckpt), ("noselfplay", ckpt))
    assert not gpu.has_cross("1v1", ("spiral", ckpt), ("noselfplay", ckpt))
    assert race_device("cuda:0", [ckpt, SE_IBR]) == "cpu"
    assert race_device("cuda:0", [ckpt]) == "cuda:0"
