"""The worker process of ``spiral run --jobs N`` (:mod:`spiral.pipeline.parallel` spawns it): run one step of a
pipeline whose lock the parent holds, exactly as the sequential runner would."""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

from spiral.core.threads import take_share
from spiral.pipeline.runner import PipelineRunner
from spiral.pipeline.step import PipelineError

__all__ = ["follow_thread_share", "main"]


def follow_thread_share(path: Path, threads: int) -> bool:
    """Take ``threads`` torch threads now, and from then on the count in ``path`` whenever SIGUSR1 arrives (the
    parent writes it first); False where the platform has no SIGUSR1 (the count then stays).

    The handler runs in the main thread between two Python operations, never inside a torch call, so the new
    count applies from the next operation on. ``path`` is written only after the handler is in place: the parent
    signals a worker whose file exists, never one that a signal would still end.
    """
    take_share(threads)
    if not hasattr(signal, "SIGUSR1"):
        return False

    def on_signal(*_: object) -> None:
        try:
            count = int(path.read_text())
        except (OSError, ValueError):  # a file being replaced, or not ours: keep the current count
            return
        if count >= 1:
            take_share(count)  # deferred while code holds a count of its own (spiral.core.threads.pinned)

    signal.signal(signal.SIGUSR1, on_signal)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(str(threads))
    tmp.replace(path)
    return True


def main(argv: list[str] | None = None) -> int:
    """Worker entry point: run one step of a pipeline whose lock the parent holds."""
    parser = argparse.ArgumentParser(description="Run one pipeline step (spawned by spiral run --jobs)")
    parser.add_argument("pipeline", type=Path)
    parser.add_argument("step")
    parser.add_argument("--runs-dir", type=Path, required=True)
    parser.add_argument("--checkpoints-dir", type=Path, required=True)
    parser.add_argument("--device", required=True)
    parser.add_argument("--threads", type=int, required=True)
    parser.add_argument("--threads-file", type=Path, default=None,
                        help="File the parent writes a new thread share to before it sends SIGUSR1")
    parser.add_argument("--fresh", action="store_true")
    parser.add_argument("--accept-code-changes", action="store_true")
    args = parser.parse_args(argv)
    if args.threads_file is None:
        take_share(args.threads)
    else:
        follow_thread_share(args.threads_file, args.threads)
    runner = PipelineRunner(args.pipeline, runs_dir=args.runs_dir, checkpoints_dir=args.checkpoints_dir,
                            device=args.device, progress=False, log=lambda m: print(m, flush=True),
                            accept_code_changes=args.accept_code_changes)
    try:
        runner.run_step(args.step, fresh=args.fresh)
    except PipelineError as exc:
        print(str(exc).splitlines()[0], file=sys.stderr, flush=True)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
