"""Pipelines: skip complete steps, rerun what changed, resume killed training, one run at a time."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from spiral.config import SpecError
from spiral.core.checkpoint import list_checkpoints, newest_valid_checkpoint
from spiral.pipeline import PipelineLock, PipelineLockedError, PipelineRunner

ROOT = Path(__file__).resolve().parents[2]


def runner_for(path: Path, tmp_path: Path, logs: list[str] | None = None) -> PipelineRunner:
    return PipelineRunner(path, runs_dir=tmp_path / "runs", checkpoints_dir=tmp_path / "ckpt", progress=False,
                          log=(logs.append if logs is not None else lambda _: None))


def write_pipeline(tmp_path: Path, *, iterations: int = 2, lr: float = 1e-3, stages: int = 1) -> Path:
    data = yaml.safe_load((ROOT / "pipelines" / "smoke.yaml").read_text())
    data = json.loads(json.dumps({k: v for k, v in data.items() if not k.startswith("x-")}))  # unshare anchors
    data["track"] = str(ROOT / "tracks" / "oval4.yaml")
    data["report"] = {"enabled": False}
    data["stages"] = data["stages"][:stages]
    data["stages"][0]["iterations"] = iterations
    data["stages"][0]["ppo"]["learning_rate"] = lr
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.bitwise
def test_smoke_pipeline_twice_skips_every_step_the_second_time(smoke_run, tmp_path, monkeypatch):
    """Run smoke.yaml end to end, then again: the second run runs nothing and publishes the final policies. With
    every file no manifest declares deleted, every step runs again to the same training outputs."""
    logs: list[str] = []
    smoke_run.copy_to(tmp_path)
    monkeypatch.chdir(tmp_path)
    first = smoke_run.ran
    here = Path()  # the copy's manifests name their files relative to it, and its publishing folder so
    assert first == [s.name for s in runner_for(ROOT / "pipelines" / "smoke.yaml", here).steps]
    second = runner_for(ROOT / "pipelines" / "smoke.yaml", here, logs).run()
    assert second == []
    assert sum("unchanged, skipping" in line for line in logs) == len(first)
    published = tmp_path / "ckpt" / "smoke"
    for name in ("spiral.pt", "ppo-noselfplay.pt", "solo/best.pt", "solo/eval.json", "pool/pool.json"):
        assert (published / name).is_file(), name
    assert json.loads((published / "solo" / "eval.json").read_text())["runs"] == 2
    outputs = {d.name: json.loads((d / "manifest.json").read_text())["outputs"]
               for d in (tmp_path / "runs" / "smoke").glob("train-*")}
    assert {name for name, out in outputs.items() if "pool" in out} == {"train-1v1", "train-2v2"}  # self-play only
    members = {name: [m["id"] for m in json.loads(Path(outputs[name]["pool"]["path"]).read_text())["members"]]
               for name in ("train-1v1", "train-2v2")}
    assert members["train-2v2"][:len(members["train-1v1"])] == members["train-1v1"]  # read from the declared pool

    # every step reads only what its input steps declared: with every other file gone (a declared pool's members,
    # pinned by their checksums in it, count as declared), each runs again and the stages train the same policies
    _keep_only_declared(tmp_path / "runs" / "smoke", keep=set())
    assert runner_for(ROOT / "pipelines" / "smoke.yaml", here).run(force=first) == first
    again = {d.name: json.loads((d / "manifest.json").read_text())["outputs"]
             for d in (tmp_path / "runs" / "smoke").glob("train-*")}
    assert {(name, key): _resolved(again[name][key]) for name in outputs for key in ("best", "last")} == {
        (name, key): _resolved(outputs[name][key]) for name in outputs for key in ("best", "last")}


def _resolved(output: dict) -> tuple[Path, str]:
    """A manifest's output entry as its file's absolute path and checksum."""
    return Path(output["path"]).resolve(), output["sha256"]


def test_no_self_play_2v2_stage_waits_for_the_stage_its_frozen_opponent_comes_from(tmp_path):
    """smoke.yaml's 2v2-noselfplay starts from 1v1-noselfplay and races the solo best: it needs both."""
    steps = {s.name: s for s in runner_for(ROOT / "pipelines" / "smoke.yaml", tmp_path).steps}
    assert steps["train:2v2-noselfplay"].inputs == ["train:1v1-noselfplay", "train:solo"]
    assert steps["train:1v1-noselfplay"].inputs == ["train:solo"]
    assert steps["train:2v2"].inputs == ["train:1v1"]


