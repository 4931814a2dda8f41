"""PPO's update in four variants, timed in one process on the same trainer: float32 or bfloat16 autocast
(``ppo.mixed_precision``), mini-batches gathered by rsl-rl's generator (once per mini-batch and epoch) or by
``spiral.train.batches.gather_once`` (once per update).

Run from the repository root with spiral's interpreter, on an otherwise idle machine:

    python benchmarks/ppo_update_variants.py pipelines/full.yaml --stage solo --repeats 4 --json OUT.json

The variants take turns, each after a fresh rollout of the same stage (a repeat times every variant once), so that a
change of the machine's speed during the run hits all of them alike; the best and every time per variant are printed.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import torch
from rsl_rl.storage import RolloutStorage

from spiral.config import load_pipeline, resolve_airframe
from spiral.env.setting import RaceSetting
from spiral.train.batches import GatherOnceStorage
from spiral.train.runner import StageTrainer

VARIANTS = [(precision, gather) for precision in ("float32", "bfloat16") for gather in ("rsl_rl", "gather_once")]


def time_variants(pipeline: Path, stage_name: str, *, repeats: int, worlds: int | None = None,
                  device: str = "cpu") -> dict[str, list[float]]:
    """Seconds of ``repeats`` updates per variant (keys ``"<precision> <gather>"``)."""
    spec, track = load_pipeline(pipeline)
    stage = next((s for s in spec.stages if s.name == stage_name), None)
    if stage is None:
        raise SystemExit(f"--stage: {pipeline} has no stage named {stage_name!r}")
    if worlds is not None:
        stage = stage.model_copy(update={"worlds": worlds})
    times: dict[str, list[float]] = defaultdict(list)
    with tempfile.TemporaryDirectory() as tmp:
        setting = RaceSetting(track, resolve_airframe(spec.airframe, source=str(pipeline)), spec.sim)
        trainer = StageTrainer(setting, stage, Path(tmp), device=device, seed=spec.seed, progress=False)
        alg, storage = trainer.runner.alg, trainer.runner.alg.storage
        alg.train_mode()
        obs = trainer.collect(trainer.vec_env.get_observations())[0]
        alg.update()  # warm-up
        for _ in range(repeats):
            for precision, gather in VARIANTS:
                alg.use_mixed_precision = precision == "bfloat16"
                # the same rollout buffers, handed out by one generator or the other
                storage.__class__ = GatherOnceStorage if gather == "gather_once" else RolloutStorage
                obs = trainer.collect(obs)[0]
                t0 = time.perf_counter()
                alg.update()
                times[f"{precision} {gather}"].append(time.perf_counter() - t0)
    return dict(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("pipeline", type=Path)
    parser.add_argument("--stage", default="solo")
    parser.add_argument("--repeats", type=int, default=4)
    parser.add_argument("--worlds", type=int, default=None, help="override the stage's worlds (smoke runs)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    times = time_variants(args.pipeline, args.stage, repeats=args.repeats, worlds=args.worlds, device=args.device)
    for name, values in times.items():
        print(f"{name:<22} best {min(values):.3f} s  all {', '.join(f'{v:.3f}' for v in values)}")
    if args.json is not None:
        args.json.write_text(json.dumps({"pipeline": str(args.pipeline), "stage": args.stage,
                                         "torch_threads": torch.get_num_threads(), "update_s": times}, indent=2))


if __name__ == "__main__":
    main()
