"""The gymnasium id of the race environment, registered on ``import spiral.env``."""

from __future__ import annotations

import gymnasium

__all__ = ["ENV_ID", "register_envs"]

ENV_ID = "spiral/Race-v0"
"""gymnasium id of the race environment."""


def register_envs() -> None:
    """Register ``spiral/Race-v0`` with gymnasium (done on ``import spiral.env``; repeated calls are no-ops).

    The entry points are strings: gymnasium imports :mod:`spiral.adapters.gym_env` (which sits above
    ``spiral.baselines``, for its SE-IBR opponent) only when an env is made.
    """
    if ENV_ID not in gymnasium.registry:
        gymnasium.register(ENV_ID, entry_point="spiral.adapters.gym_env:RaceSingleEnv",
                           vector_entry_point="spiral.adapters.gym_env:RaceVectorEnv")