def test_a_step_run_alone_before_the_steps_it_reads_is_refused_naming_them(tmp_path):
    """--only train:1v1 before train:solo has run: one line names the missing step and the way on; nothing runs."""
    from spiral.core.errors import UsageError

    path = write_pipeline(tmp_path, stages=2)
    with pytest.raises(UsageError, match=r"step 'train:1v1' reads train:solo, not complete: run it first "
                                         r"\(--only train:solo\)"):
        runner_for(path, tmp_path).run(only="train:1v1")
    assert not list((tmp_path / "runs").glob("*/train-1v1"))


def test_changing_a_stage_parameter_reruns_that_step_and_downstream_only(tmp_path):
    """Rerun train, eval and promote of a changed stage and nothing upstream of it."""
    path = write_pipeline(tmp_path, stages=2)
    assert len(runner_for(path, tmp_path).run()) == 6
    data = yaml.safe_load(path.read_text())
    data["stages"][1]["ppo"]["learning_rate"] = 5e-4
    path.write_text(yaml.safe_dump(data))
    runner = runner_for(path, tmp_path)
    assert [s.status for s in runner.status()][:3] == ["complete"] * 3
    assert runner.run() == ["train:1v1", "eval:1v1", "publish:1v1"]


def test_a_change_to_the_spiral_source_makes_finished_steps_stale_unless_accepted(tmp_path, monkeypatch):
    """Steps that ran with other package source are stale and rerun; --accept-code-changes keeps them knowingly."""
    from spiral.pipeline import manifest

    path = write_pipeline(tmp_path)
    assert len(runner_for(path, tmp_path).run()) == 3
    monkeypatch.setattr(manifest, "source_hash", lambda: "edited rewards.py")
    status = runner_for(path, tmp_path).status()
    assert {s.status for s in status} == {"stale"}
    assert status[0].reason == "the spiral source changed since it ran (--accept-code-changes keeps it)"
    kept = PipelineRunner(path, runs_dir=tmp_path / "runs", checkpoints_dir=tmp_path / "ckpt", progress=False,
                          log=lambda _: None, accept_code_changes=True)
    assert {s.status for s in kept.status()} == {"complete"} and kept.run() == []
    assert runner_for(path, tmp_path).run() == ["train:solo", "eval:solo", "publish:solo"]


def test_fingerprints_differ_by_source_and_share_their_spec_part():
    from spiral.pipeline.manifest import Fingerprint, fingerprint, source_hash

    assert len(source_hash()) == 64
    a, b = (fingerprint("train:solo", {"x": 1}, [Fingerprint("u", "v")], source=src) for src in ("one", "two"))
    assert a.full != b.full and a.spec == b.spec


def test_a_new_option_left_at_its_default_keeps_the_fingerprint_and_a_set_one_changes_it():
    """Specs are hashed by the fields that differ from their defaults, so adding an option keeps finished steps."""
    from pydantic import BaseModel

    from spiral.pipeline.manifest import fingerprint

    class Reward(BaseModel):
        progress: float = 1.0

    class RewardWithNewTerm(BaseModel):
        progress: float = 1.0
        new_term: float = 1.0

    def fp(reward: BaseModel):
        return fingerprint("train:1v1", {"stage": reward, "seed": 0}, [], source="same")

    before, after = fp(Reward(progress=2.0)), fp(RewardWithNewTerm(progress=2.0))
    assert (before.full, before.spec) == (after.full, after.spec)
    assert fp(RewardWithNewTerm(progress=2.0, new_term=0.0)).spec != before.spec
    assert fp(RewardWithNewTerm(progress=1.0)).spec == fp(RewardWithNewTerm()).spec  # a default set explicitly


