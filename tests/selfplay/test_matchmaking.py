"""Matchmaking on scripted numbers: the latest best's and the first member's shares, prioritised draws."""

from __future__ import annotations

import pytest
import torch

from spiral.selfplay import Matchmaker


def test_matchmaking_draws_the_latest_best_with_probability_p():
    """Draw the latest member about p of the time and the others uniformly otherwise."""
    mm = Matchmaker(4, latest=3, p_latest=0.5, mode="uniform")
    draws = mm.draw(40_000, torch.Generator().manual_seed(0))
    freq = torch.bincount(draws, minlength=4).float() / draws.numel()
    assert freq[3].item() == pytest.approx(0.5 + 0.5 / 4, abs=0.01)
    assert freq[:3].tolist() == pytest.approx([0.125] * 3, abs=0.01)


def test_matchmaking_draws_a_uniform_number_for_the_latest_best_then_a_pool_sample():
    """A seed gives its draws in this order (a uniform number for the latest best, then a pool sample, per world),
    so earlier runs reproduce."""
    g = torch.Generator().manual_seed(3)
    u = torch.rand(1000, generator=g)
    sampled = torch.multinomial(torch.full((5,), 0.2), 1000, replacement=True, generator=g)
    before = torch.where(u < 0.5, torch.full_like(sampled, 4), sampled)
    now = Matchmaker(5, latest=4, p_latest=0.5, mode="uniform").draw(1000, torch.Generator().manual_seed(3))
    assert torch.equal(now, before)  # exact: integer draws


def test_prioritized_matchmaking_favours_members_the_learner_loses_to():
    """Weight members by the learner's smoothed loss rate against them."""
    mm = Matchmaker(2, latest=0, p_latest=0.0, mode="prioritized")
    mm.record(torch.tensor([0] * 8 + [1] * 8), torch.tensor([True] * 8 + [False] * 8))
    assert mm.weights().tolist() == pytest.approx([0.1, 0.9])
    draws = mm.draw(20_000, torch.Generator().manual_seed(1))
    assert (draws == 1).float().mean().item() == pytest.approx(0.9, abs=0.01)
