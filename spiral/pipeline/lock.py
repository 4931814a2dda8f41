"""One run of a pipeline at a time: a lock file with the owner's pid, taken over when that process is gone."""

from __future__ import annotations

import json
import os
import socket
import time
from pathlib import Path

__all__ = ["PipelineLock", "PipelineLockedError"]


class PipelineLockedError(Exception):
    """Another live process runs the same pipeline."""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class PipelineLock:
    """``with PipelineLock(path):`` holds ``path`` exclusively; a stale lock (dead pid, same host) is taken over."""

    def __init__(self, path: Path, *, log=print) -> None:
        self.path, self.log = Path(path), log

    def __enter__(self) -> PipelineLock:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        me = json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "started": time.time()})
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                self._take_over_if_stale()
                continue
            with os.fdopen(fd, "w") as f:
                f.write(me)
            return self
        raise PipelineLockedError(f"{self.path}: could not be taken")

    def _take_over_if_stale(self) -> None:
        try:
            owner = json.loads(self.path.read_text())
        except (OSError, json.JSONDecodeError):
            owner = {}
        pid, host = owner.get("pid"), owner.get("host")
        if isinstance(pid, int) and host == socket.gethostname() and not _alive(pid):
            self.log(f"taking over the stale lock of process {pid} ({self.path})")
            self.path.unlink(missing_ok=True)
            return
        if not owner:  # unreadable: a writer died between create and write
            self.path.unlink(missing_ok=True)
            return
        raise PipelineLockedError(
            f"{self.path}: pipeline already running (pid {pid} on {host}); wait for it or remove the lock")

    def __exit__(self, *exc: object) -> None:
        self.path.unlink(missing_ok=True)
