"""Adapters that need more than ``spiral.env``: the gymnasium envs, whose opponents may be the SE-IBR planner
(``spiral.baselines``). ``import spiral.env`` registers their id ``spiral/Race-v0``."""

from __future__ import annotations

from spiral.adapters.gym_env import NAMED_OPPONENTS, RaceSingleEnv, RaceVectorEnv

__all__ = ["NAMED_OPPONENTS", "RaceSingleEnv", "RaceVectorEnv"]
