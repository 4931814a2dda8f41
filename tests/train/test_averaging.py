"""Moving average of the policy's weights: the update rule, what best.pt keeps, and resume."""

from __future__ import annotations

import pytest
import torch

from spiral.config import AIRFRAMES, SimCfg
from spiral.core.checkpoint import load_checkpoint
from spiral.env import RaceSetting
from spiral.train import StageTrainer
from spiral.train.averaging import PolicyAverage
from spiral.train.resume import AVERAGE_KEY
from tests.train.test_trainer import tiny_stage


def test_average_moves_by_one_minus_decay_and_copies_buffers():
    """Weights 0 averaged towards 1 with decay 0.9: 0.1, then 0.19; a buffer takes the actor's value at once."""
    actor = torch.nn.BatchNorm1d(1)
    with torch.no_grad():
        actor.weight.zero_()
    average = PolicyAverage(actor, 0.9)
    with torch.no_grad():
        actor.weight.fill_(1.0)
        actor.running_mean.fill_(5.0)
    average.update(actor)
    assert float(average.model.weight) == pytest.approx(0.1)
    assert float(average.model.running_mean) == pytest.approx(5.0)  # a buffer, copied
    average.update(actor)
    assert float(average.model.weight) == pytest.approx(0.19)
    assert not average.model.training and not average.model.weight.requires_grad
    with pytest.raises(ValueError, match="decay"):
        PolicyAverage(actor, 1.0)


def test_best_checkpoint_keeps_the_average_and_a_resume_restores_it(oval2, tmp_path):
    """best.pt's actor is the averaged policy selection raced; periodic checkpoints carry the average too, and a
    resumed stage continues from it rather than restarting it at the current weights."""
    stage = tiny_stage(4).model_copy(update={"selection": tiny_stage(4).selection.model_copy(update={"average": 0.5})})
    trainer = StageTrainer(RaceSetting(oval2, AIRFRAMES["cf2x"], SimCfg()), stage, tmp_path, seed=2, progress=False)
    trainer.train()
    best = load_checkpoint(tmp_path / "best.pt")
    actor, average = best["actor_state_dict"]["mlp.0.weight"], best[AVERAGE_KEY]["mlp.0.weight"]
    torch.testing.assert_close(actor, average)  # the average, copied
    last = load_checkpoint(tmp_path / "ckpt" / "model_3.pt")
    live, averaged = last["actor_state_dict"]["mlp.0.weight"], last[AVERAGE_KEY]["mlp.0.weight"]
    assert not torch.allclose(live, averaged)
    resumed = StageTrainer(RaceSetting(oval2, AIRFRAMES["cf2x"], SimCfg()), stage.model_copy(update={"iterations": 6}),
                           tmp_path, seed=2, progress=False)
    assert resumed.selection.average is not None
    restored = resumed.selection.average.state_dict()["mlp.0.weight"]
    torch.testing.assert_close(restored, averaged)  # loaded from the checkpoint
