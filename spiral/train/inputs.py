"""Inputs a policy never saw vary, and how a policy takes them up in a stage where they do.

The observation layout is the same in every stage, so a solo policy has opponent slots too, filled with a
constant placeholder. Its observation normaliser therefore holds a standard deviation of 0 for them, and their
first-layer weights never received a gradient: they are still the random initial values. Fed a stage's varying
opponent features, ``(x − mean) / (std + eps)`` multiplies them by ``1 / eps`` (100) on the way into those
random weights: the next stage would start from a policy that reacts wildly to every opponent, and its
normaliser would take the whole stage to catch up with the new inputs' spread (it averages over every sample
the policy has seen). Two remedies:

* :func:`silence_inputs` zeroes the weights of unused inputs. The policy then computes exactly what it did in
  its own stage, and ignores inputs it never learned about. Frozen policies (pool opponents, evaluation) load
  that way.
* :func:`calibrate_inputs` gives unused inputs statistics measured in the new stage, so that a stage trains
  their (zeroed) weights on unit-scale inputs from its first iteration.
"""

from __future__ import annotations

import torch
from rsl_rl.models import MLPModel
from rsl_rl.modules.normalization import EmpiricalNormalization
from tensordict import TensorDict

__all__ = ["UNUSED_STD", "calibrate_inputs", "model_inputs", "silence_inputs", "unused_inputs", "widen_inputs"]

UNUSED_STD = 1e-4
"""A normalised input whose standard deviation is below this never varied in training."""


def _normalizer(model: MLPModel) -> EmpiricalNormalization | None:
    norm = getattr(model, "obs_normalizer", None)
    return norm if isinstance(norm, EmpiricalNormalization) else None


def _first_linear_name(model: MLPModel) -> str:
    return "mlp." + next(n for n, m in model.mlp.named_modules() if isinstance(m, torch.nn.Linear))


def _first_linear(model: MLPModel) -> torch.nn.Linear:
    return model.get_submodule(_first_linear_name(model))


def widen_inputs(state: dict[str, torch.Tensor], model: MLPModel) -> dict[str, torch.Tensor]:
    """``state`` (a state dict of a model like ``model`` with fewer inputs) with inputs appended up to ``model``'s.

    The new inputs get zero first-layer weights and zero statistics: the model computes what it computed before,
    and :func:`unused_inputs` reports them, so a stage calibrates them like any input its init policy never saw
    vary (e.g. a centralised critic's inputs about the other drones, from a stage without them).
    """
    name = _first_linear_name(model)
    had, width = state[f"{name}.weight"].shape[1], _first_linear(model).in_features
    if had > width:
        raise ValueError(f"the stored model has {had} inputs, this one {width}: inputs can be added, not removed")
    out = dict(state)
    for key in (f"{name}.weight", "obs_normalizer._mean", "obs_normalizer._var", "obs_normalizer._std"):
        if key in state:
            out[key] = torch.nn.functional.pad(state[key], (0, width - had))
    return out


def unused_inputs(model: MLPModel) -> torch.Tensor:
    """Boolean mask over the model's inputs that never varied while it trained (none without a normaliser)."""
    norm = _normalizer(model)
    if norm is None:
        return torch.zeros(_first_linear(model).in_features, dtype=torch.bool)
    return norm.std.cpu() < UNUSED_STD


@torch.no_grad()
def silence_inputs(model: MLPModel, mask: torch.Tensor) -> None:
    """Zero the first-layer weights of the inputs in ``mask``: the model's output no longer depends on them."""
    _first_linear(model).weight[:, mask.to(_first_linear(model).weight.device)] = 0.0


def model_inputs(model: MLPModel, obs: TensorDict) -> torch.Tensor:
    """The un-normalised input rows the model builds from ``obs`` (its observation groups, concatenated)."""
    return torch.cat([obs[group] for group in model.obs_groups], dim=-1)


@torch.no_grad()
def calibrate_inputs(model: MLPModel, inputs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Set the normaliser's mean and standard deviation of the ``mask`` inputs from ``inputs`` (N, obs_dim).

    Inputs that are constant in ``inputs`` too are left alone. Returns the mask of inputs that were calibrated.
    """
    norm = _normalizer(model)
    if norm is None:
        return torch.zeros_like(mask)
    inputs = inputs.to(norm._mean.device).float()
    var, mean = torch.var_mean(inputs, dim=0, unbiased=False)
    varied = mask.to(var.device) & (var.sqrt() >= UNUSED_STD)
    norm._mean[0, varied] = mean[varied]
    norm._var[0, varied] = var[varied]
    norm._std[0, varied] = var[varied].sqrt()
    return varied.cpu()
