"""Inputs a policy never saw vary: frozen policies ignore them, a new stage takes them up at unit scale."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from spiral.config import AIRFRAMES, SimCfg, StageSpec
from spiral.core.inputs import UNUSED_STD, silence_inputs, unused_inputs
from spiral.env import RaceSetting
from spiral.selfplay import StageSources, run_stage
from spiral.train import StageStart, StageTrainer, load_policy
from spiral.train.inputs import calibrate_inputs

CF2X = AIRFRAMES["cf2x"]
COMMON = {"worlds": 8, "env": {"obs": {"history_len": 1, "gate_normals": True, "pid_integral": True}},
          "ppo": {"num_steps_per_env": 8, "actor_hidden_dims": [16, 16], "critic_hidden_dims": [16, 16]}}


@pytest.fixture(scope="module")
def solo_best(line2, tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("solo")
    solo = StageSpec.model_validate({"name": "solo", "iterations": 2, "selection": {"interval": 1, "races": 2},
                                     **COMMON})
    run_stage(RaceSetting(line2, CF2X, SimCfg()), solo, run_dir, sources=StageSources(pool_dir=run_dir / "pool"),
              progress=False)
    return run_dir / "best.pt"


def as_obs(rows: torch.Tensor) -> TensorDict:
    return TensorDict({"policy": rows, "critic": rows}, batch_size=[rows.shape[0]])


def test_frozen_solo_policy_ignores_the_opponent_inputs_it_never_saw_vary(solo_best):
    """Random values in the inputs constant during solo training leave the actions unchanged; others do not."""
    policy = load_policy(solo_best)
    unused = unused_inputs(policy.actor)
    assert unused.any() and not unused.all()
    base = torch.randn(16, unused.numel())
    noisy = base.clone()
    noisy[:, unused] = 50.0 * torch.randn(16, int(unused.sum()))
    torch.testing.assert_close(policy(as_obs(base)), policy(as_obs(noisy)))  # zero weights on the unused inputs
    used = base.clone()
    used[:, ~unused] += torch.randn(16, int((~unused).sum()))
    assert not torch.allclose(policy(as_obs(base)), policy(as_obs(used)))


def test_calibrate_sets_statistics_of_unused_inputs_only(solo_best):
    """Unused inputs that vary get the batch's mean and std; used and still-constant inputs keep theirs."""
    actor = load_policy(solo_best).actor
    unused = unused_inputs(actor)
    first, second = torch.nonzero(unused).flatten()[:2].tolist()
    before = actor.obs_normalizer.std.clone()
    inputs = torch.zeros(4000, unused.numel())
    inputs[:, first] = 3.0 + 2.0 * torch.randn(4000)
    inputs[:, second] = 7.0  # still constant in this batch
    calibrated = calibrate_inputs(actor, inputs, unused)
    assert calibrated.tolist() == [i == first for i in range(unused.numel())]
    assert actor.obs_normalizer.mean[first].item() == pytest.approx(3.0, abs=0.15)
    assert actor.obs_normalizer.std[first].item() == pytest.approx(2.0, abs=0.15)
    keep = torch.ones_like(unused)
    keep[first] = False
    torch.testing.assert_close(actor.obs_normalizer.std[keep], before[keep])  # kept, not recomputed


def test_silenced_inputs_have_zero_first_layer_weights(solo_best):
    actor = load_policy(solo_best).actor
    mask = torch.zeros(actor.obs_normalizer.std.numel(), dtype=torch.bool)
    mask[[0, 3]] = True
    silence_inputs(actor, mask)
    weight = actor.mlp[0].weight
    assert (weight[:, mask] == 0).all() and (weight[:, ~mask] != 0).any()


def test_1v1_stage_starts_as_the_solo_policy_with_calibrated_opponent_inputs(line2, solo_best, tmp_path):
    """A stage from a solo checkpoint acts exactly like the solo policy at first, and the opponent inputs it
    will learn from are normalised with statistics measured in 1v1 worlds (not the solo's std of 0)."""
    solo = load_policy(solo_best)
    unused = unused_inputs(solo.actor)
    stage = StageSpec.model_validate({"name": "1v1", "scenario": "1v1", "iterations": 1, **COMMON})
    trainer = StageTrainer(RaceSetting(line2, CF2X, SimCfg()), stage, tmp_path,
                           start=StageStart(solo_best, {stage.scenario: solo}), progress=False)
    actor = trainer.runner.alg.actor
    std = actor.obs_normalizer.std
    assert (std[unused] >= UNUSED_STD).any()  # the opponent's relative position now varies
    obs = trainer.vec_env.get_observations()
    with torch.no_grad():
        assert torch.allclose(actor(obs), solo(obs), atol=1e-6)
    for model in (actor, trainer.runner.alg.critic):  # both saw the same observations in solo
        assert (model.mlp[0].weight[:, unused] == 0).all()