def test_killed_training_step_resumes_and_ends_with_the_full_iteration_count(tmp_path):
    """SIGKILL `spiral run` after its first checkpoint; the rerun resumes and finishes every iteration."""
    path = write_pipeline(tmp_path, iterations=30)
    cmd = [sys.executable, "-m", "spiral.cli", "run", str(path), "--runs-dir", str(tmp_path / "runs"),
           "--checkpoints-dir", str(tmp_path / "ckpt")]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=ROOT)
    ckpt_dir = tmp_path / "runs" / "smoke" / "train-solo" / "ckpt"
    deadline = time.time() + 120
    while time.time() < deadline and _newest_valid_iteration(ckpt_dir) < 1:  # a file being written is not one
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    killed_at = int(newest_valid_checkpoint(ckpt_dir).stem.split("_")[1])  # the kill may cut the newest one short
    assert 0 < killed_at < 29
    logs: list[str] = []
    ran = runner_for(path, tmp_path, logs).run()
    assert ran[0] == "train:solo"
    assert any("resuming" in line and f"iteration {killed_at + 1}" in line for line in logs)
    assert list_checkpoints(ckpt_dir)[0][0] == 29
    rows = (tmp_path / "runs" / "smoke" / "train-solo" / "train_log.jsonl").read_text().splitlines()
    assert [json.loads(r)["iteration"] for r in rows] == list(range(30))
    manifest = json.loads((tmp_path / "runs" / "smoke" / "train-solo" / "manifest.json").read_text())
    assert manifest["info"]["iterations"] == 30


def _newest_valid_iteration(ckpt_dir: Path) -> int:
    """Iteration of the newest checkpoint in ``ckpt_dir`` that loads, -1 without one."""
    newest = newest_valid_checkpoint(ckpt_dir) if ckpt_dir.is_dir() else None
    return -1 if newest is None else int(newest.stem.split("_")[1])


def test_second_concurrent_run_is_refused(tmp_path):
    """Refuse to run a pipeline whose lock a live process holds; take over a dead process's lock."""
    path = write_pipeline(tmp_path)
    runner = runner_for(path, tmp_path)
    with PipelineLock(runner.plan.run_root / ".lock"), pytest.raises(PipelineLockedError, match="already running"):
        runner.run()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    lock = runner.plan.run_root / ".lock"
    lock.write_text(json.dumps({"pid": dead.pid, "host": os.uname().nodename, "started": 0}))
    assert runner.run()[0] == "train:solo"
    assert not lock.exists()


def test_malformed_pipeline_fails_before_any_step_runs(tmp_path):
    """Name the bad field and create no run folder."""
    path = write_pipeline(tmp_path)
    data = yaml.safe_load(path.read_text())
    data["stages"][0]["worlds"] = "many"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(SpecError, match=r"stages\.0\.worlds"):
        runner_for(path, tmp_path)
    assert not (tmp_path / "runs").exists()


def write_branching_pipeline(tmp_path: Path, **nsp_overrides) -> Path:
    """smoke.yaml's solo stage, then its 1v1 and 1v1-noselfplay stages: two branches from the solo best."""
    path = write_pipeline(tmp_path, stages=5)
    data = yaml.safe_load(path.read_text())
    data["stages"] = [data["stages"][0], data["stages"][1], {**data["stages"][3], **nsp_overrides}]
    path.write_text(yaml.safe_dump(data))
    return path


def test_failed_parallel_step_keeps_the_work_of_the_steps_running_beside_it(tmp_path):
    """A branch that fails (its init policy's observation layout is not its own) names the step and its log;
    the other branch's training finishes and stays complete, and nothing new starts after the failure."""
    from spiral.pipeline import PipelineError

    path = write_branching_pipeline(tmp_path, env={"obs": {"history_len": 2}})
    runner = runner_for(path, tmp_path)
    with pytest.raises(PipelineError, match=r"train:1v1-noselfplay' failed .*train-1v1-noselfplay\.log"):
        runner.run(jobs=2)
    status = {s.name: s.status for s in runner.status()}
    assert status["train:1v1"] == "complete"
    assert status["eval:1v1"] == "missing"
    assert "observation layout" in (runner.plan.run_root / "logs" / "train-1v1-noselfplay.log").read_text()


