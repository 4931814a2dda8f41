"""Time to a solo policy: train a pipeline's solo stage for several seeds and report when its selection evaluation
first reaches the target (success and lap time), in iterations, env steps and wall seconds.

Run from the repository root with spiral's interpreter, on an otherwise idle machine:

    python benchmarks/time_to_solo.py pipelines/full.yaml --seeds 0,1,2 --json benchmarks/time_to_solo.json

Each seed trains ``spiral train PIPELINE --stage solo`` in a fresh run directory (the pipeline file copied with
its ``seed`` changed, everything else as written), one seed after the other.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml


def first_reaching(rows: list[dict[str, Any]], success: float, lap: float) -> dict[str, Any] | None:
    """The first evaluated row of a train log whose success is at least ``success`` and lap at most ``lap``."""
    for row in rows:
        s, t = row.get("eval/success"), row.get("eval/lap_time")
        if s is not None and t is not None and s >= success and t <= lap:
            return row
    return None


def seeded_pipeline(pipeline: Path, seed: int, out: Path) -> Path:
    """Copy ``pipeline`` to ``out`` with its seed set and its track path made absolute."""
    data = yaml.safe_load(pipeline.read_text())
    data["seed"] = seed
    data["track"] = str((pipeline.parent / data["track"]).resolve())
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    return out


def run_seed(pipeline: Path, stage: str, seed: int, *, success: float, lap: float,
             threads: int = 1, sim_threads: int = 1) -> dict[str, Any]:
    """Train the stage for one seed and return when it first reached the target."""
    with tempfile.TemporaryDirectory() as tmp:
        spec = seeded_pipeline(pipeline, seed, Path(tmp) / "pipeline.yaml")
        cmd = [sys.executable, "-m", "spiral.cli", "train", str(spec), "--stage", stage,
               "--runs-dir", f"{tmp}/runs", "--checkpoints-dir", f"{tmp}/checkpoints",
               "--threads", str(threads), "--sim-threads", str(sim_threads)]
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - t0
        log = next(Path(tmp, "runs").glob(f"*/train-{stage}/train_log.jsonl"))
        rows = [json.loads(line) for line in log.read_text().splitlines()]
    hit = first_reaching(rows, success, lap)
    return {"seed": seed, "stage_wall_s": wall, "iterations": len(rows),
            "reached_at_iteration": hit["iteration"] + 1 if hit else None,
            "reached_after_s": hit["wall_s"] if hit else None,
            "success": hit["eval/success"] if hit else None, "lap_time": hit["eval/lap_time"] if hit else None}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pipeline", type=Path, nargs="?", default=Path("pipelines/full.yaml"))
    parser.add_argument("--stage", default="solo")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--success", type=float, default=0.95)
    parser.add_argument("--lap", type=float, default=5.5)
    parser.add_argument("--threads", type=int, default=1, help="spiral train --threads (torch threads)")
    parser.add_argument("--sim-threads", type=int, default=1, help="spiral train --sim-threads")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    load = os.getloadavg()
    rows = [run_seed(args.pipeline, args.stage, int(s), success=args.success, lap=args.lap,
                     threads=args.threads, sim_threads=args.sim_threads) for s in args.seeds.split(",")]
    print("| seed | reached at iteration | after [s] | success | lap [s] | stage wall [s] |")
    print("|---|---:|---:|---:|---:|---:|")
    for r in rows:
        hit = r["reached_at_iteration"] is not None
        cells = (r["reached_at_iteration"], f"{r['reached_after_s']:.0f}", r["success"], f"{r['lap_time']:.2f}") \
            if hit else ("-",) * 4
        print(f"| {r['seed']} | " + " | ".join(map(str, cells)) + f" | {r['stage_wall_s']:.0f} |")
    result = {"pipeline": str(args.pipeline), "stage": args.stage, "threads": args.threads,
              "sim_threads": args.sim_threads,
              "target": {"success": args.success, "lap": args.lap}, "load_at_start": load, "results": rows}
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
