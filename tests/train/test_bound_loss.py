"""The bound loss on the actor's mean actions (``ppo.bound_loss_coef``): a gradient hook equal to a loss term."""

from __future__ import annotations

import pytest
import torch
from rsl_rl.modules.distribution import GaussianDistribution
from torch import nn

from spiral.config import AIRFRAMES, PPOCfg, SimCfg, StageSpec
from spiral.env import RaceSetting
from spiral.train import StageTrainer
from spiral.train.distribution import BoundedGaussianDistribution, bound_loss


def test_bound_loss_on_hand_made_means_counts_only_the_excess_beyond_one():
    """Row 1: (2 − 1)² + (1.5 − 1)², row 2: (3 − 1)²; entries within ±1 cost nothing; the mean over rows."""
    mean = torch.tensor([[2.0, -1.5, 0.5, 1.0], [0.0, 0.0, -3.0, 0.9]])
    assert float(bound_loss(mean)) == pytest.approx(((1.0 + 0.25) + 4.0) / 2)


def test_the_bound_hook_adds_exactly_the_gradient_of_the_weighted_loss_term():
    """Same samples, log-probabilities and parameters as rsl-rl's Gaussian; the weights' gradient through the
    bounded mean equals that of the plain Gaussian's loss plus coef times the bound loss."""
    gen = torch.Generator().manual_seed(0)
    x, actions = 2 * torch.randn(64, 4, generator=gen), torch.randn(64, 4, generator=gen)
    w = torch.randn(4, 4, generator=gen, requires_grad=True)

    def gradient(dist: GaussianDistribution, coef: float = 0.0) -> torch.Tensor:
        w.grad = None
        mean = x @ w
        dist.update(mean)
        loss = -dist.log_prob(actions).mean() + coef * bound_loss(mean)
        loss.backward()
        return w.grad.clone()

    bounded, plain = BoundedGaussianDistribution(4, bound_coef=0.5, init_std=0.5), GaussianDistribution(4, init_std=0.5)
    assert bounded.state_dict().keys() == plain.state_dict().keys()
    with_hook, as_term, without = gradient(bounded), gradient(plain, coef=0.5), gradient(plain)
    assert torch.allclose(with_hook, as_term, atol=1e-5) and not torch.allclose(with_hook, without, atol=1e-2)
    with torch.no_grad():  # a rollout's forward pass: nothing to hook
        bounded.update(x @ w)
    torch.testing.assert_close(bounded.log_prob(actions), plain.log_prob(actions))  # the same computation, no hook


def stage(coef: float) -> StageSpec:
    return StageSpec.model_validate({
        "name": "tiny", "worlds": 16, "iterations": 1, "env": {"obs": {"history_len": 1}},
        "ppo": {"num_steps_per_env": 8, "actor_hidden_dims": [16], "critic_hidden_dims": [16],
                "bound_loss_coef": coef, "learning_rate": 0.02, "schedule": "fixed"},
        "selection": {"interval": 4, "races": 2}})


def saturated_means_after_updates(trainer: StageTrainer, updates: int) -> float:
    """Mean |mean action| over the env's current observations after setting the actor's output bias to 3 (its
    weights near 0) and running ``updates`` PPO updates."""
    alg = trainer.runner.alg
    last = [m for m in alg.actor.modules() if isinstance(m, nn.Linear)][-1]
    with torch.no_grad():
        last.weight.mul_(0.01)
        last.bias.fill_(3.0)
    alg.train_mode()
    for _ in range(updates):
        trainer.collect(trainer.vec_env.get_observations())
        alg.update()
    with torch.no_grad():
        return float(alg.get_policy()(trainer.vec_env.get_observations()).abs().mean())


def test_a_stage_with_a_bound_loss_pulls_saturated_mean_actions_back_into_range(oval2, tmp_path):
    off = PPOCfg(bound_loss_coef=0).to_rsl_rl()["actor"]["distribution_cfg"]
    assert off["class_name"].endswith(".GaussianDistribution")
    bounded = StageTrainer(RaceSetting(oval2, AIRFRAMES["cf2x"], SimCfg()), stage(5.0), tmp_path / "on", progress=False)
    plain = StageTrainer(RaceSetting(oval2, AIRFRAMES["cf2x"], SimCfg()), stage(0.0), tmp_path / "off", progress=False)
    assert isinstance(bounded.runner.alg.actor.distribution, BoundedGaussianDistribution)
    assert type(plain.runner.alg.actor.distribution) is GaussianDistribution
    pulled, kept = saturated_means_after_updates(bounded, 3), saturated_means_after_updates(plain, 3)
    assert pulled < 2.0 and kept > 2.7, (pulled, kept)
