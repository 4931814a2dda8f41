"""Eval fixtures: a short 2-gate sprint track and a tiny checkpoint trained for one iteration on it."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from spiral.config import AIRFRAMES, SimCfg, StageSpec, TrackSpec
from spiral.env import RaceSetting
from spiral.train import StageTrainer
from tests.env.helpers import obs_with

SPRINT = {
    "kind": "track",
    "name": "sprint2",
    "gates": [
        {"position": [0.0, 0.0, 1.0], "rpy_deg": [0, 0, 0], "direction": 1},
        {"position": [2.5, 0.0, 1.0], "rpy_deg": [0, 0, 0], "direction": 1},
    ],
    "start": {"center": [-1.2, 0.0, 1.0], "size": [0.8, 0.8, 0.3], "min_separation": 0.25},
    "bounds": {"min": [-3.0, -3.0, 0.0], "max": [5.0, 3.0, 2.5]},
    "time_limit_s": 2.0,
}
"""Two gates ahead of a start box roomy enough for four drones; races last at most 2 s."""


def tiny_stage(scenario: str = "solo", *, name: str = "tiny", mode: str = "pool", obs: dict | None = None) -> StageSpec:
    """A one-iteration stage with a compact observation, gate normals and the PID integral its only extras (or
    ``obs``, extras off unless named), and a small network."""
    obs_cfg = obs_with(**(obs or {"history_len": 1, "gate_normals": True, "pid_integral": True}))
    return StageSpec.model_validate({
        "name": name, "scenario": scenario, "worlds": 4, "iterations": 1,
        "env": {"obs": obs_cfg.model_dump()},
        "ppo": {"num_steps_per_env": 8, "actor_hidden_dims": [16, 16], "critic_hidden_dims": [16, 16]},
        **({"selfplay": {"mode": mode, "promotion": {"interval": 1, "races": 2}}} if scenario != "solo" else
           {"selection": {"interval": 1, "races": 2}})})


@pytest.fixture(scope="session")
def sprint() -> TrackSpec:
    """The 2-second sprint track."""
    return TrackSpec.model_validate(SPRINT)


@pytest.fixture(scope="session")
def sprint_yaml(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The sprint track as a YAML file."""
    path = tmp_path_factory.mktemp("tracks") / "sprint2.yaml"
    path.write_text(yaml.safe_dump(SPRINT))
    return path


@pytest.fixture(scope="session")
def tiny_checkpoint(sprint: TrackSpec, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """best.pt of one PPO iteration on the sprint track (an almost untrained policy that hovers)."""
    run_dir = tmp_path_factory.mktemp("tiny")
    result = StageTrainer(RaceSetting(sprint, AIRFRAMES["cf2x"], SimCfg()), tiny_stage(), run_dir, seed=0,
                          progress=False, log=lambda _: None).train()
    return result.best_path


@pytest.fixture(scope="session")
def tiny_checkpoint_other_inputs(sprint: TrackSpec, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Like ``tiny_checkpoint``, but trained with another observation layout (two history entries, other terms)."""
    run_dir = tmp_path_factory.mktemp("tiny-other")
    stage = tiny_stage(obs={"history_len": 2, "opponent_velocity": True})
    return StageTrainer(RaceSetting(sprint, AIRFRAMES["cf2x"], SimCfg()), stage, run_dir, seed=0, progress=False,
                        log=lambda _: None).train().best_path
