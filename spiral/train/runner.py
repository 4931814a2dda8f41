"""Stage training: rsl-rl PPO over a RaceEnv, as a loop over parts with one job each.

The parts: :class:`~spiral.train.resume.StageCheckpoints` (checkpoints and resume), :class:`~spiral.train.selection.
Selection` (evaluation races and the moving-average candidate; the selector that keeps ``best.pt`` is plugged in,
e.g. selfplay's promotion), :class:`~spiral.train.progress.TrainLog` (TensorBoard, ``train_log.jsonl``, progress),
:mod:`spiral.train.distributed` (the process group's sync) and :func:`~spiral.train.inputs.take_up_new_inputs`
(inputs new to a stage).
"""

from __future__ import annotations

import contextlib
import io
import math
import random
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict

from spiral.config.stage import StageSpec
from spiral.core.policy import MirrorOpponent, OpponentPolicy
from spiral.core.seeds import stream_seed
from spiral.env.mixed import MixedRaceEnv, training_env
from spiral.env.race_env import RaceEnv
from spiral.env.setting import RaceSetting
from spiral.env.vec_env import RaceVecEnv
from spiral.train import distributed
from spiral.train.inputs import take_up_new_inputs
from spiral.train.progress import TrainLog
from spiral.train.resume import AVERAGE_KEY, StageCheckpoints, stage_meta
from spiral.train.selection import EvalScore, Selection

__all__ = ["EvalScore", "StageStart", "StageTrainer", "TrainResult", "seed_everything"]


def seed_everything(seed: int) -> None:
    """Seed Python, numpy and torch (CPU and CUDA)."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


@dataclass
class TrainResult:
    """What a stage's training produced."""

    best_path: Path
    last_path: Path
    best: EvalScore
    iterations: int
    wall_time_s: float
    env_steps: int
    history: list[dict[str, float]]


@dataclass(frozen=True)
class StageStart:
    """What a stage's training starts from and races."""

    init_checkpoint: Path | None = None
    """The checkpoint of the policy the learner starts from (None: a fresh policy)."""
    opponents: dict[str, OpponentPolicy] = field(default_factory=dict)
    """The opponents of each part of its worlds that has opponent slots, by part name (the stage's own worlds are
    named for its scenario; :func:`spiral.selfplay.curriculum.published_opponents` builds a pipeline's); slots
    without one stay empty."""


