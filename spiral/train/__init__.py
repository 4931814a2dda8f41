"""PPO training of a stage (rsl-rl) with checkpoints, resume and selection by evaluation."""

from __future__ import annotations

from spiral.train.checkpoint import CheckpointError, FrozenPolicy, load_checkpoint, load_policy, save_checkpoint
from spiral.train.runner import EvalScore, StageTrainer, TrainResult, seed_everything

__all__ = [
    "CheckpointError",
    "EvalScore",
    "FrozenPolicy",
    "StageTrainer",
    "TrainResult",
    "load_checkpoint",
    "load_policy",
    "save_checkpoint",
    "seed_everything",
]
