"""Batched race environment (torch) over the Warp simulator, its rsl-rl adapter and its PettingZoo view.

Importing this package registers the gymnasium id ``spiral/Race-v0``; the gymnasium envs themselves are in
:mod:`spiral.adapters.gym_env`, above ``spiral.baselines``, whose SE-IBR planner they offer as an opponent.
"""

from __future__ import annotations

from spiral.env.factory import RaceOptions, make_race_env
from spiral.env.observations import HISTORY_FEATURES, ObservationBuilder
from spiral.env.race_env import RaceEnv
from spiral.env.racing import RaceResults, concat_results, run_races
from spiral.env.registration import ENV_ID, register_envs
from spiral.env.rewards import REWARD_TERMS, StepOutcome, compute_rewards
from spiral.env.setting import RaceSetting

__all__ = [
    "ENV_ID",
    "HISTORY_FEATURES",
    "REWARD_TERMS",
    "ObservationBuilder",
    "RaceEnv",
    "RaceOptions",
    "RaceResults",
    "RaceSetting",
    "StepOutcome",
    "compute_rewards",
    "concat_results",
    "make_race_env",
    "register_envs",
    "run_races",
]

register_envs()