def test_parallel_run_trains_branches_side_by_side_restarts_a_killed_worker_then_skips_like_a_sequential_run(
        tmp_path, worker_pid, kill_once):
    """With --jobs 2, train:1v1 and train:1v1-noselfplay start together once train:solo is done, every worker on the
    run's one torch thread. train:1v1's worker, killed (SIGKILL) once it has saved a checkpoint, starts again and
    resumes from that checkpoint; every step completes, and a sequential rerun finds nothing to do."""

    path = write_branching_pipeline(tmp_path)
    data = yaml.safe_load(path.read_text())
    data["stages"][1].update(iterations=12, selfplay={"promotion": {"interval": 6, "races": 4}})
    path.write_text(yaml.safe_dump(data))
    logs: list[str] = []
    ckpt = runner_for(path, tmp_path).plan.run_root / "train-1v1" / "ckpt"

    def saved() -> bool:  # a checkpoint and its sidecar: a kill between the two files would leave nothing to resume
        return ckpt.is_dir() and newest_valid_checkpoint(ckpt) is not None

    killed = kill_once(lambda: worker_pid("train:1v1", tmp_path / "runs"), saved)
    ran = runner_for(path, tmp_path, logs).run(jobs=2)
    runner = runner_for(path, tmp_path)
    assert sorted(ran) == sorted(s.name for s in runner.steps)
    started = [line for line in logs if "started in a worker" in line]
    assert started[0].startswith("step 'train:solo' started in a worker")
    pair = {"step 'train:1v1' started", "step 'train:1v1-noselfplay' started"}
    first_pair = [i for i, line in enumerate(started) if any(line.startswith(p) for p in pair)][:2]
    assert first_pair == [1, 2] and all("(1 torch thread;" in line for line in started)
    assert any(line.startswith("[train:1v1-noselfplay] ") for line in logs)
    assert killed and any("train:1v1': its worker was killed (signal 9); starting it again" in line for line in logs)
    assert "resuming stage '1v1' from model_" in (runner.plan.run_root / "logs" / "train-1v1.log").read_text()
    assert runner.run() == []


def test_a_step_computes_with_the_runs_torch_threads_and_more_than_the_cores_are_refused(tmp_path):
    """The sequential runner trains a step with the run's torch threads (recorded in its manifest) and gives the
    process its own count back; a step of more threads than the machine has cores is refused before anything runs."""
    import torch

    from spiral.core.errors import UsageError
    from spiral.pipeline.manifest import read_manifest

    path = write_branching_pipeline(tmp_path)
    runner = runner_for(path, tmp_path)
    with pytest.raises(UsageError, match=r"--threads \d+: a step runs on one machine"):
        runner.run(jobs=2, threads=(os.cpu_count() or 1) + 1)
    assert not (runner.plan.run_root / "train-solo").exists()
    before = torch.get_num_threads()
    assert runner.run(only="train:solo", threads=1) == ["train:solo"]
    assert torch.get_num_threads() == before
    assert (read_manifest(runner.plan.run_root / "train-solo") or {})["info"]["torch_threads"] == 1


def test_held_out_check_and_head_to_head_sides_are_the_reports_alone(tmp_path):
    """Adding a held-out check or changing the head-to-head sides leaves trained and evaluated stages complete: only
    the report and its races run again."""
    path = write_pipeline(tmp_path)
    data = yaml.safe_load(path.read_text())
    data["report"] = {"enabled": True, "cross_play": False}
    path.write_text(yaml.safe_dump(data))
    runner = runner_for(path, tmp_path)
    for change in ({"holdout_runs": 4, "holdout_seed": 9}, {"sides": "a"}):
        data["evaluation"] = {**data.get("evaluation", {}), **change}
        path.write_text(yaml.safe_dump(data))
        before, after = runner._fingerprints(), runner_for(path, tmp_path)._fingerprints()
        assert list(after) == ["train:solo", "eval:solo", "publish:solo", "eval:report", "report"]
        assert [name for name in after if after[name] != before[name]] == ["eval:report", "report"]
        runner = runner_for(path, tmp_path)


def test_a_racing_section_without_held_out_placements_is_refused_before_any_step_runs(tmp_path):
    """report.racing races the held-out placements: without evaluation.holdout_runs the pipeline fails to load,
    naming the field."""
    path = write_pipeline(tmp_path)
    data = yaml.safe_load(path.read_text())
    data["report"] = {"racing": {"laps": 3}}
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(SpecError, match=r"report\.racing"):
        runner_for(path, tmp_path)


