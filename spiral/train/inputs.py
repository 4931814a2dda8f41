"""How a training stage takes up inputs its init policy never saw vary (see :mod:`spiral.core.inputs` for why
such inputs exist and how a frozen policy silences them).

:func:`calibrate_inputs` gives unused inputs statistics measured in the new stage, so that a stage trains their
(zeroed) weights on unit-scale inputs from its first iteration; :func:`take_up_new_inputs` does it for a stage that
starts from an earlier stage's policy.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from rsl_rl.models import MLPModel
from rsl_rl.runners import OnPolicyRunner
from tensordict import TensorDict

from spiral.core.inputs import (
    UNUSED_STD,
    input_normalizer,
    silence_inputs,
    unused_inputs,
)
from spiral.env.vec_env import RaceVecEnv

__all__ = ["WARMUP_S", "calibrate_inputs", "model_inputs", "take_up_new_inputs"]

WARMUP_S = 2.0
"""Flight time of the rollout that measures the statistics of inputs new to a stage [s]."""


def model_inputs(model: MLPModel, obs: TensorDict) -> torch.Tensor:
    """The un-normalised input rows the model builds from ``obs`` (its observation groups, concatenated)."""
    return torch.cat([obs[group] for group in model.obs_groups], dim=-1)


@torch.no_grad()
def calibrate_inputs(model: MLPModel, inputs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Set the normaliser's mean and standard deviation of the ``mask`` inputs from ``inputs`` (N, obs_dim).

    Inputs that are constant in ``inputs`` too are left alone. Returns the mask of inputs that were calibrated.
    """
    norm = input_normalizer(model)
    if norm is None:
        return torch.zeros_like(mask)
    inputs = inputs.to(norm._mean.device).float()
    var, mean = torch.var_mean(inputs, dim=0, unbiased=False)
    varied = mask.to(var.device) & (var.sqrt() >= UNUSED_STD)
    norm._mean[0, varied] = mean[varied]
    norm._var[0, varied] = var[varied]
    norm._std[0, varied] = var[varied].sqrt()
    return varied.cpu()


def take_up_new_inputs(runner: OnPolicyRunner, vec_env: RaceVecEnv, *, device: str, name: str,
                       log: Callable[[str], None]) -> None:
    """Inputs the init policy never saw vary (e.g. the opponents of a solo policy) start with zero weights, so the
    stage starts from exactly that policy, and with statistics from a short warm-up rollout in this stage's worlds,
    so they train at unit scale from the first iteration. The env starts fresh races afterwards."""
    models = {"actor": runner.alg.actor, "critic": runner.alg.critic}
    unused = {key: unused_inputs(model) for key, model in models.items()}
    if not any(mask.any() for mask in unused.values()):
        return
    for key, model in models.items():
        silence_inputs(model, unused[key])
    policy = runner.get_inference_policy(device=device)
    obs = vec_env.get_observations().to(device)
    batches = []
    with torch.inference_mode():
        for _ in range(math.ceil(WARMUP_S / vec_env.env.dt)):
            obs = vec_env.step(policy(obs))[0].to(device)
            batches.append(obs)
        vec_env.env.reset()  # training starts from fresh races (env buffers are inference tensors by now)
    inputs = {key: torch.cat([model_inputs(model, b) for b in batches]).clone() for key, model in models.items()}
    calibrated = {key: calibrate_inputs(model, inputs[key], unused[key]) for key, model in models.items()}
    runner.alg.train_mode()
    vec_env.env.pop_stats()
    log(f"stage '{name}': {int(unused['actor'].sum())} policy inputs were constant in the init policy's stage; "
        f"{int(calibrated['actor'].sum())} vary here and start with zero weights and statistics from a "
        f"{WARMUP_S:.0f} s warm-up (critic: {int(calibrated['critic'].sum())} of {int(unused['critic'].sum())})")
