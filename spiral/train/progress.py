"""A stage's training log: one row per iteration to TensorBoard and ``train_log.jsonl``, and a progress bar (or a
line per evaluation where there is no terminal, e.g. in a pipeline worker)."""

from __future__ import annotations

import contextlib
import json
import math
from collections.abc import Callable, Iterator
from pathlib import Path

from rich.progress import BarColumn, Progress, TaskID, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from torch.utils.tensorboard import SummaryWriter

__all__ = ["TRAIN_LOG", "TrainLog", "status_line"]


def status_line(row: dict[str, float]) -> str:
    """Success, lap time and speed of an iteration's row, with the evaluation's when there is one."""
    lap = row.get("lap_time", float("nan"))
    text = f"success {row.get('success', 0):.2f} lap {lap:.2f}s fps {row['fps']:.0f}"
    if "eval/success" in row:
        text += f" | eval {row['eval/success']:.2f} @ {row['eval/lap_time']:.2f}s"
    return text


TRAIN_LOG = "train_log.jsonl"
"""A stage's JSON-lines training log in its run folder."""


class TrainLog:
    """Writes ``run_dir/tb`` (TensorBoard) and ``run_dir/train_log.jsonl`` on the main process and shows progress.

    ``show_progress`` draws a bar; otherwise each evaluation logs one line through ``log``.
    """

    def __init__(self, run_dir: Path, name: str, *, main: bool, show_progress: bool,
                 log: Callable[[str], None]) -> None:
        self.run_dir, self.name, self.main, self.show_progress, self.log = run_dir, name, main, show_progress, log
        self._writer: SummaryWriter | None = None
        self._progress: Progress | None = None
        self._task: TaskID | None = None

    @property
    def path(self) -> Path:
        """The JSON-lines log, one row per iteration."""
        return self.run_dir / TRAIN_LOG

    def truncate(self, start: int) -> None:
        """Drop rows of iterations that will be trained again after a resume."""
        if not self.path.exists() or not self.main:
            return
        rows = [line for line in self.path.read_text().splitlines() if line.strip()]
        kept = [line for line in rows if json.loads(line)["iteration"] < start]
        self.path.write_text("".join(line + "\n" for line in kept))

    @contextlib.contextmanager
    def open(self, total: int, start: int) -> Iterator[TrainLog]:
        """Open the TensorBoard writer and the progress bar for iterations ``start`` .. ``total`` − 1."""
        self._writer = SummaryWriter(log_dir=str(self.run_dir / "tb"), flush_secs=30) if self.main else None
        self._progress = Progress(
            TextColumn(f"[bold]{self.name}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
            TimeElapsedColumn(), TimeRemainingColumn(), TextColumn("{task.fields[stats]}"),
            disable=not self.show_progress,
        )
        try:
            with self._progress:
                self._task = self._progress.add_task(self.name, total=total, completed=start, stats="")
                yield self
        finally:
            if self._writer is not None:
                self._writer.close()

    def evaluated(self, it: int, total: int, row: dict[str, float]) -> None:
        """Log a line for an evaluation when no bar shows progress."""
        if not self.show_progress:
            self.log(f"{self.name} {it + 1}/{total} ({row['wall_s']:.0f} s): {status_line(row)}")

    def write(self, it: int, row: dict[str, float]) -> None:
        """Write iteration ``it``'s row (main process only)."""
        if self._writer is None:
            return
        for key, value in row.items():
            if key != "iteration" and isinstance(value, float) and math.isfinite(value):
                self._writer.add_scalar(key if "/" in key else f"train/{key}", value, it)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        with open(self.path, "a") as f:
            f.write(json.dumps(row) + "\n")

    def advance(self, it: int, row: dict[str, float]) -> None:
        """Move the bar past iteration ``it``."""
        if self._progress is not None and self._task is not None:
            self._progress.update(self._task, completed=it + 1, stats=status_line(row))
