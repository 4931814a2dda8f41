"""The actor's action distribution with a bound loss: rsl-rl's Gaussian whose mean is pulled back into the action
range, so that exploration noise falls on both sides of it.

The env clamps every action to [-1, 1]. A mean beyond that bound (a policy that always flies at full tilt on one
axis) makes nearly every sampled action the same clamped value, and PPO gets no signal for acting less on that axis
(braking behind a slower drone, for one). ``BoundedGaussianDistribution`` adds the gradient of
``coef · mean over samples of Σ_axes relu(|μ| − 1)²`` to the mean's gradient in PPO's update, as a loss term would,
without changing rsl-rl's update: a tensor hook on the mean, registered only when a gradient flows through it.
"""

from __future__ import annotations

import torch
from rsl_rl.modules.distribution import GaussianDistribution

__all__ = ["ACTION_BOUND", "BoundedGaussianDistribution", "bound_loss"]

ACTION_BOUND = 1.0
"""Largest action magnitude the env applies (it clamps beyond)."""


def bound_loss(mean: torch.Tensor) -> torch.Tensor:
    """Mean over rows of the summed squared excess of the mean actions (rows, axes) beyond :data:`ACTION_BOUND`."""
    return (mean.abs() - ACTION_BOUND).clamp_min(0.0).square().sum(-1).mean()


class BoundedGaussianDistribution(GaussianDistribution):
    """rsl-rl's ``GaussianDistribution`` (same parameters, state dict and samples) with the bound loss's gradient,
    weighted ``bound_coef``, added to the mean's in every backward pass through it."""

    def __init__(self, output_dim: int, *, bound_coef: float, **kwargs) -> None:
        super().__init__(output_dim, **kwargs)
        self.bound_coef = bound_coef

    def update(self, mlp_output: torch.Tensor) -> None:
        super().update(mlp_output)
        if self.bound_coef > 0 and mlp_output.requires_grad:
            excess = (mlp_output.detach().abs() - ACTION_BOUND).clamp_min(0.0) * mlp_output.detach().sign()
            extra = (2.0 * self.bound_coef / mlp_output.shape[0]) * excess
            mlp_output.register_hook(lambda grad: grad + extra.to(grad.dtype))
