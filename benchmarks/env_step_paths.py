"""The training env step on its two paths, timed in one process: the CPU's (ended worlds and each pool member's rows
found on the host) and the sync-free one (starts drawn for every world, every pool member run on every row: the
default off a CPU).

Run from the repository root with spiral's interpreter, on an otherwise idle machine:

    OMP_NUM_THREADS=1 python benchmarks/env_step_paths.py --json env_step_paths.json

Each of pipelines/full.yaml's solo, 1v1 and 2v2 stages is built at its own size (the multi-drone stages from the
published checkpoints and pool, as ``spiral bench ppo`` profiles them). For every repeat, both paths step the same
trainer's env ``--steps`` times with the policy acting between steps (not timed), the path order alternating between
repeats; the best repeat's seconds per step is printed. Run from an older checkout (``PYTHONPATH``), where the flag
does not exist, the script times that checkout's only path twice.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import gpu_check  # the stages' trainers and the switch between the paths

from spiral.train import StageTrainer


def seconds_per_step(trainer: StageTrainer, steps: int) -> float:
    """Wall time of ``steps`` env steps (the policy acting between them is not counted)."""
    alg, env = trainer.runner.alg, trainer.vec_env
    obs, spent = env.get_observations(), 0.0
    with torch.inference_mode():
        for _ in range(steps):
            actions = alg.act(obs)
            t0 = time.perf_counter()
            obs, rewards, dones, extras = env.step(actions)
            spent += time.perf_counter() - t0
            alg.process_env_step(obs, rewards, dones, extras)
            if alg.storage.step == alg.storage.num_transitions_per_env:
                alg.storage.clear()
    return spent / steps


def run(stages: list[str], *, steps: int, repeats: int) -> dict[str, Any]:
    """Seconds per env step of each stage on both paths, every repeat."""
    out: dict[str, Any] = {"torch_threads": torch.get_num_threads(), "steps": steps, "stages": {}}
    for name in stages:
        with tempfile.TemporaryDirectory() as scratch:
            trainer = gpu_check._stage_trainer(name, "cpu", None, Path(scratch))
            trainer.runner.alg.train_mode()
            times: dict[str, list[float]] = {"cpu_path": [], "sync_free": []}
            seconds_per_step(trainer, steps)  # warm-up
            for r in range(repeats):
                order = ("cpu_path", "sync_free") if r % 2 == 0 else ("sync_free", "cpu_path")
                for path in order:
                    gpu_check.set_sync_free(trainer, path == "sync_free")
                    times[path].append(seconds_per_step(trainer, steps))
            out["stages"][name] = {"worlds": trainer.stage.worlds, "seconds_per_step": times}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--stages", default="solo,1v1,2v2")
    ap.add_argument("--steps", type=int, default=48)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    r = run(args.stages.split(","), steps=args.steps, repeats=args.repeats)
    for name, s in r["stages"].items():
        cpu, free = (min(s["seconds_per_step"][k]) for k in ("cpu_path", "sync_free"))
        print(f"{name} ({s['worlds']} worlds): CPU path {1e3 * cpu:.2f} ms per env step, sync-free "
              f"{1e3 * free:.2f} ms ({free / cpu:.2f}x)")
    if args.json:
        args.json.write_text(json.dumps(r, indent=1))


if __name__ == "__main__":
    main()
