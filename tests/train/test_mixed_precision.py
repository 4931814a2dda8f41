"""bfloat16 autocast in PPO's update (``ppo.mixed_precision``): matrix products in bfloat16, weights in float32."""

from __future__ import annotations

import torch
from torch import nn

from spiral.config import AIRFRAMES, PPOCfg, SimCfg, StageSpec
from spiral.env import RaceSetting
from spiral.train import StageTrainer


def stage(mixed: bool) -> StageSpec:
    return StageSpec.model_validate({
        "name": "tiny", "worlds": 16, "iterations": 1, "env": {"obs": {"history_len": 1}},
        "ppo": {"num_steps_per_env": 8, "actor_hidden_dims": [16], "critic_hidden_dims": [16],
                "mixed_precision": mixed}, "selection": {"interval": 4, "races": 2}})


def layer_dtypes(trainer: StageTrainer) -> tuple[set[torch.dtype], set[torch.dtype]]:
    """Output dtypes of every linear layer of actor and critic during one update, and the parameters' dtypes."""
    alg, seen = trainer.runner.alg, set()
    hooks = [m.register_forward_hook(lambda mod, args, out: seen.add(out.dtype))
             for net in (alg.actor, alg.critic) for m in net.modules() if isinstance(m, nn.Linear)]
    alg.train_mode()
    trainer.collect(trainer.vec_env.get_observations())
    seen.clear()  # the rollout's own forward passes run in float32 either way
    alg.update()
    for h in hooks:
        h.remove()
    return seen, {p.dtype for net in (alg.actor, alg.critic) for p in net.parameters()}


def test_mixed_precision_runs_the_updates_products_in_bfloat16_and_keeps_float32_weights(oval2, tmp_path):
    on = StageTrainer(RaceSetting(oval2, AIRFRAMES["cf2x"], SimCfg()), stage(True), tmp_path / "on", progress=False)
    off = StageTrainer(RaceSetting(oval2, AIRFRAMES["cf2x"], SimCfg()), stage(False), tmp_path / "off", progress=False)
    assert layer_dtypes(on) == ({torch.bfloat16}, {torch.float32})
    assert layer_dtypes(off) == ({torch.float32}, {torch.float32})


def test_mixed_precision_is_off_by_default_and_reaches_rsl_rl():
    assert PPOCfg().to_rsl_rl()["algorithm"]["use_mixed_precision"] is False
    assert PPOCfg(mixed_precision=True).to_rsl_rl()["algorithm"]["use_mixed_precision"] is True
