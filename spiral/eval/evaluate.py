"""Seeded evaluation races of learned policies: identical start placements for every method."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from spiral.config.airframe import AirframeCfg
from spiral.config.env import ActionCfg, EnvCfg, ObsCfg
from spiral.config.sim import SimCfg
from spiral.config.stage import SCENARIO_DRONES
from spiral.config.track import TrackSpec
from spiral.env.race_env import RaceEnv
from spiral.env.racing import RaceResults, run_races
from spiral.eval.metrics import summarize_races
from spiral.train.checkpoint import FrozenPolicy, load_policy

__all__ = ["eval_env_for", "evaluate_policy", "evaluate_methods"]


def eval_env_for(policy: FrozenPolicy, track: TrackSpec, scenario: str, runs: int, seed: int, *,
                 device: str = "cpu") -> RaceEnv:
    """A non-resetting env with the policy's observation/action layout, airframe and simulator settings.

    Start placements depend on ``seed`` and ``scenario`` only, so every method races from the same ones.
    """
    meta = policy.meta
    obs = {k: v for k, v in meta["obs_layout"].items() if k != "obs_dim"}
    cfg = EnvCfg(obs=ObsCfg(**obs), action=ActionCfg(**meta["env"]["action"]))
    drones = SCENARIO_DRONES[scenario]
    return RaceEnv(track, AirframeCfg(**meta["airframe"]), SimCfg(**meta["sim"]), cfg, world_count=runs,
                   drones_per_world=drones, learner_slots=list(range(drones)), device=device, seed=seed,
                   auto_reset=False)


def evaluate_policy(policy: FrozenPolicy, track: TrackSpec, scenario: str, runs: int, seed: int, *,
                    device: str = "cpu", record: bool = False) -> RaceResults:
    """Self-match races: every drone of every race runs ``policy``."""
    env = eval_env_for(policy, track, scenario, runs, seed, device=device)
    return run_races(env, policy, record=record)


def evaluate_methods(track: TrackSpec, methods: dict[str, Path], *, scenario: str, runs: int, seed: int,
                     device: str = "cpu") -> dict[str, Any]:
    """The evaluation JSON of ``spiral eval``: metrics of each named checkpoint in ``scenario``."""
    out: dict[str, Any] = {"track": track.name, "scenario": scenario, "runs": runs, "seed": seed, "methods": {}}
    for name, path in methods.items():
        policy = load_policy(path, device=device)
        res = evaluate_policy(policy, track, scenario, runs, seed, device=device)
        out["methods"][name] = {"checkpoint": str(path), **summarize_races(res)}
    return out
