"""Stage training: rsl-rl PPO over a RaceEnv with atomic checkpoints, resume, selection by evaluation, progress."""

from __future__ import annotations

import contextlib
import functools
import io
import json
import math
import random
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from torch.utils.tensorboard import SummaryWriter

from spiral.config.airframe import AirframeCfg
from spiral.config.sim import SimCfg
from spiral.config.stage import StageSpec
from spiral.config.track import TrackSpec
from spiral.core.checkpoint import CheckpointError, load_checkpoint, newest_valid_checkpoint, save_checkpoint
from spiral.core.inputs import silence_inputs, unused_inputs
from spiral.core.policy import MirrorOpponent, OpponentPolicy, Policy
from spiral.env.mixed import MixedRaceEnv, training_env
from spiral.env.observations import HISTORY_FIELDS
from spiral.env.race_env import RaceEnv
from spiral.env.racing import run_races
from spiral.env.vec_env import RaceVecEnv
from spiral.train import distributed
from spiral.train.averaging import PolicyAverage
from spiral.train.inputs import calibrate_inputs, model_inputs, widen_inputs

__all__ = ["EvalScore", "StageTrainer", "TrainResult", "seed_everything"]

AVERAGE_KEY = "average_actor_state_dict"
"""Checkpoint key of the moving average of the actor's weights (``selection.average``)."""

WARMUP_S = 2.0
"""Flight time of the rollout that measures the statistics of inputs new to a stage [s]."""


