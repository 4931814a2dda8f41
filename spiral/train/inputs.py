"""How a training stage takes up inputs its init policy never saw vary (see :mod:`spiral.core.inputs` for why
such inputs exist and how a frozen policy silences them).

* :func:`calibrate_inputs` gives unused inputs statistics measured in the new stage, so that a stage trains
  their (zeroed) weights on unit-scale inputs from its first iteration.
* :func:`widen_inputs` appends inputs a stored model did not have (a centralised critic's), as unused ones.
"""

from __future__ import annotations

import torch
from rsl_rl.models import MLPModel
from tensordict import TensorDict

from spiral.core.inputs import UNUSED_STD, first_linear, first_linear_name, input_normalizer

__all__ = ["calibrate_inputs", "model_inputs", "widen_inputs"]


def widen_inputs(state: dict[str, torch.Tensor], model: MLPModel) -> dict[str, torch.Tensor]:
    """``state`` (a state dict of a model like ``model`` with fewer inputs) with inputs appended up to ``model``'s.

    The new inputs get zero first-layer weights and zero statistics: the model computes what it computed before,
    and :func:`~spiral.core.inputs.unused_inputs` reports them, so a stage calibrates them like any input its init
    policy never saw vary (e.g. a centralised critic's inputs about the other drones, from a stage without them).
    """
    name = first_linear_name(model)
    had, width = state[f"{name}.weight"].shape[1], first_linear(model).in_features
    if had > width:
        raise ValueError(f"the stored model has {had} inputs, this one {width}: inputs can be added, not removed")
    out = dict(state)
    for key in (f"{name}.weight", "obs_normalizer._mean", "obs_normalizer._var", "obs_normalizer._std"):
        if key in state:
            out[key] = torch.nn.functional.pad(state[key], (0, width - had))
    return out


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
