"""Stage training: learning signal, checkpoints, resume and policy reload."""

from __future__ import annotations

import json

import pytest
import torch

from spiral.config import AIRFRAMES, PPOCfg, SimCfg, StageSpec
from spiral.core.checkpoint import CheckpointError, list_checkpoints, load_checkpoint, newest_valid_checkpoint
from spiral.env import RaceSetting
from spiral.eval.evaluate import RaceSet, evaluate_policy
from spiral.train import StageStart, StageTrainer, load_policy

CF2X = AIRFRAMES["cf2x"]


def tiny_stage(iterations: int, *, worlds: int = 64) -> StageSpec:
    return StageSpec.model_validate({
        "name": "tiny", "worlds": worlds, "iterations": iterations,
        "env": {"obs": {"history_len": 1, "gate_normals": True, "pid_integral": True, "opponent_velocity": False,
                        "teammates": False, "closest_approach": False}},
        "ppo": {"num_steps_per_env": 16, "save_interval": 2, "actor_hidden_dims": [32, 32],
                "critic_hidden_dims": [32, 32]},
        "selection": {"interval": 4, "races": 4}})


def test_short_training_improves_the_mean_reward(line2, tmp_path):
    """Raise the mean per-step reward of a 2-gate track within a few dozen iterations."""
    stage = tiny_stage(40, worlds=128).model_copy(update={"ppo": PPOCfg(
        num_steps_per_env=24, actor_hidden_dims=[64, 64], critic_hidden_dims=[64, 64], save_interval=100)})
    result = StageTrainer(RaceSetting(line2, CF2X, SimCfg()), stage, tmp_path, seed=1, progress=False).train()
    rows = [json.loads(line) for line in (tmp_path / "train_log.jsonl").read_text().splitlines()]
    early = sum(r["reward_per_step"] for r in rows[:5]) / 5
    late = sum(r["reward_per_step"] for r in rows[-5:]) / 5
    assert late > early + 0.01
    assert result.best_path.exists()


def test_checkpoint_round_trip_and_resume_continue_the_iteration_count(oval2, tmp_path):
    """Resume a stopped stage from its newest checkpoint and end at the full iteration count."""
    StageTrainer(RaceSetting(oval2, CF2X, SimCfg()), tiny_stage(4), tmp_path, seed=2, progress=False).train()
    assert [it for it, _ in list_checkpoints(tmp_path / "ckpt")] == [3, 1]
    data = load_checkpoint(tmp_path / "ckpt" / "model_3.pt")
    assert data["iter"] == 3 and data["spiral"]["stage"] == "tiny"
    assert data["spiral"]["obs_slices"] == {"ego": [0, 12], "presence": [12, 14], "gate_normals": [14, 20],
                                            "pid_integral": [20, 23], "history": [23, 39]}
    assert data["spiral"]["obs_history_fields"] == {"opponents": [0, 6], "gates": [6, 12], "action": [12, 16]}
    trainer = StageTrainer(RaceSetting(oval2, CF2X, SimCfg()), tiny_stage(6), tmp_path, seed=2, progress=False)
    assert trainer.start_iteration == 4
    result = trainer.train()
    assert result.iterations == 6
    assert load_checkpoint(tmp_path / "ckpt" / "model_5.pt")["iter"] == 5
    lines = (tmp_path / "train_log.jsonl").read_text().splitlines()
    assert [json.loads(x)["iteration"] for x in lines] == [0, 1, 2, 3, 4, 5]


def test_corrupt_newest_checkpoint_falls_back_to_the_previous_one(oval2, tmp_path):
    """Skip a truncated newest checkpoint with a warning and resume from the one before."""
    StageTrainer(RaceSetting(oval2, CF2X, SimCfg()), tiny_stage(4), tmp_path, seed=2, progress=False).train()
    newest = tmp_path / "ckpt" / "model_3.pt"
    newest.write_bytes(newest.read_bytes()[:100])
    with pytest.raises(CheckpointError, match="checksum"):
        load_checkpoint(newest)
    warnings: list[str] = []
    assert newest_valid_checkpoint(tmp_path / "ckpt", warn=warnings.append) == tmp_path / "ckpt" / "model_1.pt"
    assert "model_3.pt" in warnings[0]
    trainer = StageTrainer(RaceSetting(oval2, CF2X, SimCfg()), tiny_stage(4), tmp_path, seed=2, progress=False,
                           log=warnings.append)
    assert trainer.start_iteration == 2


def test_loaded_policy_reproduces_the_trained_actor(oval2, tmp_path):
    """Give the same actions from a reloaded best.pt as from the trainer's inference policy."""
    trainer = StageTrainer(RaceSetting(oval2, CF2X, SimCfg()), tiny_stage(4), tmp_path, seed=3, progress=False)
    trainer.train()
    data = load_checkpoint(tmp_path / "best.pt")
    trainer.runner.alg.load(data, {"actor": True}, strict=True)
    policy = load_policy(tmp_path / "best.pt")
    obs = trainer.env.get_observations()
    expected = trainer.runner.get_inference_policy()(obs)
    assert torch.allclose(policy(obs), expected, atol=1e-6)
    res = evaluate_policy(policy, RaceSet(oval2, "solo", 3, 0))
    assert res.finished.shape == (3, 1)


