"""Data-parallel training: rank and device selection, per-rank seeds, and a 2-process run on CPU (gloo)."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from spiral.train import distributed
from spiral.train.distributed import DistInfo, env_info, init_distributed, rank_device

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(("device", "expected"), [(None, "cuda:1"), ("cuda", "cuda:1"), ("cuda:1", "cuda:1"),
                                                  ("cpu", "cpu")])
def test_rank_device_is_the_local_rank_gpu(device, expected):
    """Map no device, `cuda` and this rank's `cuda:N` to cuda:LOCAL_RANK; keep `cpu`."""
    assert rank_device(device, DistInfo(rank=3, local_rank=1, world_size=4)) == expected


@pytest.mark.parametrize(("device", "message"), [("cuda:0", "cuda:LOCAL_RANK"), ("tpu", "expected cpu, cuda")])
def test_rank_device_refuses_another_gpu_or_an_unknown_device(device, message):
    """Refuse a GPU that belongs to another local rank, and device strings that are not cpu/cuda."""
    with pytest.raises(ValueError, match=message):
        rank_device(device, DistInfo(rank=1, local_rank=1, world_size=2))


def test_env_info_reads_torchrun_variables():
    """Read RANK, LOCAL_RANK and WORLD_SIZE; None outside torchrun; refuse inconsistent values."""
    assert env_info({}) is None
    assert env_info({"RANK": "5", "LOCAL_RANK": "1", "WORLD_SIZE": "8"}) == DistInfo(5, 1, 8)
    with pytest.raises(ValueError, match="inconsistent"):
        env_info({"RANK": "2", "LOCAL_RANK": "0", "WORLD_SIZE": "2"})
    with pytest.raises(ValueError, match="three integers"):
        env_info({"RANK": "0", "WORLD_SIZE": "2"})


def test_rank_seeds_and_main_rank():
    """Seed rank r with seed + r; only rank 0 is the writing rank; rank 0 of 1 without a process group."""
    assert [DistInfo(r, r, 3).seed(100) for r in range(3)] == [100, 101, 102]
    assert [DistInfo(r, r, 3).is_main for r in range(3)] == [True, False, False]
    assert distributed.current() == DistInfo(0, 0, 1) and not distributed.current().enabled


def test_distributed_without_torchrun_is_an_error():
    """Refuse --distributed outside torchrun with a message that names torchrun."""
    with pytest.raises(ValueError, match="torchrun"):
        init_distributed("cpu", environ={})


def test_runner_under_torchrun_without_a_process_group_is_an_error(monkeypatch):
    """Refuse to let rsl-rl open its own NCCL group when spiral's process group was not set up."""
    monkeypatch.setenv("WORLD_SIZE", "2")
    with pytest.raises(ValueError, match="--distributed"):
        distributed.GroupRunner._configure_multi_gpu(object())  # type: ignore[arg-type]


WORKER = textwrap.dedent("""
    import json, sys
    from pathlib import Path
    import torch
    from spiral.config import AIRFRAMES, SimCfg, StageSpec, load_track
    from spiral.env import RaceSetting
    from spiral.train import StageTrainer
    from spiral.train.distributed import init_distributed, shutdown

    out = Path(sys.argv[1])
    info, device = init_distributed("cpu")
    stage = StageSpec.model_validate({
        "name": "dp", "worlds": 8, "iterations": 2, "env": {"obs": {"history_len": 1}},
        "ppo": {"num_steps_per_env": 8, "save_interval": 1, "actor_hidden_dims": [16], "critic_hidden_dims": [16]},
        "selection": {"interval": 2, "races": 2}})
    trainer = StageTrainer(RaceSetting(load_track(sys.argv[2]), AIRFRAMES["cf2x"], SimCfg()), stage, out / "run",
                           device=device, seed=10, progress=False, log=lambda m: None)
    first = {k: v.clone() for k, v in trainer.runner.alg.actor.state_dict().items()}
    trainer.train()
    last = trainer.runner.alg.actor.state_dict()
    torch.save({"first": first, "last": last, "multi_gpu": trainer.runner.alg.is_multi_gpu,
                "seed": trainer.env.generator.initial_seed()}, out / f"rank{info.rank}.pt")
    shutdown()
""")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_cpu_ranks_stay_in_sync_and_only_rank_0_writes(tmp_path):
    """Train 2 gloo ranks: identical weights after the updates, seeds 10 and 11, one log and checkpoint set."""
    script = tmp_path / "worker.py"
    script.write_text(WORKER)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", f"--master_port={_free_port()}",
           str(script), str(tmp_path), str(ROOT / "tracks" / "oval4.yaml")]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    r0, r1 = (torch.load(tmp_path / f"rank{r}.pt") for r in (0, 1))
    assert r0["multi_gpu"] and r1["multi_gpu"]
    assert (r0["seed"], r1["seed"]) == (10, 11)
    for key, value in r0["last"].items():
        torch.testing.assert_close(r1["last"][key], value, rtol=0, atol=1e-6)
    changed = [not torch.allclose(r0["first"][k], v) for k, v in r0["last"].items()]
    assert any(changed)  # training changed them
    rows = (tmp_path / "run" / "train_log.jsonl").read_text().splitlines()
    assert [json.loads(r)["iteration"] for r in rows] == [0, 1]
    assert sorted(p.name for p in (tmp_path / "run" / "ckpt").glob("*.pt")) == ["model_0.pt", "model_1.pt"]


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_stage_trains_on_cuda(tmp_path):
    """Train a tiny stage with Warp and torch on cuda:0 and save a checkpoint whose tensors load on the CPU."""
    from spiral.config import AIRFRAMES, SimCfg, StageSpec, load_track
    from spiral.env import RaceSetting
    from spiral.train import StageTrainer, load_policy

    stage = StageSpec.model_validate({"name": "gpu", "worlds": 64, "iterations": 2, "env": {"obs": {"history_len": 2}},
                                      "ppo": {"num_steps_per_env": 8}, "selection": {"interval": 2, "races": 4}})
    trainer = StageTrainer(RaceSetting(load_track(ROOT / "tracks" / "oval4.yaml"), AIRFRAMES["cf2x"], SimCfg()), stage,
                           tmp_path, device="cuda:0", progress=False)
    assert trainer.env.pos.device.type == "cuda" and trainer.env.world.device == "cuda:0"
    result = trainer.train()
    assert result.iterations == 2
    assert load_policy(result.best_path, device="cpu").obs_layout["obs_dim"] == trainer.env.obs_dim


@pytest.mark.gpu
@pytest.mark.skipif(torch.cuda.device_count() < 2, reason="needs two CUDA devices")
def test_two_gpu_ranks_stay_in_sync(tmp_path):
    """Train 2 NCCL ranks on cuda:0 and cuda:1 and end with identical weights."""
    script = tmp_path / "worker.py"
    script.write_text(WORKER.replace('init_distributed("cpu")', "init_distributed(None)"))
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", f"--master_port={_free_port()}",
           str(script), str(tmp_path), str(ROOT / "tracks" / "oval4.yaml")]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    r0, r1 = (torch.load(tmp_path / f"rank{r}.pt", map_location="cpu") for r in (0, 1))
    for key, value in r0["last"].items():
        torch.testing.assert_close(r1["last"][key], value, rtol=0, atol=1e-5)
