"""``spiral train PIPELINE --stage S --distributed`` under torchrun: one training step over every rank.

Rank 0 runs the step through the pipeline as usual (lock, resume, checkpoints, manifest). The other ranks run the
same step function in a private scratch folder, so they never touch the run folder; the trainer then starts them
from rank 0's state and only rank 0 writes (see :mod:`spiral.train.distributed`). Every rank reads the stage's
inputs (upstream manifests, initial checkpoint, pool), so ``runs/`` and ``checkpoints/`` must be visible to every
node at the same path.
"""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path

from spiral.core.errors import UsageError
from spiral.pipeline.manifest import read_manifest
from spiral.pipeline.runner import PipelineRunner
from spiral.pipeline.step import StepContext
from spiral.train.distributed import StageCancelledError, cancel_workers, init_distributed, shutdown

__all__ = ["train_stage_distributed"]


def _quiet(_: str) -> None:
    """Ranks > 0 do not log."""


def train_stage_distributed(
    pipeline: Path,
    stage: str,
    *,
    runs_dir: Path = Path("runs"),
    checkpoints_dir: Path = Path("checkpoints"),
    device: str | None = None,
    log: Callable[[str], None] = print,
    overrides: Sequence[str] = (),
) -> list[str]:
    """Train ``stage`` of ``pipeline`` with ``overrides`` set with every torchrun rank; return the steps rank 0 ran
    (ranks > 0 return ``[]``).

    Raises:
        ValueError: outside torchrun or with a device that is not this rank's.
    """
    info, dev = init_distributed(device)
    name = f"train:{stage}"
    if info.is_main:
        log(f"distributed training: {info.world_size} processes, rank 0 on {dev}")
        runner = PipelineRunner(pipeline, runs_dir=runs_dir, checkpoints_dir=checkpoints_dir, device=dev, log=log,
                                overrides=overrides)
        ran = runner.run(only=name)
        if name not in ran:  # complete already: release the ranks waiting for rank 0's training state
            cancel_workers()
    else:
        ran = []
        _train_worker(PipelineRunner(pipeline, runs_dir=runs_dir, checkpoints_dir=checkpoints_dir, device=dev,
                                     log=_quiet, progress=False, overrides=overrides), name, info.rank)
    shutdown()
    return ran


def _train_worker(runner: PipelineRunner, name: str, rank: int) -> None:
    """Run step ``name``'s function in a scratch folder that is deleted afterwards."""
    steps = {s.name: s for s in runner.steps}
    if name not in steps:
        raise UsageError(f"unknown step {name!r}; steps: {', '.join(steps)}")
    step = steps[name]
    inputs = {i: read_manifest(runner.plan.run_root / steps[i].dirname) or {} for i in step.inputs}
    # StageCancelledError: rank 0 found the step complete and trains nothing
    with tempfile.TemporaryDirectory(prefix=f"spiral-rank{rank}-") as scratch, contextlib.suppress(StageCancelledError):
        step.fn(StepContext(Path(scratch), inputs, _quiet, progress=False))
