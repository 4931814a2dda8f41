"""``spiral run --jobs N``: independent steps of a pipeline run side by side, each in its own process.

The parent holds the pipeline lock and schedules: a step starts once every step it depends on has finished, at
most N at a time, training steps first. Each worker process runs one step exactly as the sequential runner would
(same folder, fingerprint, resume and manifest), with the run's torch threads (``--threads``, one by default): on
the CPU they decide a step's numbers to the bit, so a worker trains what the sequential runner trains, whatever
else runs beside it. N workers of T threads want N·T cores (with fewer, torch's thread pools contend and slow down
many times over; the run says so when it starts). Worker output is relayed line by line, prefixed with the step's
name, and kept in ``<run>/logs/<step>.log``.

Where the workers run is the launcher's: :class:`LocalLauncher` starts them as child processes of this one;
:class:`spiral.pipeline.ray_executor.RayLauncher` as Ray tasks on a cluster whose nodes share the working directory.
The scheduling, retries and messages are the same for both.

A failed step lets the running ones finish (their work is kept) and starts nothing new; the error names the
step, its log and the command that resumes. A worker killed by a signal (or, under Ray, lost with its node) is
started again, resuming, up to :data:`WORKER_RETRIES` times. An interrupt stops the workers; training resumes from
checkpoints.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Collection
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Protocol

from spiral.core.errors import UsageError
from spiral.pipeline.step import PipelineError, Step

__all__ = ["Launcher", "LocalLauncher", "StepJob", "WorkerHandle", "check_cores", "run_parallel", "worker_command"]

POLL_S = 0.2
WORKER_RETRIES = 2
"""Times a step whose worker was killed (by a signal: out of memory, a lost machine, a user) starts again, resuming
from what it left (a training step from its newest checkpoint); a worker that exits with an error is not retried."""


class WorkerHandle(Protocol):
    """A started worker, wherever it runs."""

    def poll(self) -> int | None:
        """None while it runs; then its exit code, negative when it was killed by a signal or lost."""

    def stop(self) -> None:
        """End it and wait until it has ended."""


class Launcher(Protocol):
    """Starts workers: ``command`` is the worker's arguments after the Python interpreter."""

    cores: int
    """CPU cores of the largest machine a worker can run on."""
    total_cores: int
    """CPU cores of all the machines together."""

    def start(self, command: list[str], env: dict[str, str], threads: int, log_path: Path,
              log: Callable[[str], None]) -> WorkerHandle:
        """Start a worker with ``threads`` torch threads; its output goes to ``log_path`` (appended) and, line by
        line, to ``log``."""


@dataclass
class StepJob:
    """A step's running worker."""

    step: Step
    worker: WorkerHandle
    log_path: Path
    threads: int
    retries: int = 0
    """Times this step's worker was started again after being killed."""
    returncode: int | None = None

    def done(self) -> bool:
        """Whether the worker has ended (its exit code is then in ``returncode``)."""
        self.returncode = self.worker.poll()
        return self.returncode is not None

    @property
    def killed(self) -> bool:
        """Whether the worker ended by a signal (or was lost) rather than by exiting."""
        return self.returncode is not None and self.returncode < 0


class _LocalWorker:
    def __init__(self, process: subprocess.Popen, relay: threading.Thread) -> None:
        self.process, self.relay = process, relay

    def poll(self) -> int | None:
        if self.process.poll() is None:
            return None
        self.relay.join()
        return self.process.returncode

    def stop(self) -> None:
        self.process.terminate()
        self.process.wait()


class LocalLauncher:
    """Workers as child processes of this one, on this machine."""

    def __init__(self) -> None:
        self.cores = self.total_cores = os.cpu_count() or 1

    def start(self, command: list[str], env: dict[str, str], threads: int, log_path: Path,
              log: Callable[[str], None]) -> WorkerHandle:
        process = subprocess.Popen([sys.executable, *command, "--parent", str(os.getpid())], stdout=subprocess.PIPE,
                                   stderr=subprocess.STDOUT, text=True, env={**os.environ, **env})
        relay = threading.Thread(target=_relay, args=(process.stdout, log_path, log), daemon=True)
        relay.start()
        return _LocalWorker(process, relay)


def _relay(stream: IO[str], log_file: Path, log: Callable[[str], None]) -> None:
    with log_file.open("a") as out:
        for line in stream:
            out.write(line)
            out.flush()
            log(line.rstrip())


