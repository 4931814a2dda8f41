"""``spiral run --executor ray``: the pipeline's steps as Ray tasks on a cluster whose nodes share the working
directory (the run and checkpoint folders, the pipeline file, the Python environment).

Each step is one Ray task asking for its CPU threads (and one GPU on a CUDA device). The task starts the same worker
process as the local executor (``python -m spiral.pipeline.workers``) on its node, in the driver's working
directory, its output appended to the step's log file, which the driver follows and relays. Everything else is the
driver's, as with the local executor: the pipeline lock, the dependency order, fingerprints and manifests (written by
the worker, last and atomically), resume from the newest checkpoint, and retries of a worker that was killed or lost
with its node (:data:`spiral.pipeline.parallel.WORKER_RETRIES`; Ray's own task retries are off).

Ray is an optional extra (``pip install 'spiral[ray]'``); nothing imports this module unless ``--executor ray``.
"""

from __future__ import annotations

import contextlib
import os
import platform
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from spiral.core.errors import UsageError

__all__ = ["RAY_EXTRA", "RayLauncher", "import_ray"]

RAY_EXTRA = "pip install 'spiral[ray]'"
FORWARDED_ENV = ("SPIRAL_", "WARP_", "CUBLAS_WORKSPACE_CONFIG")
"""Environment variables of the driver that reach the workers (those that choose a build or a code path)."""
TAIL_POLL_S = 0.1


def import_ray() -> Any:
    """The ``ray`` module; a clear error naming the extra when it is not installed."""
    try:
        import ray
    except ImportError:
        raise UsageError(f"--executor ray needs Ray, which is not installed: {RAY_EXTRA}") from None
    return ray


class RayLauncher:
    """Workers as Ray tasks (:class:`spiral.pipeline.parallel.Launcher`). Connects to the cluster at ``address``
    (``auto``, ``ray://host:port``, ``host:port``; by default ``RAY_ADDRESS`` or a new local instance) unless Ray is
    already initialised in this process; :meth:`close` disconnects what it connected."""

    def __init__(self, address: str | None = None, *, device: str = "cpu") -> None:
        if device.startswith("cuda") and device != "cuda:0":
            raise UsageError(f"device {device}: under --executor ray a step's GPU is the one Ray grants it; "
                             "use --device cuda")
        self._ray = import_ray()
        self._owns = not self._ray.is_initialized()
        if self._owns:
            local = address is None and not os.environ.get("RAY_ADDRESS")
            # Ray runs its workers at nice 15 unless told: a step's training would yield to anything else on the node
            self._ray.init(address=address, include_dashboard=False, log_to_driver=False,
                           **({"_system_config": {"worker_niceness": 0}} if local else {}))
        nodes = [n["Resources"] for n in self._ray.nodes() if n.get("Alive")]
        self.cores = int(max(n.get("CPU", 0) for n in nodes))
        """The largest node's CPU cores: no step can ask for more threads than one node has."""
        self.total_cores = int(sum(n.get("CPU", 0) for n in nodes))
        self.gpus = 1 if device.startswith("cuda") else 0
        self._task = self._ray.remote(_run_worker)

    def start(self, command: list[str], env: dict[str, str], threads: int, log_path: Path,
              log: Callable[[str], None]) -> _RayWorker:
        forwarded = {k: v for k, v in os.environ.items() if k.startswith(FORWARDED_ENV)}
        offset = log_path.stat().st_size  # the scheduler has created or emptied it
        ref = self._task.options(num_cpus=threads, num_gpus=self.gpus, max_retries=0).remote(
            command, {**forwarded, **env}, str(log_path.resolve()), os.getcwd())
        return _RayWorker(self._ray, ref, log_path, offset, log)

    def close(self) -> None:
        """Disconnect from the cluster if this launcher connected."""
        if self._owns and self._ray.is_initialized():
            self._ray.shutdown()

    def __enter__(self) -> RayLauncher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _RayWorker:
    """A step's Ray task, and the thread that relays its log file."""

    def __init__(self, ray: Any, ref: Any, log_path: Path, offset: int, log: Callable[[str], None]) -> None:
        self._ray, self._ref, self._log_path = ray, ref, log_path
        self._ended = threading.Event()
        self._tail = threading.Thread(target=_tail, args=(log_path, offset, log, self._ended), daemon=True)
        self._tail.start()

    def poll(self) -> int | None:
        ready, _ = self._ray.wait([self._ref], timeout=0)
        if not ready:
            return None
        code = self._result()
        self._ended.set()
        self._tail.join()
        return code

    def _result(self) -> int:
        """The task's exit code: the worker's, 1 if the task failed, -SIGKILL if its Ray worker or node was lost."""
        try:
            code, problem = self._ray.get(self._ref)
        except self._ray.exceptions.RayTaskError as exc:
            self._note(f"the Ray task failed: {exc}")
            return 1
        except self._ray.exceptions.RayError as exc:
            self._note(f"the Ray worker running it was lost ({type(exc).__name__})")
            return -int(signal.SIGKILL)
        if problem:
            self._note(problem)
        return code

    def _note(self, message: str) -> None:
        """A line about the task (not from its worker) into the step's log, and to the driver's log."""
        with self._log_path.open("a") as out:
            out.write(f"spiral: {message}\n")

    def stop(self) -> None:
        self._ray.cancel(self._ref, force=True)
        with contextlib.suppress(self._ray.exceptions.RayError):
            self._ray.get(self._ref)
        self._ended.set()
        self._tail.join()


def _tail(path: Path, offset: int, log: Callable[[str], None], ended: threading.Event) -> None:
    """Relay the lines appended to ``path`` after ``offset`` until ``ended`` is set and everything is read."""
    with path.open() as stream:
        stream.seek(offset)
        partial = ""
        while True:
            chunk = stream.readline()
            if chunk:
                partial += chunk
                if partial.endswith("\n"):
                    log(partial.rstrip("\n"))
                    partial = ""
            elif ended.is_set():
                break
            else:
                time.sleep(TAIL_POLL_S)
        if partial:
            log(partial)


def _run_worker(command: list[str], env: dict[str, str], log_path: str, cwd: str) -> tuple[int, str | None]:
    """Inside a Ray task: run a pipeline worker with this node's interpreter in ``cwd``, its output appended to
    ``log_path``. Returns its exit code (negative: killed by that signal) and what kept it from starting (None when
    it ran)."""
    if not Path(log_path).parent.is_dir() or not Path(cwd).is_dir():
        node = platform.node()
        return 2, (f"node {node} does not see {Path(log_path).parent} or {cwd}: the nodes of the cluster "
                         "must share the working directory")
    with open(log_path, "a") as out:
        process = subprocess.Popen([sys.executable, *command, "--parent", str(os.getpid())], stdout=out,
                                   stderr=subprocess.STDOUT, cwd=cwd, env={**os.environ, **env})
        return process.wait(), None
