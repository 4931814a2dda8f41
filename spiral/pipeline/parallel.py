"""``spiral run --jobs N``: independent steps of a pipeline run side by side, each in its own process.

The parent holds the pipeline lock and schedules: a step starts once every step it depends on has finished, at
most N at a time, training steps first. Each worker process runs one step exactly as the sequential runner would
(same folder, fingerprint, resume and manifest), with its torch threads set to its share of the CPU cores: all of
them when it is the only step that can run (nothing else can become ready before it ends), ``cores // N``
otherwise, so the workers never oversubscribe the CPU (torch's thread pools slow down many times over when they
do). Worker output is relayed line by line, prefixed with the step's name, and kept in ``<run>/logs/<step>.log``.

A failed step lets the running ones finish (their work is kept) and starts nothing new; the error names the
step, its log and the command that resumes. An interrupt stops the workers; training resumes from checkpoints.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from spiral.pipeline.step import PipelineError, Step

__all__ = ["StepProcess", "run_parallel", "thread_share"]

POLL_S = 0.2


def thread_share(cores: int, jobs: int, alone: bool) -> int:
    """Torch threads for a worker: every core when it runs alone, else an equal share of at least one."""
    return max(1, cores if alone else cores // jobs)


@dataclass
class StepProcess:
    """A running worker: its process, the thread relaying its output and its log file."""

    step: Step
    process: subprocess.Popen
    relay: threading.Thread
    log_path: Path


def _relay(stream: IO[str], log_file: Path, prefix: str, log) -> None:
    with log_file.open("a") as out:
        for line in stream:
            out.write(line)
            out.flush()
            log(f"[{prefix}] {line.rstrip()}")


def run_parallel(runner, todo: list[Step], fresh: set[str], jobs: int, *, cores: int | None = None) -> list[str]:
    """Run ``todo`` (steps of ``runner``, a ``PipelineRunner``, in dependency order) with at most ``jobs`` workers;
    return those run.

    Raises:
        PipelineError: a step failed (after the other running steps finished) or the run was interrupted.
    """
    cores = cores or os.cpu_count() or 1
    pending, names = list(todo), {s.name for s in todo}
    running: dict[str, StepProcess] = {}
    done: list[str] = []
    failed: list[StepProcess] = []
    log_dir = runner.plan.run_root / "logs"
    log_dir.mkdir(parents=True, exist_ok=True)
    try:
        while running or (pending and not failed):
            ready = [] if failed else [s for s in pending if all(i not in names or i in done for i in s.inputs)]
            ready.sort(key=lambda s: not s.resumable)  # training first: the long steps set the wall time
            for step in ready[: jobs - len(running)]:
                alone = not running and len(ready) == 1
                running[step.name] = _spawn(runner, step, step.name in fresh,
                                            thread_share(cores, jobs, alone), log_dir)
                pending.remove(step)
            time.sleep(POLL_S)
            _reap(running, done, failed)
    except KeyboardInterrupt:
        _stop(running.values())
        raise PipelineError(f"interrupted while running {', '.join(running)}\n"
                            f"resume with: {runner.command} --jobs {jobs}") from None
    if failed:
        step = failed[0]
        raise PipelineError(f"step '{step.step.name}' failed (exit code {step.process.returncode}; its output: "
                            f"{step.log_path})\nresume with: {runner.command} --jobs {jobs}")
    return done


def _reap(running: dict[str, StepProcess], done: list[str], failed: list[StepProcess]) -> None:
    """Move the workers that have ended from ``running`` to ``done`` (exit code 0, by name) or ``failed``."""
    for name, proc in list(running.items()):
        if proc.process.poll() is None:
            continue
        proc.relay.join()
        del running[name]
        if proc.process.returncode == 0:
            done.append(name)
        else:
            failed.append(proc)


def _stop(workers: Collection[StepProcess]) -> None:
    """Terminate ``workers`` and wait for them to exit."""
    for proc in workers:
        proc.process.terminate()
    for proc in workers:
        proc.process.wait()


def _spawn(runner, step: Step, fresh: bool, threads: int, log_dir: Path) -> StepProcess:
    cmd = [sys.executable, "-m", "spiral.pipeline.workers", str(runner.path), step.name,
           "--runs-dir", str(runner.plan.runs_dir), "--checkpoints-dir", str(runner.plan.checkpoints_dir),
           "--device", runner.plan.spec.device, "--threads", str(threads)]
    if fresh:
        cmd.append("--fresh")
    if runner.accept_code_changes:
        cmd.append("--accept-code-changes")
    cmd += [arg for override in runner.overrides for arg in ("--set", override)]
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads),
           "PYTHONUNBUFFERED": "1"}
    log_path = log_dir / f"{step.dirname}.log"
    log_path.write_text("")
    process = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    relay = threading.Thread(target=_relay, args=(process.stdout, log_path, step.name, runner.log), daemon=True)
    relay.start()
    runner.log(f"step '{step.name}' started in a worker ({threads} torch thread{'s' if threads > 1 else ''}; "
               f"output also in {log_path})")
    return StepProcess(step, process, relay, log_path)
