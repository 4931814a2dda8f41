"""Inputs a stored policy never saw vary, and silencing them so that it acts as it did in its own stage.

The observation layout is the same in every stage, so a solo policy has opponent slots too, filled with a
constant placeholder. Its observation normaliser therefore holds a standard deviation of 0 for them, and their
first-layer weights never received a gradient: they are still the random initial values. Fed a stage's varying
opponent features, ``(x − mean) / (std + eps)`` multiplies them by ``1 / eps`` (100) on the way into those
random weights, and the policy would react wildly to every opponent. :func:`silence_inputs` zeroes the weights of
such inputs: the policy then computes exactly what it did in its own stage and ignores inputs it never learned
about. Frozen policies (pool opponents, evaluation) load that way; a training stage also calibrates them
(:func:`spiral.train.inputs.calibrate_inputs`).
"""

from __future__ import annotations

import torch
from rsl_rl.models import MLPModel
from rsl_rl.modules.normalization import EmpiricalNormalization

__all__ = ["UNUSED_STD", "first_linear", "first_linear_name", "input_normalizer", "silence_inputs", "unused_inputs"]

UNUSED_STD = 1e-4
"""A normalised input whose standard deviation is below this never varied in training."""


def input_normalizer(model: MLPModel) -> EmpiricalNormalization | None:
    """The model's observation normaliser, if it has one."""
    norm = getattr(model, "obs_normalizer", None)
    return norm if isinstance(norm, EmpiricalNormalization) else None


def first_linear_name(model: MLPModel) -> str:
    """State-dict prefix of the model's first linear layer (the one its inputs enter)."""
    return "mlp." + next(n for n, m in model.mlp.named_modules() if isinstance(m, torch.nn.Linear))


def first_linear(model: MLPModel) -> torch.nn.Linear:
    """The model's first linear layer."""
    return model.get_submodule(first_linear_name(model))


def unused_inputs(model: MLPModel) -> torch.Tensor:
    """Boolean mask over the model's inputs that never varied while it trained (none without a normaliser)."""
    norm = input_normalizer(model)
    if norm is None:
        return torch.zeros(first_linear(model).in_features, dtype=torch.bool)
    return norm.std.cpu() < UNUSED_STD


@torch.no_grad()
def silence_inputs(model: MLPModel, mask: torch.Tensor) -> None:
    """Zero the first-layer weights of the inputs in ``mask``: the model's output no longer depends on them."""
    first_linear(model).weight[:, mask.to(first_linear(model).weight.device)] = 0.0
