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
WORKER_RETRIES = 2
"""Times a step whose worker was killed (by a signal: out of memory, a lost machine, a user) starts again, resuming
from what it left (a training step from its newest checkpoint); a worker that exits with an error is not retried."""


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
    retries: int = 0
    """Times this step's worker was started again after being killed."""

    @property
    def killed(self) -> bool:
        """Whether the worker ended by a signal rather than by exiting."""
        return self.process.returncode is not None and self.process.returncode < 0


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
            _restart_killed(runner, running, failed, log_dir)
    except KeyboardInterrupt:
        _stop(running.values())
        raise PipelineError(f"interrupted while running {', '.join(running)}\n"
                            f"resume with: {runner.command} --jobs {jobs}") from None
    if failed:
        step = failed[0]
        how = (f"was killed (signal {-step.process.returncode}, after {step.retries} restarts" if step.killed
               else f"failed (exit code {step.process.returncode}")
        raise PipelineError(f"step '{step.step.name}' {how}; its output: {step.log_path})\n"
                            f"resume with: {runner.command} --jobs {jobs}")
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


def _restart_killed(runner, running: dict[str, StepProcess], failed: list[StepProcess], log_dir: Path) -> None:
    """Start again, resuming, the steps in ``failed`` whose worker was killed and has retries left."""
    for proc in [p for p in failed if p.killed and p.retries < WORKER_RETRIES]:
        failed.remove(proc)
        runner.log(f"step '{proc.step.name}': its worker was killed (signal {-proc.process.returncode}); starting it "
                   f"again from what it left ({proc.retries + 1} of {WORKER_RETRIES})")
        threads = int(_thread_option(proc.process.args))
        again = _spawn(runner, proc.step, False, threads, log_dir, append=True)
        again.retries = proc.retries + 1
        running[proc.step.name] = again


def _thread_option(args: list[str]) -> str:
    """The ``--threads`` value a worker was started with."""
    return args[args.index("--threads") + 1]


def _stop(workers: Collection[StepProcess]) -> None:
    """Terminate ``workers`` and wait for them to exit."""
    for proc in workers:
        proc.process.terminate()
    for proc in workers:
        proc.process.wait()


def _spawn(runner, step: Step, fresh: bool, threads: int, log_dir: Path, *, append: bool = False) -> StepProcess:
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
    if not append:
        log_path.write_text("")
    process = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    relay = threading.Thread(target=_relay, args=(process.stdout, log_path, step.name, runner.log), daemon=True)
    relay.start()
    runner.log(f"step '{step.name}' started in a worker ({threads} torch thread{'s' if threads > 1 else ''}; "
               f"output also in {log_path})")
    return StepProcess(step, process, relay, log_path)
