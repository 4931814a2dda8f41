"""Digests of a fixed simulator rollout and of a few PPO iterations, to compare runs across machines bit for bit.

Two hosts that print the same digests compute the same bits: the simulator's kernels, torch's forward and backward
passes and the optimiser's steps, as a pipeline's training steps use them. docs/results.md ("Reproducibility") lists
the digests measured so far, host by host.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path
from typing import Any

import torch
import warp as wp

from spiral.config.airframe import AIRFRAMES
from spiral.config.load import load_track
from spiral.config.sim import SimCfg
from spiral.config.stage import StageSpec
from spiral.core.checkpoint import load_checkpoint, with_legacy_defaults
from spiral.core.device import torch_threads
from spiral.core.numerics import TORCH_AVX2_ENV, cpu_target, portable_build
from spiral.env.setting import RaceSetting
from spiral.sim.bench import DEFAULT_TRACK, _make_world, machine_info, time_warp
from spiral.sim.options import MODULE_OPTIONS
from spiral.train.runner import StageTrainer

__all__ = ["numerics_in_force", "run_digests", "sim_digest", "training_digest"]


def numerics_in_force() -> dict[str, Any]:
    """The CPU arithmetic of this process: the target, the simulator's build flags and torch's kernel choices."""
    return {
        "cpu_target": cpu_target(),
        "portable_sim": portable_build(),
        "sim_cpu_flags": MODULE_OPTIONS["cpu_compiler_flags"],
        "torch": torch.__version__,
        "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "torch_env": {key: os.environ.get(key) for key in TORCH_AVX2_ENV},
    }


def sim_digest(*, world_count: int = 64, drones: int = 4, steps: int = 200, seed: int = 0) -> str:
    """SHA-256 of the drones' state after ``steps`` control steps of ``spiral bench sim``'s world (circuit6, random
    start points and targets of ``seed``, gates and collisions on)."""
    wp.init()
    world, targets, *_ = _make_world(load_track(DEFAULT_TRACK), AIRFRAMES["cf2x"], world_count, drones, "cpu", seed)
    time_warp(world, targets, steps, 0)
    digest = hashlib.sha256()
    for name in ("pos", "vel", "quat", "omega"):
        digest.update(getattr(world.state, name).numpy().tobytes())
    return digest.hexdigest()


def training_digest(*, worlds: int = 64, iterations: int = 3, seed: int = 0) -> str:
    """SHA-256 of the actor's weights after ``iterations`` PPO iterations of a solo stage on circuit6 (the compact
    observation without the inputs about other drones, one torch thread, on the CPU). The stage keeps the settings
    it had before the schema's defaults became the shipped recipe's (:data:`~spiral.core.checkpoint.LEGACY_DEFAULTS`),
    so that its digests compare with those measured before."""
    stage = StageSpec.model_validate({
        "name": "digest", "worlds": worlds, "iterations": iterations,
        "env": with_legacy_defaults({"obs": {"history_len": 1, "gate_normals": True, "pid_integral": True}}, ("env",)),
        "ppo": with_legacy_defaults({"save_interval": iterations}, ("ppo",)),
        "selection": with_legacy_defaults({"interval": 10_000}, ("selection",))})
    with torch_threads(1), tempfile.TemporaryDirectory() as tmp:
        StageTrainer(RaceSetting(load_track(DEFAULT_TRACK), AIRFRAMES["cf2x"], SimCfg()), stage, Path(tmp),
                     seed=seed, progress=False).train(lambda trainer, it: {})
        weights = load_checkpoint(Path(tmp) / "ckpt" / f"model_{iterations - 1}.pt")["actor_state_dict"]
    digest = hashlib.sha256()
    for key in sorted(weights):
        digest.update(key.encode())
        digest.update(weights[key].contiguous().numpy().tobytes())
    return digest.hexdigest()


def run_digests(*, training: bool = True) -> dict[str, Any]:
    """Both digests (the training one unless ``training`` is False) with the machine and the arithmetic in force."""
    out: dict[str, Any] = {"machine": machine_info(), "numerics": numerics_in_force(), "sim": sim_digest()}
    if training:
        out["training"] = training_digest()
    return out
