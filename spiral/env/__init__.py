"""Batched race environment (torch) over the Warp simulator, and its rsl-rl and gymnasium adapters.

Importing this package registers the gymnasium id ``spiral/Race-v0`` (see :mod:`spiral.env.gym_env`).
"""

from __future__ import annotations

from spiral.env.gym_env import ENV_ID, RaceSingleEnv, RaceVectorEnv, make_race_env, register_envs
from spiral.env.observations import HISTORY_FEATURES, ObservationBuilder
from spiral.env.race_env import RaceEnv
from spiral.env.racing import RaceResults, concat_results, run_races
from spiral.env.rewards import REWARD_TERMS, StepOutcome, compute_rewards

__all__ = [
    "ENV_ID",
    "HISTORY_FEATURES",
    "REWARD_TERMS",
    "ObservationBuilder",
    "RaceEnv",
    "RaceResults",
    "RaceSingleEnv",
    "RaceVectorEnv",
    "StepOutcome",
    "compute_rewards",
    "concat_results",
    "make_race_env",
    "register_envs",
    "run_races",
]

register_envs()