def seed_everything(seed: int) -> None:
    """Seed Python, numpy and torch (CPU and CUDA)."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


@dataclass(order=True)
class EvalScore:
    """Selection key: a higher success ratio wins, then a shorter mean lap time."""

    success: float
    neg_lap_time: float
    iteration: int = field(compare=False, default=-1)

    @property
    def lap_time(self) -> float | None:
        """Mean lap time of the successful races [s]."""
        return None if math.isinf(self.neg_lap_time) else -self.neg_lap_time


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


class StageTrainer:
    """Trains one stage's learner with rsl-rl PPO.

    Writes ``run_dir/ckpt/model_<it>.pt`` every ``save_interval`` iterations and at the end, ``run_dir/best.pt``
    (the checkpoint that evaluated best), TensorBoard events in ``run_dir/tb`` and ``run_dir/train_log.jsonl``.
    Resumes from the newest valid checkpoint in ``run_dir/ckpt``.
    """

    def __init__(
        self,
        track: TrackSpec,
        airframe: AirframeCfg,
        sim: SimCfg,
        stage: StageSpec,
        run_dir: Path,
        *,
        device: str = "cpu",
        seed: int = 0,
        init_checkpoint: Path | None = None,
        opponent: OpponentPolicy | dict[str, OpponentPolicy] | None = None,
        selector: Callable[[StageTrainer, int], dict[str, float]] | None = None,
        selection_interval: int | None = None,
        log: Callable[[str], None] = print,
        progress: bool = True,
    ) -> None:
        self.track, self.airframe, self.sim, self.stage = track, airframe, sim, stage
        self.run_dir, self.device, self.seed, self.log, self.show_progress = Path(run_dir), device, seed, log, progress
        self.dist = distributed.current()
        """This process's rank: rank 0 of 1 unless in a torchrun process group (only rank 0 writes files)."""
        self.show_progress = progress and self.dist.is_main
        seed_everything(self.dist.seed(seed))
        d = stage.drones_per_world
        self.env: RaceEnv | MixedRaceEnv = training_env(track, airframe, sim, stage, device=device,
                                                        seed=self.dist.seed(seed))
        opponents = opponent if isinstance(opponent, dict) else {stage.scenario: opponent} if opponent else {}
        opponents = {name: policy for name, policy in opponents.items() if policy is not None}
        if opponents:
            if isinstance(self.env, MixedRaceEnv):
                self.env.set_opponent_policies(opponents)
            else:
                self.env.set_opponent_policy(next(iter(opponents.values())))
            self.env.reset()  # the first episodes were drawn without opponents
        self.eval_env = RaceEnv(track, airframe, sim, stage.env, world_count=stage.selection.races,
                                drones_per_world=d, learner_slots=list(range(d)), device=device,
                                seed=seed + 10_000, auto_reset=False)
        self.vec_env = RaceVecEnv(self.env)
        with contextlib.redirect_stdout(io.StringIO()):  # rsl-rl prints the model architecture
            self.runner = distributed.GroupRunner(self.vec_env, stage.ppo.to_rsl_rl(), log_dir=None, device=device)
        actor = self.runner.alg.get_policy()  # called plainly it returns the mean action
        sampled = stage.selfplay.mirror_actions == "sampled"
        for policy in opponents.values():
            if isinstance(policy, MirrorOpponent):  # mirror self-play: opponents that race the learner's current policy
                policy.live = functools.partial(actor, stochastic_output=True) if sampled else actor
        self.start_iteration = 0
        self.best = EvalScore(-1.0, -math.inf)
        self.selector = selector or StageTrainer.select_by_solo_eval
        """Called every ``selection_interval`` iterations; keeps ``best.pt`` and returns numbers to log."""
        self.selection_interval = selection_interval or stage.selection.interval
        self.average: PolicyAverage | None = None
        """Moving average of the policy's weights: the candidate selection races (``selection.average`` > 0)."""
        self._resume_or_init(init_checkpoint)
        if self.runner.is_distributed:
            self.start_iteration, self.best = distributed.share_training_state(
                self.runner.alg, self.start_iteration, self.best, device=self.device)

    # Checkpoints

    @property
    def ckpt_dir(self) -> Path:
        """Folder of the periodic checkpoints."""
        return self.run_dir / "ckpt"

    def _meta(self, iteration: int, score: EvalScore | None = None) -> dict[str, Any]:
        meta = {
            "iteration": iteration,
            "stage": self.stage.name,
            "scenario": self.stage.scenario,
            "track": self.track.name,
            "seed": self.seed,
            "obs_layout": self.env.obs_builder.layout(),
            "obs_slices": {name: list(span) for name, span in self.env.obs_builder.slices().items()},
            "obs_history_fields": {name: list(span) for name, span in HISTORY_FIELDS.items()},
            "airframe": self.airframe.model_dump(),
            "sim": self.sim.model_dump(),
            "ppo": self.stage.ppo.model_dump(),
            "env": self.stage.env.model_dump(),
            "best": {"success": self.best.success, "lap_time": self.best.lap_time, "iteration": self.best.iteration},
        }
        if score is not None:
            meta["eval"] = {"success": score.success, "lap_time": score.lap_time, "iteration": score.iteration}
        return meta

    def _save(self, path: Path, iteration: int, score: EvalScore | None = None, *, candidate: bool = False) -> None:
        """A training checkpoint; with ``candidate`` its actor is the policy selection raced (the average, if any)."""
        state = self.runner.alg.save()
        state["iter"] = iteration
        state["infos"] = None
        if self.average is not None:
            state[AVERAGE_KEY] = self.average.state_dict()
            if candidate:
                state["actor_state_dict"] = self.average.state_dict()
        save_checkpoint(path, state, self._meta(iteration, score))

    def _resume_or_init(self, init_checkpoint: Path | None) -> None:
        newest = newest_valid_checkpoint(self.ckpt_dir, warn=lambda m: self.log(f"warning: {m}"))
        if newest is not None:
            data = load_checkpoint(newest, map_location=self.device)
            self._check_layout(data, newest)
            self.runner.alg.load(data, None, strict=True)
            self._start_average(data.get(AVERAGE_KEY))
            self.start_iteration = data["iter"] + 1  # rsl-rl stores the last completed iteration
            best = data["spiral"].get("best", {})
            if best.get("iteration", -1) >= 0:
                lap = best.get("lap_time")
                self.best = EvalScore(best["success"], -lap if lap is not None else -math.inf, best["iteration"])
            self._truncate_log(self.start_iteration)
            self.log(f"resuming stage '{self.stage.name}' from {newest.name} (iteration {self.start_iteration})")
        elif init_checkpoint is not None:
            data = load_checkpoint(init_checkpoint, map_location=self.device)
            self._check_layout(data, init_checkpoint)
            try:  # a centralised critic sees more than the init stage's critic did
                data["critic_state_dict"] = widen_inputs(data["critic_state_dict"], self.runner.alg.critic)
            except ValueError as exc:
                raise CheckpointError(f"{init_checkpoint}: critic: {exc}") from exc
            self.runner.alg.load(data, {"actor": True, "critic": True}, strict=True)
            self.log(f"stage '{self.stage.name}' starts from {init_checkpoint}")
            self._clamp_noise()
            self._take_up_new_inputs()
        if self.average is None:
            self._start_average(None)

    def _start_average(self, state: dict[str, torch.Tensor] | None) -> None:
        """Start the moving average at the current policy, or at a saved average."""
        if self.stage.selection.average <= 0:
            return
        self.average = PolicyAverage(self.runner.alg.get_policy(), self.stage.selection.average)
        if state is not None:
            self.average.load_state_dict(state)

    def _clamp_noise(self) -> None:
        """Bring the action noise taken over from the init policy into this stage's range, where it trains."""
        with torch.no_grad():  # PPOCfg builds a Gaussian with a scalar std parameter
            self.runner.alg.actor.distribution.std_param.clamp_(self.stage.ppo.min_noise_std,
                                                                self.stage.ppo.max_noise_std)

    def _take_up_new_inputs(self) -> None:
        """Inputs the init policy never saw vary (e.g. the opponents of a solo policy) start with zero weights,
        so the stage starts from exactly that policy, and with statistics from a short warm-up rollout in this
        stage's worlds, so they train at unit scale from the first iteration (:mod:`spiral.train.inputs`)."""
        models = {"actor": self.runner.alg.actor, "critic": self.runner.alg.critic}
        unused = {name: unused_inputs(model) for name, model in models.items()}
        if not any(mask.any() for mask in unused.values()):
            return
        for name, model in models.items():
            silence_inputs(model, unused[name])
        policy = self.runner.get_inference_policy(device=self.device)
        obs = self.vec_env.get_observations().to(self.device)
        batches = []
        with torch.inference_mode():
            for _ in range(math.ceil(WARMUP_S / self.env.dt)):
                obs = self.vec_env.step(policy(obs))[0].to(self.device)
                batches.append(obs)
            self.env.reset()  # training starts from fresh races (env buffers are inference tensors by now)
        inputs = {name: torch.cat([model_inputs(model, b) for b in batches]).clone() for name, model in models.items()}
        calibrated = {name: calibrate_inputs(model, inputs[name], unused[name]) for name, model in models.items()}
        self.runner.alg.train_mode()
        self.env.pop_stats()
        self.log(f"stage '{self.stage.name}': {int(unused['actor'].sum())} policy inputs were constant in the init "
                 f"policy's stage; {int(calibrated['actor'].sum())} vary here and start with zero weights and "
                 f"statistics from a {WARMUP_S:.0f} s warm-up (critic: {int(calibrated['critic'].sum())} of "
                 f"{int(unused['critic'].sum())})")

    def _truncate_log(self, start: int) -> None:
        """Drop log rows of iterations that will be trained again after a resume."""
        path = self.run_dir / "train_log.jsonl"
        if not path.exists() or not self.dist.is_main:
            return
        rows = [line for line in path.read_text().splitlines() if line.strip()]
        kept = [line for line in rows if json.loads(line)["iteration"] < start]
        path.write_text("".join(line + "\n" for line in kept))

    def _check_layout(self, data: dict[str, Any], path: Path) -> None:
        stored = data["spiral"]["obs_layout"]
        if stored != self.env.obs_builder.layout():
            raise CheckpointError(f"{path}: observation layout {stored} differs from this stage's")

    # Evaluation

    def candidate_policy(self) -> Policy:
        """The learner's deterministic policy that selection and promotion race: the moving average of its weights
        (``selection.average``), else the current one."""
        if self.average is not None:
            return self.average.policy()
        return self.runner.get_inference_policy(device=self.device)

    def evaluate(self, iteration: int, policy: Policy | None = None) -> EvalScore:
        """Race ``policy`` (the learner's candidate by default) from seeded start-box placements (self-match in
        multi-drone stages)."""
        if policy is None:
            policy = self.candidate_policy()
        res = run_races(self.eval_env, policy)
        self.runner.alg.train_mode()
        ok = res.finished[res.present]
        laps = res.lap_time[res.finished]
        lap = float(laps.mean()) if laps.numel() else math.inf
        return EvalScore(float(ok.float().mean()), -lap, iteration)

    def evaluate_pair(self, iteration: int, other: Policy) -> tuple[EvalScore, EvalScore]:
        """Self-match scores of the learner and of ``other`` from the same fresh start placements.

        A paired comparison: the best's score is not the lucky draw that got it promoted.
        """
        state = self.eval_env.generator.get_state()
        own = self.evaluate(iteration)
        self.eval_env.generator.set_state(state)
        return own, self.evaluate(iteration, other)

    # Training loop

    def train(self) -> TrainResult:
        """Run the remaining iterations of the stage's budget and return where the best policy is."""
        total = self.stage.iteration_budget()
        alg, env, cfg, main = self.runner.alg, self.vec_env, self.runner.cfg, self.dist.is_main
        writer = SummaryWriter(log_dir=str(self.run_dir / "tb"), flush_secs=30) if main else None
        history: list[dict[str, float]] = []
        steps_per_it = cfg["num_steps_per_env"] * env.num_envs
        t_start = time.perf_counter()
        obs = env.get_observations().to(self.device)
        alg.train_mode()
        if self.runner.is_distributed:  # as rsl-rl's learn(): every rank starts from rank 0's parameters
            alg.broadcast_parameters()
        last_path = self.ckpt_dir / f"model_{max(self.start_iteration - 1, 0)}.pt"
        with self._progress(total) as (progress, task):
            for it in range(self.start_iteration, total):
                t0 = time.perf_counter()
                self.env.set_training_progress(it / total)
                reward_sum = torch.zeros((), device=env.device)
                with torch.inference_mode():
                    for _ in range(cfg["num_steps_per_env"]):
                        actions = alg.act(obs)
                        obs, rewards, dones, extras = env.step(actions.to(env.device))
                        alg.process_env_step(obs, rewards, dones, extras)
                        reward_sum += rewards.sum()
                    alg.compute_returns(obs)
                t_collect = time.perf_counter() - t0
                losses = alg.update()
                if self.average is not None:
                    self.average.update(alg.get_policy())
                self.runner.current_learning_iteration = it
                row = {"iteration": it, "wall_s": time.perf_counter() - t_start, "collect_s": t_collect,
                       "learn_s": time.perf_counter() - t0 - t_collect,
                       "fps": steps_per_it / (time.perf_counter() - t0),
                       "reward_per_step": float(reward_sum) / steps_per_it,
                       "action_std": float(alg.get_policy().output_std.detach().mean()),
                       "learning_rate": float(alg.learning_rate),
                       **{f"loss/{k}": float(v) for k, v in losses.items()}, **self.env.pop_stats()}
                if main and ((it + 1) % self.selection_interval == 0 or it == total - 1):
                    row.update(self.selector(self, it))
                    if not self.show_progress:  # e.g. a pipeline worker: a line per evaluation instead of a bar
                        self.log(f"{self.stage.name} {it + 1}/{total} ({row['wall_s']:.0f} s): {self._status(row)}")
                if writer is not None:  # the row first: a resume drops rows past its checkpoint, never misses one
                    self._write_row(writer, row, it)
                if main and ((it + 1) % self.stage.ppo.save_interval == 0 or it == total - 1):
                    last_path = self.ckpt_dir / f"model_{it}.pt"
                    self._save(last_path, it)
                history.append(row)
                progress.update(task, completed=it + 1, stats=self._status(row))
        if writer is not None:
            writer.close()
        env_steps = (total - self.start_iteration) * steps_per_it
        return TrainResult(self.run_dir / "best.pt", last_path, self.best, total, time.perf_counter() - t_start,
                           env_steps, history)

    def save_best(self, iteration: int, score: EvalScore | None = None) -> Path:
        """Write the learner's candidate policy as ``best.pt`` and return its path."""
        path = self.run_dir / "best.pt"
        self._save(path, iteration, score, candidate=True)
        return path

    def select_by_solo_eval(self, it: int) -> dict[str, float]:
        """Default selection: keep the checkpoint with the best self-match success, then lap time."""
        score = self.evaluate(it)
        if score > self.best or not (self.run_dir / "best.pt").exists():
            self.best = score if score > self.best else self.best
            self.save_best(it, score)
        lap = score.lap_time
        return {"eval/success": score.success, "eval/lap_time": lap if lap is not None else float("nan"),
                "eval/best_success": self.best.success}

    def _write_row(self, writer: SummaryWriter, row: dict[str, float], it: int) -> None:
        for key, value in row.items():
            if key != "iteration" and isinstance(value, float) and math.isfinite(value):
                writer.add_scalar(key if "/" in key else f"train/{key}", value, it)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        with open(self.run_dir / "train_log.jsonl", "a") as f:
            f.write(json.dumps(row) + "\n")

    @staticmethod
    def _status(row: dict[str, float]) -> str:
        lap = row.get("lap_time", float("nan"))
        text = f"success {row.get('success', 0):.2f} lap {lap:.2f}s fps {row['fps']:.0f}"
        if "eval/success" in row:
            text += f" | eval {row['eval/success']:.2f} @ {row['eval/lap_time']:.2f}s"
        return text

    @contextlib.contextmanager
    def _progress(self, total: int):
        progress = Progress(
            TextColumn(f"[bold]{self.stage.name}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
            TimeElapsedColumn(), TimeRemainingColumn(), TextColumn("{task.fields[stats]}"),
            disable=not self.show_progress,
        )
        with progress:
            task = progress.add_task(self.stage.name, total=total, completed=self.start_iteration, stats="")
            yield progress, task