def test_the_planners_races_are_steps_that_wait_only_for_what_they_race_and_the_report_races_nothing(
        smoke_run, tmp_path, monkeypatch):
    """With report.se_ibr the planner's self-matches are a step that needs no trained policy (listed first, so that
    --jobs runs it beside the first training step), each of its head-to-head pairings a step that needs the one stage
    it races, and the report's races among learned policies a step that needs every stage but no planner; the report
    step takes them all as inputs and finds everything raced. (The trained stages are smoke.yaml's, which this
    pipeline does not change: they are kept.)"""
    smoke_run.copy_to(tmp_path)
    monkeypatch.chdir(tmp_path)
    data = yaml.safe_load((ROOT / "pipelines" / "smoke.yaml").read_text())
    data = json.loads(json.dumps({k: v for k, v in data.items() if not k.startswith("x-")}))
    data["track"] = str(ROOT / "tracks" / "oval4.yaml")
    data["report"] = {"se_ibr": True, "robustness": False,
                      "racing": {"laps": 2, "starts": ["box"], "planner_runs": 1}}
    data["evaluation"] = {"runs": 1, "seed": 0, "holdout_runs": 1, "holdout_seed": 1}
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(data))
    logs: list[str] = []
    runner = runner_for(path, tmp_path, logs)
    steps = {s.name: s for s in runner.steps}
    assert runner.steps[0].name == "eval:se-ibr" and steps["eval:se-ibr"].inputs == []
    stages = ["solo", "1v1", "2v2", "1v1-noselfplay", "2v2-noselfplay"]
    pairings = {name: s.inputs for name, s in steps.items() if name.startswith("eval:se-ibr-vs-")}
    assert pairings == {f"eval:se-ibr-vs-{stage}": [f"train:{stage}"] for stage in stages[1:]}
    assert steps["eval:se-ibr-racing"].inputs == ["train:2v2"]  # SPIRAL's final (published) stage
    assert steps["eval:report"].inputs == [f"{kind}:{stage}" for stage in stages for kind in ("train", "eval")]
    assert set(steps["report"].inputs) == {"eval:se-ibr", *pairings, "eval:se-ibr-racing",
                                           *steps["eval:report"].inputs, "eval:report"}
    assert runner.steps[-1].name == "report"

    ran = runner.run()
    assert not [name for name in ran if name.startswith("train:")]
    report_logs = logs[logs.index("step 'report' running"):]
    assert not [line for line in report_logs if line.startswith("report: running")]
    cached = tmp_path / "runs" / "smoke" / "eval-se-ibr-vs-2v2" / "evals" / "cross-2v2-spiral-vs-se-ibr.json"
    assert json.loads(cached.read_text())["inputs"]["runs"] == 1
    racing = tmp_path / "runs" / "smoke" / "eval-se-ibr-racing" / "evals"
    assert json.loads((racing / "racing-2laps-box-cross-1v1-spiral-vs-se-ibr.json").read_text())["laps"] == 2
    results = tmp_path / "runs" / "smoke" / "report" / "results.md"
    assert "## Racing: 2-lap races" in results.read_text()
    # the report reads only what its input steps declared: with every other file gone it races nothing again
    # and writes the same results
    written = results.read_text()
    _keep_only_declared(tmp_path / "runs" / "smoke", keep={"report"})
    logs.clear()
    assert runner.run(only="report", force=["report"]) == ["report"]
    assert not [line for line in logs if line.startswith("report: running")]
    assert results.read_text().split("\n")[3:] == written.split("\n")[3:]  # line 3 names the git commit
    data["report"] = {"se_ibr": False}
    path.write_text(yaml.safe_dump(data))
    assert not [name for name in (s.name for s in runner_for(path, tmp_path).steps) if name.startswith("eval:se-ibr")]


