"""PPO training of a stage (rsl-rl) with checkpoints, resume and selection by evaluation.

``load_policy`` is re-exported here because the README's example imports it from this package; it lives in
:mod:`spiral.core.checkpoint`, with the rest of the checkpoint format.
"""

from __future__ import annotations

from spiral.core.checkpoint import load_policy
from spiral.train.runner import EvalScore, StageStart, StageTrainer, TrainResult, seed_everything

__all__ = [
    "EvalScore",
    "StageStart",
    "StageTrainer",
    "TrainResult",
    "load_policy",
    "seed_everything",
]
