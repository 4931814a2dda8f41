"""``spiral run --jobs N``: workers share the cores, and take up those that finished steps free."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from spiral.config import AIRFRAMES, SimCfg, StageSpec
from spiral.core import threads
from spiral.pipeline.parallel import StepProcess, rebalance_threads, set_worker_threads, thread_share
from spiral.train import StageTrainer

FOLLOWER = """
import sys, time, torch
from pathlib import Path
from spiral.pipeline.workers import follow_thread_share
follow_thread_share(Path(sys.argv[1]), 1)
print(torch.get_num_threads(), flush=True)
deadline = time.monotonic() + 60
while torch.get_num_threads() == 1 and time.monotonic() < deadline:
    time.sleep(0.01)
print(torch.get_num_threads(), flush=True)
"""


def test_each_running_worker_gets_an_equal_share_of_the_cores_and_at_least_one_thread():
    assert thread_share(2, 2) == 1 and thread_share(2, 1) == 2
    assert thread_share(8, 3) == 2 and thread_share(2, 3) == 1 and thread_share(4, 0) == 4


@pytest.mark.skipif(sys.platform == "win32", reason="SIGUSR1 is POSIX")
def test_a_worker_left_alone_takes_up_the_freed_cores_once_it_follows_its_threads_file(tmp_path):
    threads_file = tmp_path / "step.threads"
    worker = subprocess.Popen([sys.executable, "-c", FOLLOWER, str(threads_file)], stdout=subprocess.PIPE, text=True)
    proc = StepProcess(step=None, process=worker, relay=None, log_path=tmp_path / "step.log", threads=1,
                       threads_file=threads_file)
    try:
        logs: list[str] = []
        assert worker.stdout.readline().strip() == "1"  # the handler is in place and the file written
        rebalance_threads({"train:2v2": proc}, cores=3, log=logs.append)
        assert worker.stdout.readline().strip() == "3"
        assert proc.threads == 3 and threads_file.read_text() == "3"
        assert logs == ["step 'train:2v2' now runs on 3 torch threads (1 step running)"]
        assert worker.wait(timeout=30) == 0
    finally:
        worker.kill()


def test_a_worker_that_does_not_follow_thread_changes_yet_is_not_signalled(tmp_path):
    worker = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    proc = StepProcess(step=None, process=worker, relay=None, log_path=tmp_path / "step.log", threads=1,
                       threads_file=tmp_path / "missing.threads")
    try:
        assert not set_worker_threads(proc, 2)
        assert proc.threads == 1 and worker.poll() is None  # SIGUSR1's default action would have ended it
    finally:
        worker.kill()


def test_a_share_given_while_a_count_is_pinned_applies_when_the_pin_ends(monkeypatch):
    """The report holds one thread while planner processes take the cores: a share that arrives meanwhile waits for
    the pin to end; outside a worker (no share given) a pin restores the count from before."""
    monkeypatch.setattr(threads, "_share", None)
    monkeypatch.setattr(threads, "_pins", [])
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        with threads.pinned(1):
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 2
        threads.take_share(1)
        with threads.pinned(1):
            threads.take_share(3)
            assert torch.get_num_threads() == 1
            with threads.pinned(2):
                assert torch.get_num_threads() == 2
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(before)


def test_raising_the_torch_threads_in_the_middle_of_a_stage_trains_the_same_policy(oval2, tmp_path):
    """What makes the share safe to change: at the pipeline's mini-batch sizes torch's CPU kernels split their work
    over the threads without changing a result, so a stage trains the same weights on one thread or two."""
    spec = StageSpec.model_validate({
        "name": "solo", "worlds": 512, "iterations": 3, "env": {"obs": {"history_len": 1}},
        "ppo": {"num_steps_per_env": 24}, "selection": {"interval": 10, "races": 2}})
    threads = torch.get_num_threads()

    def train(raise_at: int) -> dict[str, torch.Tensor]:
        torch.set_num_threads(1)
        trainer = StageTrainer(oval2, AIRFRAMES["cf2x"], SimCfg(), spec, tmp_path / f"at{raise_at}", progress=False)
        alg = trainer.runner.alg
        alg.train_mode()
        obs = trainer.vec_env.get_observations()
        for it in range(3):
            if it == raise_at:
                torch.set_num_threads(2)
            obs, _ = trainer.collect(obs)
            alg.update()
        return {**alg.actor.state_dict(), **{f"critic.{k}": v for k, v in alg.critic.state_dict().items()}}

    try:
        one, raised = train(raise_at=99), train(raise_at=1)
    finally:
        torch.set_num_threads(threads)
    assert one.keys() == raised.keys()
    assert all(torch.equal(one[k], raised[k]) for k in one)