def run_parallel(runner, todo: list[Step], fresh: set[str], jobs: int, threads: int, *,
                 launcher: Launcher | None = None) -> list[str]:
    """Run ``todo`` (steps of ``runner``, a ``PipelineRunner``, in dependency order) with at most ``jobs`` workers
    of ``threads`` torch threads each, started by ``launcher`` (child processes by default); return those run.

    Raises:
        PipelineError: a step failed (after the other running steps finished) or the run was interrupted.
    """
    launcher = launcher or LocalLauncher()
    pending, names = list(todo), {s.name for s in todo}
    running: dict[str, StepJob] = {}
    done: list[str] = []
    failed: list[StepJob] = []
    log_dir = runner.plan.run_root / "logs"
    log_dir.mkdir(parents=True, exist_ok=True)
    try:
        while running or (pending and not failed):
            ready = [] if failed else [s for s in pending if all(i not in names or i in done for i in s.inputs)]
            ready.sort(key=lambda s: not s.resumable)  # training first: the long steps set the wall time
            for step in ready[: jobs - len(running)]:
                running[step.name] = _spawn(runner, launcher, step, step.name in fresh, threads, log_dir)
                pending.remove(step)
            time.sleep(POLL_S)
            _reap(running, done, failed)
            _restart_killed(runner, launcher, running, failed, log_dir)
    except KeyboardInterrupt:
        _stop(running.values())
        raise PipelineError(f"interrupted while running {', '.join(running)}\n"
                            f"resume with: {runner.command} --jobs {jobs}") from None
    if failed:
        job = failed[0]
        how = (f"was killed (signal {-job.returncode}, after {job.retries} restarts" if job.killed
               else f"failed (exit code {job.returncode}")
        raise PipelineError(f"step '{job.step.name}' {how}; its output: {job.log_path})\n"
                            f"resume with: {runner.command} --jobs {jobs}")
    return done


def check_cores(launcher: Launcher, jobs: int, threads: int, log: Callable[[str], None]) -> None:
    """Refuse steps of more torch threads than the largest machine has cores; say when ``jobs`` steps side by side
    want more cores than there are.

    Raises:
        UsageError: ``threads`` is more than the largest machine's cores.
    """
    if threads > launcher.cores:
        raise UsageError(f"--threads {threads}: a step runs on one machine, and the largest has {launcher.cores} "
                         "cores")
    if jobs * threads > launcher.total_cores:
        log(f"{jobs} steps of {threads} torch thread{'s' if threads > 1 else ''} side by side want {jobs * threads} "
            f"cores and there are {launcher.total_cores}: they run slower side by side than one at a time")


def _reap(running: dict[str, StepJob], done: list[str], failed: list[StepJob]) -> None:
    """Move the workers that have ended from ``running`` to ``done`` (exit code 0, by name) or ``failed``."""
    for name, job in list(running.items()):
        if not job.done():
            continue
        del running[name]
        if job.returncode == 0:
            done.append(name)
        else:
            failed.append(job)


def _restart_killed(runner, launcher: Launcher, running: dict[str, StepJob], failed: list[StepJob],
                    log_dir: Path) -> None:
    """Start again, resuming, the steps in ``failed`` whose worker was killed and has retries left."""
    for job in [j for j in failed if j.killed and j.retries < WORKER_RETRIES]:
        failed.remove(job)
        runner.log(f"step '{job.step.name}': its worker was killed (signal {-job.returncode}); starting it "
                   f"again from what it left ({job.retries + 1} of {WORKER_RETRIES})")
        again = _spawn(runner, launcher, job.step, False, job.threads, log_dir, append=True)
        again.retries = job.retries + 1
        running[job.step.name] = again


def _stop(jobs: Collection[StepJob]) -> None:
    """End the workers of ``jobs``."""
    for job in jobs:
        job.worker.stop()


def worker_command(runner, step: Step, fresh: bool, threads: int) -> list[str]:
    """The arguments (after the interpreter) of a worker that runs ``step`` of ``runner``'s pipeline (paths as the
    runner has them: a worker runs in this process's working directory)."""
    command = ["-m", "spiral.pipeline.workers", str(runner.path), step.name,
               "--runs-dir", str(runner.plan.runs_dir), "--checkpoints-dir", str(runner.plan.checkpoints_dir),
               "--device", runner.plan.spec.device, "--threads", str(threads)]
    if fresh:
        command.append("--fresh")
    if runner.accept_code_changes:
        command.append("--accept-code-changes")
    return command + [arg for override in runner.overrides for arg in ("--set", override)]


def _spawn(runner, launcher: Launcher, step: Step, fresh: bool, threads: int, log_dir: Path, *,
           append: bool = False) -> StepJob:
    env = {"OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads), "PYTHONUNBUFFERED": "1"}
    log_path = log_dir / f"{step.dirname}.log"
    if not append:
        log_path.write_text("")
    worker = launcher.start(worker_command(runner, step, fresh, threads), env, threads, log_path,
                            lambda line: runner.log(f"[{step.name}] {line}"))
    runner.log(f"step '{step.name}' started in a worker ({threads} torch thread{'s' if threads > 1 else ''}; "
               f"output also in {log_path})")
    return StepJob(step, worker, log_path, threads)
