"""``--executor ray``: the pipeline's steps as Ray tasks on a local Ray instance give what the local executor gives;
a killed worker resumes; without Ray, one clear error names the extra."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from spiral.core.errors import UsageError
from spiral.pipeline.sweep import run_sweep

ROOT = Path(__file__).resolve().parents[2]
SMOKE = ROOT / "pipelines" / "smoke.yaml"
UNTIMED = {"wall_time_s", "overrides", "reused_from"}
"""Manifest info that differs between two runs of the same steps."""


@pytest.fixture(scope="module")
def ray_instance():
    """A local Ray instance with 2 CPUs for this module's tests."""
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install 'spiral[ray]')")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, _system_config={"worker_niceness": 0})
    yield ray
    ray.shutdown()


def test_without_ray_the_ray_executor_is_refused_naming_the_extra(monkeypatch):
    from spiral.pipeline.ray_executor import RayLauncher

    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    with pytest.raises(UsageError, match=r"--executor ray needs Ray.*pip install 'spiral\[ray\]'"):
        RayLauncher()


def test_the_local_executor_and_the_cli_import_no_ray():
    code = ("import sys, spiral.cli, spiral.pipeline.parallel, spiral.pipeline.runner, spiral.pipeline.sweep; "
            "print('ray' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "False"


def test_an_address_without_the_ray_executor_is_refused():
    from typer.testing import CliRunner

    from spiral.cli import app

    result = CliRunner().invoke(app, ["run", str(SMOKE), "--address", "auto"])
    assert result.exit_code != 0 and "--address names a Ray cluster" in result.output


@pytest.mark.bitwise
def test_smoke_pipeline_on_ray_trains_what_the_local_executor_trains(ray_instance, smoke_run, tmp_path, monkeypatch):
    """smoke.yaml's 2v2 stages and every step after them as Ray tasks, two at a time, in a copy of the smoke pipeline
    run step by step in this process: every step ends with the manifests (the same fingerprints but where the
    checkpoints folder enters: publishing, the report) and, tensor for tensor, the checkpoints of that run."""
    from spiral.pipeline import PipelineRunner
    from spiral.pipeline.ray_executor import RayLauncher

    smoke_run.copy_to(tmp_path)
    monkeypatch.chdir(tmp_path)  # the copied manifests name their files relative to the run's root
    for step in ("train-2v2", "train-2v2-noselfplay"):
        shutil.rmtree(Path("runs") / "smoke" / step)
    again = [name for name in smoke_run.ran if "2v2" in name or name.endswith("report")]
    logs: list[str] = []
    runner = PipelineRunner(SMOKE, runs_dir=Path("runs"), checkpoints_dir=Path("ckpt"), progress=False,
                            log=logs.append)
    with RayLauncher() as launcher:
        assert sorted(runner.run(jobs=2, launcher=launcher)) == sorted(again) and len(again) == 8
    assert runner.run() == []  # complete, as a local run sees it
    assert any(line.startswith("[train:2v2] ") for line in logs)  # worker output relayed

    local, ray_run = smoke_run.root / "runs" / "smoke", Path("runs") / "smoke"
    steps = sorted(p.name for p in local.iterdir() if (p / "manifest.json").exists())
    assert steps == sorted(p.name for p in ray_run.iterdir() if (p / "manifest.json").exists())
    for step in steps:
        a, b = (json.loads((run / step / "manifest.json").read_text()) for run in (local, ray_run))
        if not step.startswith(("publish-", "report")):  # those name the run's folders, which differ
            assert (a["fingerprint"], a["spec_fingerprint"]) == (b["fingerprint"], b["spec_fingerprint"]), step
            assert _info(a) == _info(b), step
        assert a["outputs"].keys() == b["outputs"].keys(), step
        for key, out in a["outputs"].items():
            if out["path"].endswith(".pt"):
                _assert_same_tensors(smoke_run.root / out["path"], Path(b["outputs"][key]["path"]))


def test_a_sweep_on_ray_runs_its_seeds_at_once_in_folders_of_their_own(ray_instance, tmp_path):
    """Seeds 0 and 1 of a one-stage pipeline through Ray: both draws at once (their log lines named by seed), two
    run folders, one summary."""
    from spiral.pipeline.ray_executor import RayLauncher

    logs: list[str] = []
    with RayLauncher() as launcher:
        summary = run_sweep(one_stage_pipeline(tmp_path, iterations=2), [0, 1], runs_dir=tmp_path / "runs",
                            checkpoints_dir=tmp_path / "ckpt", jobs=2, launcher=launcher, log=logs.append)
    data = json.loads(summary.with_name("summary.json").read_text())
    assert [Path(d["run"]).name for d in data["draws"]] == ["smoke-seed-0", "smoke-seed-1"]
    for seed in (0, 1):
        assert (tmp_path / "runs" / f"smoke-seed-{seed}" / "train-solo" / "manifest.json").exists()
        assert any(line.startswith(f"[seed {seed}] [train:solo] ") for line in logs)


def one_stage_pipeline(tmp_path: Path, *, iterations: int) -> Path:
    """smoke.yaml's solo stage alone, ``iterations`` long, without a report."""
    import yaml

    data = yaml.safe_load(SMOKE.read_text())
    data = json.loads(json.dumps({k: v for k, v in data.items() if not k.startswith("x-")}))
    data.update(track=str(ROOT / "tracks" / "oval4.yaml"), report={"enabled": False}, stages=data["stages"][:1])
    data["stages"][0]["iterations"] = iterations
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _info(manifest: dict) -> dict:
    return {k: v for k, v in manifest["info"].items() if k not in UNTIMED}


def _assert_same_tensors(a: Path, b: Path) -> None:
    """Every tensor of two checkpoints equal, to the bit."""
    left, right = (torch.load(p, map_location="cpu", weights_only=False) for p in (a, b))
    flat_a, flat_b = dict(_tensors(left)), dict(_tensors(right))
    assert flat_a.keys() == flat_b.keys() and flat_a, a
    for name, tensor in flat_a.items():
        assert torch.equal(tensor, flat_b[name]), f"{a.name}: {name}"  # exact: same machine, same steps


def _tensors(obj, prefix: str = ""):
    if isinstance(obj, torch.Tensor):
        yield prefix, obj
    elif isinstance(obj, dict):
        for key, value in obj.items():
            yield from _tensors(value, f"{prefix}/{key}")
    elif isinstance(obj, (list, tuple)):
        for i, value in enumerate(obj):
            yield from _tensors(value, f"{prefix}/{i}")


def test_a_lost_ray_worker_ends_its_step_s_process_and_the_step_resumes_from_its_checkpoint(
        ray_instance, tmp_path, worker_pid, kill_once):
    """The Ray worker running the solo stage's task, killed (SIGKILL) once the step has saved a checkpoint past the
    first iteration, takes the step's process with it; the task is submitted again and the step resumes from that
    checkpoint; the pipeline completes with every iteration."""
    from spiral.core.checkpoint import newest_valid_checkpoint
    from spiral.pipeline import PipelineRunner
    from spiral.pipeline.ray_executor import RayLauncher

    path = one_stage_pipeline(tmp_path, iterations=30)
    ckpt = tmp_path / "runs" / "smoke" / "train-solo" / "ckpt"
    workers: list[int] = []

    def ray_worker() -> int | None:
        """The Ray worker whose task started the solo stage's worker process (that process's parent)."""
        worker = worker_pid("train:solo", tmp_path / "runs")
        if worker is None:
            return None
        workers.append(worker)
        return int(Path(f"/proc/{worker}/stat").read_text().rsplit(")", 1)[1].split()[1])

    def past_first_checkpoint() -> bool:
        newest = newest_valid_checkpoint(ckpt) if ckpt.is_dir() else None
        return newest is not None and newest.stem != "model_0"

    killed = kill_once(ray_worker, past_first_checkpoint)
    logs: list[str] = []
    runner = PipelineRunner(path, runs_dir=tmp_path / "runs", checkpoints_dir=tmp_path / "ckpt", progress=False,
                            log=logs.append)
    with RayLauncher() as launcher:
        ran = runner.run(launcher=launcher)
    assert ran == [s.name for s in runner.steps]
    assert killed and any("train:solo': its worker was killed (signal 9); starting it again" in x for x in logs)
    assert any("the Ray worker running it was lost" in line for line in logs)
    assert not _alive(workers[-1])  # the step's process did not train on without its task
    assert any("[train:solo] resuming stage 'solo' from model_" in line for line in logs)
    rows = (tmp_path / "runs" / "smoke" / "train-solo" / "train_log.jsonl").read_text().splitlines()
    assert [json.loads(r)["iteration"] for r in rows] == list(range(30))


def _alive(pid: int) -> bool:
    """Whether ``pid`` is a running (not zombie) pipeline worker."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        args = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z" and b"spiral.pipeline.workers" in args
