"""Shared helpers: a small random policy saved as a spiral checkpoint (no training needed)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from rsl_rl.models import MLPModel
from tensordict import TensorDict

from spiral.config import AIRFRAMES, EnvCfg, PPOCfg, SimCfg
from spiral.core.checkpoint import save_checkpoint
from spiral.env import ObservationBuilder

SMALL_ENV = EnvCfg.model_validate({"obs": {"history_len": 2, "gate_normals": True, "pid_integral": False,
                                           "opponent_velocity": False, "teammates": False, "closest_approach": False}})
"""Observation layout of the ecosystem tests (short history, gate normals the only extra: small inputs, fast
steps)."""


def write_policy_checkpoint(path: Path, env_cfg: EnvCfg = SMALL_ENV, *, seed: int = 0) -> Path:
    """Save a random actor with a non-trivial observation normaliser as a spiral checkpoint."""
    torch.manual_seed(seed)
    ppo = PPOCfg(actor_hidden_dims=[16, 16], critic_hidden_dims=[16, 16])
    layout = ObservationBuilder(env_cfg.obs, 1, device=torch.device("cpu")).layout()
    dim = layout["obs_dim"]
    dummy = TensorDict({"policy": torch.zeros(1, dim)}, batch_size=[1])
    actor = MLPModel(dummy, {"actor": ["policy"]}, "actor", 4, hidden_dims=ppo.actor_hidden_dims,
                     activation=ppo.activation, obs_normalization=True,
                     distribution_cfg={"class_name": "rsl_rl.modules.distribution.GaussianDistribution"})
    actor.train()
    actor.obs_normalizer.update(3.0 * torch.randn(256, dim) + 1.0)
    meta = {"stage": "test", "iteration": 0, "track": "oval4", "obs_layout": layout, "ppo": ppo.model_dump(),
            "env": env_cfg.model_dump(), "airframe": AIRFRAMES["cf2x"].model_dump(), "sim": SimCfg().model_dump()}
    save_checkpoint(path, {"actor_state_dict": actor.state_dict()}, meta)
    return path


@pytest.fixture(scope="session")
def policy_checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A random policy checkpoint with the :data:`SMALL_ENV` layout."""
    return write_policy_checkpoint(tmp_path_factory.mktemp("ckpt") / "policy.pt")


@pytest.fixture(scope="session")
def small_env() -> EnvCfg:
    """The env settings of :func:`policy_checkpoint`, with start-box starts only (repeatable resets)."""
    box = {"track_start_prob": 0.0, "passage_starts": None}
    return SMALL_ENV.model_copy(update={"episode": SMALL_ENV.episode.model_copy(update=box)})
