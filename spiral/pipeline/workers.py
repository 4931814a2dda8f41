"""The worker process of ``spiral run --jobs N`` (:mod:`spiral.pipeline.parallel` spawns it): run one step of a
pipeline whose lock the parent holds, exactly as the sequential runner would."""

from __future__ import annotations

import argparse
import os
import signal
import sys
from pathlib import Path

from spiral.pipeline.runner import PipelineRunner
from spiral.pipeline.step import PipelineError

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    """Worker entry point: run one step of a pipeline whose lock the parent holds."""
    parser = argparse.ArgumentParser(description="Run one pipeline step (spawned by spiral run --jobs)")
    parser.add_argument("pipeline", type=Path)
    parser.add_argument("step")
    parser.add_argument("--runs-dir", type=Path, required=True)
    parser.add_argument("--checkpoints-dir", type=Path, required=True)
    parser.add_argument("--device", required=True)
    parser.add_argument("--threads", type=int, required=True)
    parser.add_argument("--fresh", action="store_true")
    parser.add_argument("--accept-code-changes", action="store_true")
    parser.add_argument("--set", action="append", default=[], dest="overrides")
    parser.add_argument("--parent", type=int, help="The process that started this worker: end with it")
    args = parser.parse_args(argv)
    if args.parent is not None:
        end_with_parent(args.parent)
    runner = PipelineRunner(args.pipeline, runs_dir=args.runs_dir, checkpoints_dir=args.checkpoints_dir,
                            device=args.device, progress=False, log=lambda m: print(m, flush=True),
                            accept_code_changes=args.accept_code_changes, overrides=args.overrides)
    try:
        runner.run_step(args.step, fresh=args.fresh, threads=args.threads)
    except PipelineError as exc:
        print(str(exc).splitlines()[0], file=sys.stderr, flush=True)
        return 1
    return 0


def end_with_parent(parent: int) -> None:
    """Have the kernel kill this worker when the process that started it ends (Linux): a killed ``spiral run`` or
    Ray task leaves no worker training on while another run takes the pipeline's lock. Exits at once if ``parent``
    has already ended."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != parent:
        sys.exit(1)


if __name__ == "__main__":
    sys.exit(main())