class StageTrainer:
    """Trains one stage's learner with rsl-rl PPO.

    Writes ``run_dir/ckpt/model_<it>.pt`` every ``save_interval`` iterations and at the end, ``run_dir/best.pt``
    (the checkpoint that evaluated best), TensorBoard events in ``run_dir/tb`` and ``run_dir/train_log.jsonl``.
    Resumes from the newest valid checkpoint in ``run_dir/ckpt``.
    """

    def __init__(self, setting: RaceSetting, stage: StageSpec, run_dir: Path, *, start: StageStart | None = None,
                 device: str = "cpu", seed: int = 0, log: Callable[[str], None] = print,
                 progress: bool = True) -> None:
        start = start or StageStart()
        self.setting, self.stage = setting, stage
        self.run_dir, self.device, self.seed, self.log = Path(run_dir), device, seed, log
        self.dist = distributed.current()
        """This process's rank: rank 0 of 1 unless in a torchrun process group (only rank 0 writes files)."""
        seed_everything(self.dist.seed(seed))
        self.env: RaceEnv | MixedRaceEnv = training_env(setting, stage, device=device, seed=self.dist.seed(seed))
        opponents = self._set_opponents(start.opponents)
        d = stage.drones_per_world
        self.eval_env = RaceEnv(setting, stage.env, world_count=stage.eval_races, drones_per_world=d,
                                learner_slots=list(range(d)), device=device, seed=stream_seed(seed, "selection"),
                                training=False)
        self.vec_env = RaceVecEnv(self.env)
        with contextlib.redirect_stdout(io.StringIO()):  # rsl-rl prints the model architecture
            self.runner = distributed.GroupRunner(self.vec_env, stage.ppo.to_rsl_rl(), log_dir=None, device=device)
        self._mirror_learner(opponents)
        self.start_iteration = 0
        self.best = EvalScore(-1.0, -math.inf)
        self.selection = Selection(self.eval_env, self.runner, stage.selection, device=device)
        meta = stage_meta(stage, setting, seed=seed, obs_builder=self.env.obs_builder)
        self.checkpoints = StageCheckpoints(self.run_dir, self.runner.alg, meta, device=device, log=log)
        self.train_log = TrainLog(self.run_dir, stage.name, main=self.dist.is_main,
                                  show_progress=progress and self.dist.is_main, log=log)
        self._resume_or_init(start.init_checkpoint)
        if self.runner.is_distributed:
            self.start_iteration, self.best = distributed.share_training_state(
                self.runner.alg, self.start_iteration, self.best, device=self.device)

    # Setup

    def _set_opponents(self, opponents: dict[str, OpponentPolicy]) -> dict[str, Any]:
        """Drive the training worlds' opponent slots (per part of a mixed stage); the first races restart."""
        opponents = {name: policy for name, policy in opponents.items() if policy is not None}
        if opponents:
            if isinstance(self.env, MixedRaceEnv):
                self.env.set_opponent_policies(opponents)
            else:
                self.env.set_opponent_policy(next(iter(opponents.values())))
            self.env.reset()  # the first episodes were drawn without opponents
        return opponents

    def _mirror_learner(self, opponents: dict[str, Any]) -> None:
        """Mirror self-play: opponents that race the learner's current policy get it (its mean actions)."""
        actor = self.runner.alg.get_policy()  # called plainly it returns the mean action
        for policy in opponents.values():
            if isinstance(policy, MirrorOpponent):
                policy.live = actor

    def _resume_or_init(self, init_checkpoint: Path | None) -> None:
        """Resume from the newest valid checkpoint, else start from ``init_checkpoint``'s policy (if any)."""
        newest = self.checkpoints.newest()
        if newest is not None:
            path, data = newest
            self.runner.alg.load(data, None, strict=True)
            self.selection.start_average(data.get(AVERAGE_KEY))
            self.start_iteration = data["iter"] + 1  # rsl-rl stores the last completed iteration
            best = data["spiral"].get("best", {})
            if best.get("iteration", -1) >= 0:
                self.best = EvalScore.from_json(best)
            self.train_log.truncate(self.start_iteration)
            self.log(f"resuming stage '{self.stage.name}' from {path.name} (iteration {self.start_iteration})")
        elif init_checkpoint is not None:
            data = self.checkpoints.load(init_checkpoint)
            self.runner.alg.load(data, {"actor": True, "critic": True}, strict=True)
            self.log(f"stage '{self.stage.name}' starts from {init_checkpoint}")
            with torch.no_grad():  # the init policy's action noise, brought into this stage's range
                self.runner.alg.actor.distribution.std_param.clamp_(self.stage.ppo.min_noise_std,
                                                                    self.stage.ppo.max_noise_std)
            take_up_new_inputs(self.runner, self.vec_env, device=self.device, name=self.stage.name, log=self.log)
        if self.selection.average is None:
            self.selection.start_average(None)

    # Selection

    def save_best(self, iteration: int, score: EvalScore | None = None) -> Path:
        """Write the learner's candidate policy as ``best.pt`` and return its path."""
        path = self.run_dir / "best.pt"
        self.checkpoints.save(path, iteration, self.best, score, average=self.selection.average, candidate=True)
        return path

    def select_by_solo_eval(self, it: int) -> dict[str, float]:
        """Default selection: keep the checkpoint with the best self-match success, then lap time."""
        score = self.selection.evaluate(it)
        self.best = max(self.best, score)
        if self.best.iteration == score.iteration or not (self.run_dir / "best.pt").exists():
            self.save_best(it, score)
        lap = score.lap_time
        return {"eval/success": score.success, "eval/lap_time": lap if lap is not None else float("nan"),
                "eval/best_success": self.best.success}

    # Training loop

    def train(self, selector: Callable[[StageTrainer, int], dict[str, float]] | None = None, *,
              interval: int | None = None) -> TrainResult:
        """Run the remaining iterations of the stage's budget and return where the best policy is.

        ``selector`` keeps ``best.pt`` every ``interval`` iterations (the stage's ``selection.interval`` when None)
        and returns numbers to log; :meth:`select_by_solo_eval` when None.
        """
        select, interval = selector or StageTrainer.select_by_solo_eval, interval or self.stage.selection.interval
        total, main = self.stage.iteration_budget(), self.dist.is_main
        history: list[dict[str, float]] = []
        t_start = time.perf_counter()
        obs = self.vec_env.get_observations().to(self.device)
        self.runner.alg.train_mode()
        if self.runner.is_distributed:  # as rsl-rl's learn(): every rank starts from rank 0's parameters
            self.runner.alg.broadcast_parameters()
        last_path = self.checkpoints.periodic(max(self.start_iteration - 1, 0))
        with self.train_log.open(total, self.start_iteration) as train_log:
            for it in range(self.start_iteration, total):
                obs, row = self._iteration(it, total, obs, t_start)
                if main and ((it + 1) % interval == 0 or it == total - 1):  # selection
                    row.update(select(self, it))
                    train_log.evaluated(it, total, row)
                train_log.write(it, row)  # the row first: a resume drops rows past its checkpoint, never misses one
                if main and ((it + 1) % self.stage.ppo.save_interval == 0 or it == total - 1):  # checkpoint
                    last_path = self.checkpoints.periodic(it)
                    self.checkpoints.save(last_path, it, self.best, average=self.selection.average)
                history.append(row)
                train_log.advance(it, row)
        env_steps = (total - self.start_iteration) * self._steps_per_iteration()
        return TrainResult(self.run_dir / "best.pt", last_path, self.best, total, time.perf_counter() - t_start,
                           env_steps, history)

    def _iteration(self, it: int, total: int, obs: TensorDict, t_start: float) -> tuple[TensorDict, dict[str, float]]:
        """Iteration ``it`` of ``total``, rollout and PPO update; the last observations and the iteration's row
        (``t_start``: when the training began)."""
        alg, steps_per_it = self.runner.alg, self._steps_per_iteration()
        t0 = time.perf_counter()
        self.env.set_training_progress(it / total)
        obs, reward_sum = self.collect(obs)  # rollout
        t_collect = time.perf_counter() - t0
        losses = alg.update()  # PPO update
        self.selection.update_average()
        self.runner.current_learning_iteration = it
        row = {"iteration": it, "wall_s": time.perf_counter() - t_start, "collect_s": t_collect,
               "learn_s": time.perf_counter() - t0 - t_collect,
               "fps": steps_per_it / (time.perf_counter() - t0),
               "reward_per_step": float(reward_sum) / steps_per_it,
               "action_std": float(alg.get_policy().output_std.detach().mean()),
               "learning_rate": float(alg.learning_rate),
               **{f"loss/{k}": float(v) for k, v in losses.items()}, **self.env.pop_stats()}
        return obs, row

    def _steps_per_iteration(self) -> int:
        """Env steps of one rollout, over every learner drone."""
        return self.runner.cfg["num_steps_per_env"] * self.vec_env.num_envs

    def collect(self, obs: TensorDict) -> tuple[TensorDict, torch.Tensor]:
        """One rollout of ``num_steps_per_env`` steps into PPO's storage, and its returns; the last observations
        and the rollout's reward sum."""
        alg, env = self.runner.alg, self.vec_env
        reward_sum = torch.zeros((), device=env.device)
        with torch.inference_mode():
            for _ in range(self.runner.cfg["num_steps_per_env"]):
                actions = alg.act(obs)
                obs, rewards, dones, extras = env.step(actions.to(env.device))
                alg.process_env_step(obs, rewards, dones, extras)
                reward_sum += rewards.sum()
            alg.compute_returns(obs)
        return obs, reward_sum
