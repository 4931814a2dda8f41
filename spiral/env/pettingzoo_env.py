"""PettingZoo ``ParallelEnv`` view of one race: one agent per drone, every drone driven by the caller.

Needs the optional ``pettingzoo`` package (``pip install 'spiral[pettingzoo]'``). The race runs like an evaluation
race: drones start in the track's start box, a drone that crashes or finishes leaves the race (its agent is
removed) while the others fly on, and the time limit truncates whoever is still racing.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv

from spiral.config.airframe import AirframeCfg
from spiral.config.env import EnvCfg
from spiral.config.sim import SimCfg
from spiral.config.track import TrackSpec
from spiral.core.scenario import SCENARIO_DRONES
from spiral.env.factory import RaceOptions, make_race_env

__all__ = ["RaceParallelEnv"]


class RaceParallelEnv(ParallelEnv):
    """A ``solo``, ``1v1`` or ``2v2`` race with agents ``drone_0`` ... ``drone_{D-1}`` (teams: slots 0, 1 vs 2, 3
    in 2v2; 0 vs 1 in 1v1). Observations are float32 vectors (each drone's own view, as the policies see it),
    actions Box(−1, 1, (4,)). ``infos`` of an agent that leaves hold ``success``, ``crashed`` and ``lap_time``.

    Args:
        track: A ``TrackSpec``, a track YAML file, or the name of a shipped track.
        scenario: ``solo``, ``1v1`` or ``2v2``.
        env_cfg, sim, airframe, device, seed: as in :class:`spiral.env.factory.RaceOptions`.
    """

    metadata: ClassVar[dict[str, Any]] = {"name": "spiral_race_v0", "render_modes": [], "is_parallelizable": True}

    def __init__(
        self,
        track: str | Path | TrackSpec = "oval4",
        *,
        scenario: Literal["solo", "1v1", "2v2"] = "1v1",
        env_cfg: EnvCfg | dict | None = None,
        sim: SimCfg | dict | None = None,
        airframe: str | AirframeCfg = "cf2x",
        device: str = "cpu",
        seed: int = 0,
    ) -> None:
        drones = SCENARIO_DRONES.get(scenario, 0)
        self.race = make_race_env(RaceOptions(track, scenario=scenario, env_cfg=env_cfg, sim=sim, airframe=airframe,
                                              learner_slots=range(drones), device=device, seed=seed, training=False))
        self.possible_agents = [f"drone_{i}" for i in range(drones)]
        self.agents: list[str] = []
        self._index = {agent: i for i, agent in enumerate(self.possible_agents)}
        obs_space = spaces.Box(-np.inf, np.inf, shape=(self.race.obs_dim,), dtype=np.float32)
        act_space = spaces.Box(-1.0, 1.0, shape=(4,), dtype=np.float32)
        self.observation_spaces = {a: obs_space for a in self.possible_agents}
        self.action_spaces = {a: act_space for a in self.possible_agents}

    def observation_space(self, agent: str) -> spaces.Box:
        """Observation space of ``agent`` (the same object on every call)."""
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Box:
        """Action space of ``agent`` (the same object on every call)."""
        return self.action_spaces[agent]

    def _obs(self, obs: torch.Tensor, agents: list[str]) -> dict[str, np.ndarray]:
        rows = obs.detach().cpu().numpy()
        return {a: rows[self._index[a]].copy() for a in agents}

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Start a new race (``seed`` reseeds the start placements)."""
        if seed is not None:
            self.race.generator.manual_seed(seed)
        obs = self.race.reset()["policy"]
        self.agents = list(self.possible_agents)
        return self._obs(obs, self.agents), {a: {} for a in self.agents}

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Fly one control step; agents missing from ``actions`` hold their position."""
        race = self.race
        batch = torch.zeros(race.num_envs, 4, device=race.device)
        for agent, action in actions.items():
            batch[self._index[agent]] = torch.as_tensor(np.asarray(action, dtype=np.float32), device=race.device)
        obs, rewards, _, _ = race.step(batch)
        idx = race.learner_idx
        out = (race.records.crashed | race.records.finished)[idx].cpu()
        limit = race.world_tracks.world_time_limit[0]
        time_up = bool(race.world_time()[0] >= limit - 1e-6) or bool(race.world_nonfinite[0] != 0)
        live, reward = self.agents, rewards.cpu()
        terminated = {a: bool(out[self._index[a]]) for a in live}
        truncated = {a: time_up and not terminated[a] for a in live}
        infos: dict[str, dict] = {a: {} for a in live}
        for a in live:
            if terminated[a] or truncated[a]:
                i = idx[self._index[a]]
                rec = race.records
                infos[a] = {"success": bool(rec.finished[i]), "crashed": bool(rec.crashed[i]),
                            "lap_time": float(rec.lap_time[i]) if bool(rec.finished[i]) else float("nan")}
        self.agents = [a for a in live if not (terminated[a] or truncated[a])]
        return (self._obs(obs["policy"], live), {a: float(reward[self._index[a]]) for a in live}, terminated,
                truncated, infos)

    def close(self) -> None:
        """Nothing to release beyond the simulation's memory."""