@pytest.mark.bitwise
def test_same_seed_gives_the_same_training_on_cpu(oval2, tmp_path):
    """Produce bit-identical weights from two runs with the same seed."""
    a = StageTrainer(RaceSetting(oval2, CF2X, SimCfg()), tiny_stage(2), tmp_path / "a", seed=5, progress=False)
    a.train()
    b = StageTrainer(RaceSetting(oval2, CF2X, SimCfg()), tiny_stage(2), tmp_path / "b", seed=5, progress=False)
    b.train()
    wa = load_checkpoint(tmp_path / "a" / "ckpt" / "model_1.pt")["actor_state_dict"]
    wb = load_checkpoint(tmp_path / "b" / "ckpt" / "model_1.pt")["actor_state_dict"]
    assert all(torch.equal(wa[k], wb[k]) for k in wa)


@pytest.mark.bitwise
def test_simulator_threads_leave_the_training_unchanged(oval2, tmp_path):
    """Step the worlds on two threads (rollouts and selection evaluations) and get the weights and the log of one
    thread, bit for bit."""
    runs = {}
    for threads in (1, 2):
        out = tmp_path / str(threads)
        setting = RaceSetting(oval2, CF2X, SimCfg(), sim_threads=threads)
        trainer = StageTrainer(setting, tiny_stage(4), out, seed=5, progress=False)
        assert len(trainer.env.world._shards) == threads
        trainer.train()
        runs[threads] = (load_checkpoint(out / "ckpt" / "model_3.pt")["actor_state_dict"],
                         [json.dumps({k: v for k, v in json.loads(x).items() if not k.endswith("_s") and k != "fps"})
                          for x in (out / "train_log.jsonl").read_text().splitlines()])  # as text: NaN == NaN
    (w1, log1), (w2, log2) = runs[1], runs[2]
    assert all(torch.equal(w1[k], w2[k]) for k in w1)
    assert log1 == log2 and any("eval/success" in row for row in log1)


@pytest.mark.bitwise
def test_paired_evaluation_races_both_policies_from_the_same_fresh_placements(oval2, tmp_path):
    """Start the learner's and the other policy's self-match from one draw, and the next pair from a new one."""
    trainer = StageTrainer(RaceSetting(oval2, CF2X, SimCfg()), tiny_stage(2), tmp_path, seed=4, progress=False)
    env, reset, starts = trainer.eval_env, trainer.eval_env.reset, []

    def recording_reset():
        obs = reset()
        starts.append(env.pos.clone())
        return obs

    env.reset = recording_reset
    own, other = trainer.selection.evaluate_pair(0, trainer.runner.get_inference_policy())
    assert (own.success, own.lap_time) == (other.success, other.lap_time)  # same policy, same placements
    trainer.selection.evaluate_pair(1, trainer.runner.get_inference_policy())
    assert len(starts) == 4
    assert torch.equal(starts[0], starts[1]) and torch.equal(starts[2], starts[3])
    assert not torch.equal(starts[0], starts[2])


def test_stage_takes_over_its_init_noise_clamped_to_its_own_range_and_keeps_training_it(oval2, tmp_path):
    """A stage whose max_noise_std is below its init policy's noise starts at that maximum, not stuck on it."""
    first = tiny_stage(2).model_copy(update={"ppo": tiny_stage(2).ppo.model_copy(update={"init_noise_std": 0.4})})
    init = StageTrainer(RaceSetting(oval2, CF2X, SimCfg()), first, tmp_path / "a", seed=0,
                        progress=False).train().best_path
    quiet = tiny_stage(2)
    quiet = quiet.model_copy(update={"ppo": quiet.ppo.model_copy(update={"max_noise_std": 0.1})})
    trainer = StageTrainer(RaceSetting(oval2, CF2X, SimCfg()), quiet, tmp_path / "b", seed=0, progress=False,
                           start=StageStart(init))
    std = trainer.runner.alg.actor.distribution.std_param
    assert torch.allclose(std, torch.full_like(std, 0.1))
    trainer.train()
    assert not torch.allclose(std, torch.full_like(std, 0.1))


def test_noise_range_must_not_be_empty():
    """Reject a maximum action noise below the minimum."""
    with pytest.raises(ValueError, match="max_noise_std"):
        PPOCfg(min_noise_std=0.2, max_noise_std=0.1)


@pytest.mark.bitwise
def test_frozen_policy_acts_as_its_actor_modules_to_the_bit_after_a_reload_or_a_cast_too(oval2, tmp_path):
    """A frozen policy's direct forward pass gives what the actor's modules give, for any number of rows, and
    follows weights loaded into it or cast afterwards."""
    StageTrainer(RaceSetting(oval2, CF2X, SimCfg()), tiny_stage(4), tmp_path, seed=3, progress=False).train()
    policy, other = load_policy(tmp_path / "best.pt"), load_policy(tmp_path / "ckpt" / "model_1.pt")
    obs = torch.randn(200, policy.obs_layout["obs_dim"])
    actor = policy.actor
    for rows in (1, 13, 200):
        assert torch.equal(policy.actions(obs[:rows]), actor.mlp(actor.obs_normalizer(obs[:rows])))
    assert not torch.equal(policy.actions(obs), other.actions(obs))
    policy.load_state_dict(other.state_dict())
    assert torch.equal(policy.actions(obs), other.actions(obs))
    policy.double()
    assert torch.equal(policy.actions(obs.double()), actor.mlp(actor.obs_normalizer(obs.double())))


def test_the_stage_trainer_runs_ppo_over_the_storage_that_gathers_once(oval2, tmp_path):
    """The algorithm named in the rsl-rl config is built with the storage that gathers its rollout once per update."""
    from spiral.train.batches import GatherOncePPO, GatherOnceStorage

    trainer = StageTrainer(RaceSetting(oval2, CF2X, SimCfg()), tiny_stage(1, worlds=4), tmp_path, seed=2,
                           progress=False)
    assert isinstance(trainer.runner.alg, GatherOncePPO)
    assert isinstance(trainer.runner.alg.storage, GatherOnceStorage)
