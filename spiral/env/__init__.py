"""Batched race environment (torch) over the Warp simulator, and its rsl-rl adapter."""

from __future__ import annotations

from spiral.env.observations import HISTORY_FEATURES, ObservationBuilder
from spiral.env.race_env import OpponentPolicy, RaceEnv
from spiral.env.racing import RaceResults, race_winners, run_races
from spiral.env.rewards import REWARD_TERMS, StepOutcome, compute_rewards

__all__ = [
    "HISTORY_FEATURES",
    "REWARD_TERMS",
    "ObservationBuilder",
    "OpponentPolicy",
    "RaceEnv",
    "RaceResults",
    "StepOutcome",
    "compute_rewards",
    "race_winners",
    "run_races",
]
