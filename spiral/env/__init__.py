"""Batched race environment (torch) over the Warp simulator, and its rsl-rl adapter."""

from __future__ import annotations

from spiral.env.observations import HISTORY_FEATURES, ObservationBuilder
from spiral.env.race_env import OpponentPolicy, RaceEnv
from spiral.env.rewards import REWARD_TERMS, StepOutcome, compute_rewards

__all__ = [
    "HISTORY_FEATURES",
    "REWARD_TERMS",
    "ObservationBuilder",
    "OpponentPolicy",
    "RaceEnv",
    "StepOutcome",
    "compute_rewards",
]
