"""rsl-rl ``VecEnv`` adapter around :class:`RaceEnv` (the only module of spiral.env importing rsl_rl)."""

from __future__ import annotations

import torch
from rsl_rl.env import VecEnv
from tensordict import TensorDict

from spiral.env.mixed import MixedRaceEnv
from spiral.env.race_env import RaceEnv

__all__ = ["RaceVecEnv"]


class RaceVecEnv(VecEnv):
    """Exposes a :class:`RaceEnv` (or a :class:`MixedRaceEnv`) to rsl-rl: one environment per learner drone,
    4 actions."""

    def __init__(self, env: RaceEnv | MixedRaceEnv) -> None:
        self.env = env
        self.num_envs = env.num_envs
        self.num_actions = 4
        self.max_episode_length = env.max_episode_length
        self.device = env.device
        self.cfg = env.cfg.model_dump()

    @property
    def episode_length_buf(self) -> torch.Tensor:
        """Control steps since each learner drone's episode started."""
        return self.env.episode_length_buf

    @episode_length_buf.setter
    def episode_length_buf(self, value: torch.Tensor) -> None:
        self.env.episode_length_buf = value

    def get_observations(self) -> TensorDict:
        """Current learner observations."""
        return self.env.current_observations()

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        """One control step of every world."""
        return self.env.step(actions)
