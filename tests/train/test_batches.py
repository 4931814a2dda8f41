"""PPO's mini-batches from one gather per update: the batches and the update of rsl-rl's own generator."""

from __future__ import annotations

import pytest
import torch
from rsl_rl.storage import RolloutStorage
from tensordict import TensorDict

from spiral.train.batches import gather_once


def filled_storage(envs: int = 6, steps: int = 4) -> RolloutStorage:
    obs = TensorDict({"policy": torch.zeros(envs, 5), "critic": torch.zeros(envs, 7)}, batch_size=[envs])
    storage = RolloutStorage("rl", envs, steps, obs, [3], "cpu")
    gen = torch.Generator().manual_seed(3)
    for name in ("actions", "values", "returns", "actions_log_prob", "advantages"):
        t = getattr(storage, name)
        t.copy_(torch.randn(t.shape, generator=gen))
    for key in ("policy", "critic"):
        storage.observations[key].copy_(torch.randn(storage.observations[key].shape, generator=gen))
    storage.distribution_params = tuple(torch.randn(steps, envs, 3, generator=gen) for _ in range(2))
    return storage


@pytest.mark.bitwise
def test_gather_once_yields_rsl_rls_mini_batches_row_for_row():
    """Same permutation (same RNG draw), same rows in the same order in every epoch; batches are slices."""
    storage = filled_storage()
    torch.manual_seed(7)
    ours = list(gather_once(storage, num_mini_batches=3, num_epochs=2))
    torch.manual_seed(7)
    theirs = list(storage.mini_batch_generator(num_mini_batches=3, num_epochs=2))
    assert len(ours) == len(theirs) == 6
    for a, b in zip(ours, theirs, strict=True):
        for name in ("actions", "values", "advantages", "returns", "old_actions_log_prob"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name
        for key in ("policy", "critic"):
            assert torch.equal(a.observations[key], b.observations[key])
        assert all(torch.equal(p, q) for p, q in zip(a.old_distribution_params, b.old_distribution_params, strict=True))
    assert ours[0].actions.data_ptr() == ours[3].actions.data_ptr()  # epoch 2 reuses epoch 1's gathered rows
    assert ours[0].actions.shape == (8, 3)