def test_overrides_run_in_folders_of_their_own_with_their_fingerprints_recorded_in_the_manifests(tmp_path):
    """`--set seed=1` names the run `smoke-seed-1...` (runs and checkpoints), changes the training step's
    fingerprint, and reaches the worker processes of a parallel run: its solo stage trains the iterations set, and
    each step's manifest records the overrides; the plain file's run stays untouched."""
    from spiral.pipeline.manifest import read_manifest

    path = write_pipeline(tmp_path, iterations=2)
    plain = runner_for(path, tmp_path)
    runner = PipelineRunner(path, runs_dir=tmp_path / "runs", checkpoints_dir=tmp_path / "ckpt", progress=False,
                            log=lambda _: None, overrides=["seed=1", "stages.solo.iterations=1"])
    assert runner.plan.run_root == tmp_path / "runs" / "smoke-seed-1_stages.solo.iterations-1"
    assert runner.plan.publish_root == tmp_path / "ckpt" / "smoke-seed-1_stages.solo.iterations-1"
    assert runner._fingerprints()["train:solo"].full != plain._fingerprints()["train:solo"].full
    assert runner.command == "spiral run " + str(path) + " --set seed=1 --set stages.solo.iterations=1"
    runner.run(jobs=2)
    manifest = read_manifest(runner.plan.run_root / "train-solo")
    assert manifest["info"]["iterations"] == 1
    assert manifest["info"]["overrides"] == ["seed=1", "stages.solo.iterations=1"]
    assert not plain.plan.run_root.exists()


def test_a_variant_reuses_the_finished_steps_another_run_has_with_the_same_fingerprint(tmp_path):
    """A variant that changes only the 1v1 stage runs in its own folder and reuses the plain run's solo steps (their
    manifests point at the plain run's files, checked by their checksums); they count as complete from then on, and
    one whose files are gone is stale."""
    from spiral.pipeline.manifest import read_manifest

    path = write_pipeline(tmp_path, iterations=2, stages=2)
    runner_for(path, tmp_path).run()
    logs: list[str] = []
    variant = PipelineRunner(path, runs_dir=tmp_path / "runs", checkpoints_dir=tmp_path / "ckpt", progress=False,
                             log=logs.append, overrides=["stages.1v1.iterations=1"])
    assert {s.name: s.reason for s in variant.status()}["train:solo"].endswith("spiral run reuses it")
    ran = variant.run()
    assert "train:1v1" in ran and not {"train:solo", "eval:solo"} & set(ran)
    assert f"step 'train:solo' reused from {tmp_path / 'runs' / 'smoke' / 'train-solo'} (the same fingerprint)" in logs
    solo = read_manifest(variant.plan.run_root / "train-solo")
    assert Path(solo["outputs"]["best"]["path"]).parent == tmp_path / "runs" / "smoke" / "train-solo"
    assert read_manifest(variant.plan.run_root / "train-1v1")["info"]["iterations"] == 1
    assert variant.run() == []
    seed = PipelineRunner(path, runs_dir=tmp_path / "runs", checkpoints_dir=tmp_path / "ckpt", progress=False,
                          log=logs.append, overrides=["stages.1v1.seed=3"])
    assert seed.run(only="train:1v1") == ["train:1v1"]  # one stage alone: its input reused from the plain run
    (tmp_path / "runs" / "smoke" / "train-solo" / "best.pt").unlink()
    assert {s.name: s.status for s in variant.status()}["train:solo"] == "stale"


def test_a_step_trained_on_another_device_is_kept_and_the_run_refused_unless_forced(tmp_path):
    """A training step that finished on cuda:0 (its manifest as a GPU run writes it) is complete for `spiral status
    --device cuda`, and a CPU run refuses with one line naming the step, its device and the two ways on, leaving its
    folder as it was; forced, it trains again on the CPU."""
    from spiral.core.errors import UsageError
    from spiral.pipeline.manifest import read_manifest

    path = write_pipeline(tmp_path, iterations=1)
    runner_for(path, tmp_path).run()
    step_dir = tmp_path / "runs" / "smoke" / "train-solo"
    gpu = PipelineRunner(path, runs_dir=tmp_path / "runs", checkpoints_dir=tmp_path / "ckpt", progress=False,
                         log=lambda _: None, device="cuda")
    assert gpu.plan.spec.device == "cuda:0"  # one name, one fingerprint
    fp = gpu._fingerprints()["train:solo"]
    manifest = read_manifest(step_dir)
    assert manifest["info"]["device"] == "cpu"
    manifest.update(fingerprint=fp.full, spec_fingerprint=fp.spec, info={**manifest["info"], "device": "cuda:0"})
    (step_dir / "manifest.json").write_text(json.dumps(manifest))
    assert {s.name: s.status for s in gpu.status()}["train:solo"] == "complete"
    before = sorted(p.name for p in step_dir.rglob("*"))
    with pytest.raises(UsageError, match=r"step 'train:solo' finished on cuda:0 .*--device cuda:0.*--force train:solo"):
        runner_for(path, tmp_path).run()
    assert sorted(p.name for p in step_dir.rglob("*")) == before
    assert "train:solo" in runner_for(path, tmp_path).run(force=["train:solo"])
    assert read_manifest(step_dir)["info"]["device"] == "cpu"


