"""What a pipeline step costs under ``--executor ray`` beyond the local executor, on one machine.

Run from the repository root with spiral's interpreter (Ray installed: ``pip install 'spiral[ray]'``):

    OMP_NUM_THREADS=1 python benchmarks/ray_overhead.py --repeats 2 --json ray_overhead.json

smoke.yaml, whose steps are short (so a step's wall time is mostly what it costs to start and finish one), runs from
scratch in fresh folders with ``--jobs 2`` under both executors, alternately, ``--repeats`` times each; both start
every step in its own worker process. The local Ray instance (as many CPUs as the machine has) is started once,
before the first timed run, as a cluster would be. Printed: each run's wall time, and the difference of the best runs
divided by the pipeline's steps, the overhead per step.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from spiral.pipeline import PipelineRunner
from spiral.pipeline.ray_executor import RayLauncher

SMOKE = Path(__file__).resolve().parents[1] / "pipelines" / "smoke.yaml"


def timed_run(launcher: RayLauncher | None, jobs: int) -> tuple[float, int]:
    """Wall time of smoke.yaml from scratch, and the number of steps that ran."""
    with tempfile.TemporaryDirectory() as tmp:
        runner = PipelineRunner(SMOKE, runs_dir=Path(tmp) / "runs", checkpoints_dir=Path(tmp) / "ckpt",
                                progress=False, log=lambda _: None)
        start = time.perf_counter()
        ran = runner.run(jobs=jobs, launcher=launcher)
        return time.perf_counter() - start, len(ran)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    times: dict[str, list[float]] = {"local": [], "ray": []}
    with RayLauncher() as ray_launcher:
        steps = 0
        for repeat in range(args.repeats):
            order = [("local", None), ("ray", ray_launcher)]
            for name, launcher in order if repeat % 2 == 0 else order[::-1]:
                seconds, steps = timed_run(launcher, args.jobs)
                times[name].append(seconds)
                print(f"{name:5s} run {repeat}: {seconds:6.1f} s ({steps} steps)", flush=True)
    per_step = (min(times["ray"]) - min(times["local"])) / steps
    print(f"overhead per step under Ray: {per_step:+.2f} s (best runs, {steps} steps, --jobs {args.jobs})")
    if args.json:
        args.json.write_text(json.dumps({"times_s": times, "steps": steps, "jobs": args.jobs,
                                         "overhead_per_step_s": per_step, "cpus": os.cpu_count()}, indent=1))


if __name__ == "__main__":
    main()
