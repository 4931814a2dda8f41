"""Helpers of the env tests: a small RaceEnv, drones placed by hand, observation terms by name, a scripted lap."""

from __future__ import annotations

import torch

from spiral.config import AIRFRAMES, EnvCfg, ObsCfg, SimCfg, TrackSpec
from spiral.env import RaceEnv, RaceSetting

CF2X = AIRFRAMES["cf2x"]


def obs_with(history_len: int, **extras: bool | float) -> ObsCfg:
    """An observation layout of ``history_len`` history entries with only the ``extras`` given on (the schema's
    defaults turn every extra on)."""
    off = {"gate_normals": False, "pid_integral": False, "opponent_velocity": False, "teammates": False,
           "closest_approach": False}
    return ObsCfg(**{**off, "history_len": history_len, **extras})


def paper_obs() -> ObsCfg:
    """The paper's observation layout: K = 50 history entries and no extra (814 inputs)."""
    return obs_with(50)


def make_env(track: TrackSpec, *, worlds: int = 2, drones: int = 1, learners=(0,), training: bool = True,
             obs: ObsCfg | None = None, **env_kw) -> RaceEnv:
    """A RaceEnv of ``worlds`` worlds whose training episodes start in the start box (no track or passage starts),
    observing a 3-step history without extras unless ``obs`` says."""
    env_kw.setdefault("episode", {"track_start_prob": 0.0, "passage_starts": None})
    cfg = EnvCfg(obs=obs or obs_with(3), **env_kw)
    return RaceEnv(RaceSetting(track, CF2X, SimCfg()), cfg, world_count=worlds, drones_per_world=drones,
                   learner_slots=learners, seed=3, training=training)


def place(env: RaceEnv, positions: list[list[float]]) -> None:
    """Put the drones of world 0 at ``positions``, at rest, and rebuild the observations."""
    env.pos[: len(positions)] = torch.tensor(positions)
    env.vel.zero_()
    env.get_observations()


def term(env: RaceEnv, name: str) -> torch.Tensor:
    """Observe now and return observation term ``name`` of every learner drone."""
    return env.obs_builder.select(env.get_observations()["policy"], name)


def newest(env: RaceEnv, obs: torch.Tensor, field: str) -> torch.Tensor:
    """History field ``field`` of the newest history entry in observation rows ``obs``."""
    return env.obs_builder.select_history(obs, field)[:, -1]


def waypoint_policy(env: RaceEnv, drones: torch.Tensor | None = None):
    """Line up 0.5 m in front of the next gate, then fly 0.6 m past its centre (the learner drones by default)."""
    def act(obs):
        idx = env.learner_idx if drones is None else drones
        gate = env.next_gate.long()[idx]
        center, forward = env.world_tracks.gate_center[gate], env.world_tracks.gate_forward[gate]
        rel_gate = env.pos[idx] - center
        along = (rel_gate * forward).sum(-1, keepdim=True)
        lateral = (rel_gate - along * forward).norm(dim=-1, keepdim=True)
        lined_up = (along > -0.2) | (lateral < 0.1)
        target = torch.where(lined_up, center + 0.6 * forward, center - 0.5 * forward)
        rel = (target - env.pos[idx]) / env.cfg.action.pos_scale
        return torch.cat([rel.clamp(-1, 1), torch.zeros(len(idx), 1)], dim=-1)
    return act
