"""End-to-end training throughput: env steps per second of PPO iterations, split into rollout and update."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from spiral.config.stage import StageSpec
from spiral.core.checkpoint import with_legacy_defaults
from spiral.env.setting import RaceSetting
from spiral.train.runner import StageTrainer

__all__ = ["LAYOUTS", "run_train_bench"]

_OFF = {"gate_normals": False, "pid_integral": False, "opponent_velocity": False, "teammates": False,
        "closest_approach": False}
LAYOUTS: dict[str, dict[str, Any]] = {
    "compact": {**_OFF, "history_len": 1, "gate_normals": True, "pid_integral": True},
    "paper": {**_OFF, "history_len": 50},
}
"""Observation layouts compared: the compact one without the inputs about other drones (39 inputs) and the paper's
K = 50 history (814)."""


def run_train_bench(setting: RaceSetting, *, worlds: int = 1024, iterations: int = 10, warmup: int = 2,
                    device: str = "cpu", seed: int = 0) -> dict[str, Any]:
    """Time ``iterations`` PPO iterations of a solo stage (after ``warmup``) for each observation layout; the stage
    keeps the settings it had before the schema's defaults became the shipped recipe's
    (:data:`~spiral.core.checkpoint.LEGACY_DEFAULTS`), so that its rates compare with those measured before."""
    rows = []
    for name, obs in LAYOUTS.items():
        stage = StageSpec.model_validate({
            "name": f"bench-{name}", "worlds": worlds, "iterations": warmup + iterations,
            "env": with_legacy_defaults({"obs": obs}, ("env",)),
            "ppo": with_legacy_defaults({"save_interval": 10_000}, ("ppo",)),
            "selection": with_legacy_defaults({"interval": 10_000}, ("selection",))})
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
