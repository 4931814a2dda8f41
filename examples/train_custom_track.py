"""Train a policy on a track defined in Python, then race it: spiral's Python API on one page.

    python examples/train_custom_track.py [--device cuda:0] [--iterations 5]

The settings are tiny so that it finishes in seconds on a CPU; the policy will not have learned to race yet.
For real budgets, copy a stage from pipelines/full.yaml.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import torch

from spiral.config import AIRFRAMES, SimCfg, StageSpec, TrackSpec
from spiral.env import RaceEnv, RaceSetting, run_races
from spiral.train import StageTrainer, load_policy

# A 3-gate slalom: every field is documented in `spiral schema` / spiral/config/track.py.
TRACK = TrackSpec.model_validate({
    "kind": "track",
    "name": "slalom3",
    "gates": [
        {"position": [2.0, 0.5, 1.0], "rpy_deg": [0, 0, 0]},
        {"position": [4.0, -0.5, 1.4], "rpy_deg": [0, 0, 0]},
        {"position": [6.0, 0.5, 1.0], "rpy_deg": [0, 0, 0]},
    ],
    "start": {"center": [0.0, 0.0, 1.0], "size": [0.4, 0.4, 0.2]},
    "bounds": {"min": [-1.5, -2.5, 0.0], "max": [7.5, 2.5, 3.0]},
    "time_limit_s": 8.0,
})


def main() -> None:
    """Train briefly, then race the best policy from the start box."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", help="cpu or cuda:N")
    parser.add_argument("--iterations", type=int, default=5, help="PPO iterations")
    args = parser.parse_args()
    torch.set_num_threads(1)  # networks this small run faster on one CPU thread, and busy CPUs stall thread pools

    stage = StageSpec(
        name="solo", scenario="solo", worlds=32, iterations=args.iterations,
        env={"obs": {"history_len": 2, "gate_normals": True, "pid_integral": True}},
        ppo={"num_steps_per_env": 16, "actor_hidden_dims": [32, 32], "critic_hidden_dims": [32, 32]},
        selection={"interval": args.iterations, "races": 8},
    )
    airframe, sim = AIRFRAMES["cf2x"], SimCfg()
    run_dir = Path(tempfile.mkdtemp(prefix="spiral-example-"))
    trainer = StageTrainer(RaceSetting(TRACK, airframe, sim), stage, run_dir, device=args.device, seed=0,
                           progress=False)
    result = trainer.train()
    print(f"trained {result.iterations} iterations, {result.env_steps} env steps in {result.wall_time_s:.1f} s; "
          f"best checkpoint: {result.best_path}")

    # Race the best policy: 16 seeded races from the start box, no resets.
    policy = load_policy(result.best_path, device=args.device)
    env = RaceEnv(RaceSetting(TRACK, airframe, sim), stage.env, world_count=16, drones_per_world=1, device=args.device,
                  seed=1, training=False)
    races = run_races(env, policy)
    print(f"success {races.finished.float().mean():.2f}, gates passed per race "
          f"{races.gates_passed.float().mean():.2f}, crashes {races.crashed.float().mean():.2f}")


if __name__ == "__main__":
    main()