def _keep_only_declared(run_root: Path, *, keep: set[str]) -> None:
    """Delete every file of the run folder's steps but their manifests and the outputs these declare (the steps named
    in ``keep`` stay whole)."""
    declared = set()
    for manifest in run_root.glob("*/manifest.json"):
        declared |= {Path(out["path"]).resolve() for out in json.loads(manifest.read_text())["outputs"].values()}
    for pool in [path for path in declared if path.name == "pool.json"]:
        declared |= {pool.parent / m["file"] for m in json.loads(pool.read_text())["members"]}
    for step_dir in (d for d in run_root.iterdir() if d.is_dir() and d.name not in keep):
        for path in [p for p in step_dir.rglob("*") if p.is_file()]:
            checkpoint_sidecar = path.suffix == ".json" and path.with_suffix(".pt").resolve() in declared
            if path.name not in ("manifest.json", "fingerprint") and path.resolve() not in declared \
                    and not checkpoint_sidecar:
                path.unlink()


def test_a_stage_fine_tunes_a_checkpoint_file_named_by_init_from_and_reruns_when_the_file_changes(smoke_run,
                                                                                                 tmp_path):
    """A one-stage pipeline whose solo stage starts from another run's policy (``init_from: base.pt``, beside the
    pipeline file): its training step reads no other step, trains on from that policy's weights (at a learning rate
    too small to move them), reruns when the file's content changes, and a missing file is refused naming the
    field."""
    import torch

    from spiral.core.errors import UsageError

    path = write_pipeline(tmp_path, iterations=1, lr=1e-9)
    data = yaml.safe_load(path.read_text())
    data["stages"][0]["init_from"] = "base.pt"
    path.write_text(yaml.safe_dump(data))
    published = smoke_run.root / "ckpt" / "smoke"
    with pytest.raises(UsageError, match=r"stages\.0\.init_from: checkpoint .*base\.pt does not exist"):
        runner_for(path, tmp_path)
    for suffix in (".pt", ".json"):
        (tmp_path / f"base{suffix}").write_bytes((published / "solo" / f"best{suffix}").read_bytes())
    runner = runner_for(path, tmp_path)
    assert next(s for s in runner.steps if s.name == "train:solo").inputs == []
    assert runner.run()[0] == "train:solo"
    base = torch.load(tmp_path / "base.pt", weights_only=False)["actor_state_dict"]
    last = torch.load(next((tmp_path / "runs").glob("*/train-solo/ckpt/*.pt")), weights_only=False)
    layers = ["mlp.0.bias", "mlp.2.weight", "mlp.2.bias", "mlp.4.weight"]  # the normaliser keeps counting, and
    # the first layer's columns of inputs constant in the policy's stage start at zero (``take_up_new_inputs``)
    for name in layers:
        torch.testing.assert_close(last["actor_state_dict"][name], base[name], rtol=0, atol=1e-5, msg=name)
    for suffix in (".pt", ".json"):
        (tmp_path / f"base{suffix}").write_bytes((published / "1v1" / f"best{suffix}").read_bytes())
    assert runner_for(path, tmp_path).run()[0] == "train:solo"


