"""End-to-end training throughput: env steps per second of PPO iterations, split into rollout and update."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from spiral.config.stage import StageSpec
from spiral.env.setting import RaceSetting
from spiral.train.runner import StageTrainer

__all__ = ["LAYOUTS", "run_train_bench"]

LAYOUTS: dict[str, dict[str, Any]] = {
    "compact": {"history_len": 1, "gate_normals": True, "pid_integral": True},
    "paper": {"history_len": 50},
}
"""Observation layouts compared: the pipelines' compact one and the paper's K = 50 history."""


def run_train_bench(setting: RaceSetting, *, worlds: int = 1024, iterations: int = 10, warmup: int = 2,
                    device: str = "cpu", seed: int = 0) -> dict[str, Any]:
    """Time ``iterations`` PPO iterations of a solo stage (after ``warmup``) for each observation layout."""
    rows = []
    for name, obs in LAYOUTS.items():
        stage = StageSpec.model_validate({
            "name": f"bench-{name}", "worlds": worlds, "iterations": warmup + iterations,
            "env": {"obs": obs}, "ppo": {"save_interval": 10_000}, "selection": {"interval": 10_000}})
        with tempfile.TemporaryDirectory() as tmp:
            trainer = StageTrainer(setting, stage, Path(tmp), device=device, seed=seed,
                                   progress=False)
            t0 = time.perf_counter()
            history = trainer.train(lambda trainer, it: {}).history[warmup:]
            wall = time.perf_counter() - t0
        collect = sum(r["collect_s"] for r in history)
        learn = sum(r["learn_s"] for r in history)
        steps = len(history) * stage.ppo.num_steps_per_env * worlds
        rows.append({
            "layout": name, "obs_dim": trainer.env.obs_dim, "worlds": worlds, "iterations": len(history),
            "env_steps_per_s": steps / (collect + learn), "rollout_share": collect / (collect + learn),
            "update_share": learn / (collect + learn), "iteration_s": (collect + learn) / len(history),
            "stage_wall_s": wall,
        })
    return {"device": device, "torch_threads": torch.get_num_threads(), "results": rows}
