"""The smoke pipeline run once per session, in this process, for the tests that compare other runs with it."""

from __future__ import annotations

import os
import shutil
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from spiral.pipeline import PipelineRunner

ROOT = Path(__file__).resolve().parents[2]
SMOKE = ROOT / "pipelines" / "smoke.yaml"


@dataclass(frozen=True)
class SmokeRun:
    """A finished run of smoke.yaml under ``root`` (its ``runs`` and ``ckpt`` folders; the manifests name the files
    relative to ``root``) and the steps it ran, in order."""

    root: Path
    ran: list[str]

    def copy_to(self, root: Path) -> None:
        """The run's folders copied under ``root``; with ``root`` the working directory, its manifests name the
        copies (a test that changes them changes its copy)."""
        for name in ("runs", "ckpt"):
            shutil.copytree(self.root / name, root / name, symlinks=True)


@pytest.fixture(scope="session")
def smoke_run(tmp_path_factory) -> SmokeRun:
    """smoke.yaml run step by step in this process (the local executor's sequential path), from its root folder."""
    root = tmp_path_factory.mktemp("smoke-run")
    here = Path.cwd()
    os.chdir(root)
    try:
        runner = PipelineRunner(SMOKE, runs_dir=Path("runs"), checkpoints_dir=Path("ckpt"), progress=False,
                                log=lambda _: None)
        return SmokeRun(root, runner.run())
    finally:
        os.chdir(here)


@pytest.fixture(scope="session")
def worker_pid():
    """``worker_pid(step, runs_dir)``: the pid of the live pipeline worker running ``step`` of a run under
    ``runs_dir`` (from /proc), or None; workers of other pipelines on the machine are not the test's."""

    def find(step: str, runs_dir: Path) -> int | None:
        for proc in Path("/proc").iterdir():
            try:
                args = (proc / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if b"spiral.pipeline.workers" in args and step.encode() in args and str(runs_dir).encode() in args:
                return int(proc.name)
        return None

    return find


@pytest.fixture
def kill_once():
    """``kill_once(target, ready)``: starts a thread that SIGKILLs the process ``target()`` names once it names one
    and ``ready()`` holds (polling for up to two minutes); returns the list the killed pid goes into."""
    threads: list[threading.Thread] = []

    def start(target: Callable[[], int | None], ready: Callable[[], bool]) -> list[int]:
        killed: list[int] = []

        def run() -> None:
            for _ in range(2400):
                pid = target()
                if pid is not None and ready():
                    os.kill(pid, signal.SIGKILL)
                    killed.append(pid)
                    return
                time.sleep(0.05)

        threads.append(threading.Thread(target=run))
        threads[-1].start()
        return killed

    yield start
    for thread in threads:
        thread.join()