def test_generated_training_tracks_are_a_step_every_training_step_reads_and_trains_on(tmp_path):
    """``training_tracks`` with two training seeds and one held out, of 5 and 6 gates in turn: a ``tracks`` step
    writes the three generated tracks (valid track files, the held-out one apart, each seed's gate count), the solo
    stage reads it and trains on the generated tracks (its policy records the first; it draws the tracks it fails more
    often), and its evaluation races the pipeline's own track, unseen in training. Without training tracks, drawing
    the hard ones is refused naming the field."""
    from spiral.config import load_track

    path = write_pipeline(tmp_path, iterations=1)
    data = yaml.safe_load(path.read_text())
    data["stages"][0].setdefault("env", {}).setdefault("episode", {})["hard_tracks"] = {"share": 0.5}
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(SpecError, match=r"stages\.0\.env\.episode\.hard_tracks: .*set training_tracks"):
        runner_for(path, tmp_path)
    data["training_tracks"] = {"train_seeds": [3, 2], "held_out_seeds": [100, 1], "gate_counts": [5, 6]}
    path.write_text(yaml.safe_dump(data))
    runner = runner_for(path, tmp_path)
    assert next(s for s in runner.steps if s.name == "train:solo").inputs == ["tracks"]
    assert runner.run()[:2] == ["tracks", "train:solo"]
    root = next((tmp_path / "runs").iterdir())
    train = sorted(load_track(p).name for p in (root / "tracks" / "train").glob("*.yaml"))
    held_out = [load_track(p).name for p in (root / "tracks" / "held_out").glob("*.yaml")]
    assert train == ["gen-s3-g6", "gen-s4-g5"] and held_out == ["gen-s100-g5"]
    best = json.loads((root / "train-solo" / "best.json").read_text())
    assert best["track"] == "gen-s3-g6"
    evaluation = json.loads((root / "eval-solo" / "eval.json").read_text())
    assert evaluation["track"] == "oval4"


def test_held_out_track_seeds_that_overlap_the_training_seeds_are_refused(tmp_path):
    from spiral.config.pipeline import TrackSetCfg

    with pytest.raises(ValueError, match=r"held_out_seeds: seeds 5\.\.6 overlap the training seeds 0\.\.5"):
        TrackSetCfg(train_seeds=(0, 6), held_out_seeds=(5, 2))


def test_the_unseen_tracks_section_races_each_methods_final_policy_once_it_and_the_tracks_exist(tmp_path):
    """smoke.yaml on generated tracks with an unseen-tracks section: its step reads both branches' final stages and
    the tracks step, and the report reads it."""
    data = yaml.safe_load((ROOT / "pipelines" / "smoke.yaml").read_text())
    data["track"] = str(ROOT / "tracks" / "oval4.yaml")
    data["training_tracks"] = {"train_seeds": [0, 3], "held_out_seeds": [100, 1]}
    data["report"] = {"unseen_tracks": {"races": 2, "tracks": [str(ROOT / "tracks" / "figure8.yaml")]}}
    path = tmp_path / "g.yaml"
    path.write_text(yaml.safe_dump(data))
    steps = {s.name: s for s in runner_for(path, tmp_path).steps}
    assert steps["eval:unseen-tracks"].inputs == ["train:2v2", "train:2v2-noselfplay", "tracks"]
    assert "eval:unseen-tracks" in steps["report"].inputs


def test_an_unseen_tracks_specialist_is_fingerprinted_by_its_content_and_a_missing_one_is_refused(tmp_path):
    """A specialist named in report.unseen_tracks enters the section's fingerprint by its checkpoint's content (a
    retrained specialist races again); a missing file is refused naming the field, before anything runs."""
    import shutil

    from spiral.core.errors import UsageError

    data = yaml.safe_load((ROOT / "pipelines" / "smoke.yaml").read_text())
    data["track"] = str(ROOT / "tracks" / "oval4.yaml")
    data["report"] = {"unseen_tracks": {"races": 2, "tracks": [str(ROOT / "tracks" / "circuit6.yaml")],
                                        "specialists": {"circuit6": "spec.pt"}}}
    path = tmp_path / "g.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(UsageError, match=r"report\.unseen_tracks\.specialists\.circuit6: checkpoint .*spec\.pt"):
        runner_for(path, tmp_path)
    fingerprints = []
    for source in ("spiral.pt", "ppo-noselfplay.pt"):
        shutil.copy(ROOT / "checkpoints" / "full" / source, tmp_path / "spec.pt")
        fingerprints.append(runner_for(path, tmp_path)._fingerprints()["eval:unseen-tracks"].full)
    assert fingerprints[0] != fingerprints[1]
