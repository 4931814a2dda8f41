"""Which policy of a stage is its best: the candidate (the moving average of the weights, or the current policy)
raced from seeded start-box placements, scored by success, then lap time."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from rsl_rl.runners import OnPolicyRunner

from spiral.config.stage import SelectionCfg
from spiral.core.policy import Policy
from spiral.env.race_env import RaceEnv
from spiral.env.racing import run_races
from spiral.train.averaging import PolicyAverage

__all__ = ["EvalScore", "Selection", "paired_scores", "race_score"]


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

    def to_json(self) -> dict[str, float | int | None]:
        """``success``, ``lap_time`` (None without a finished lap) and ``iteration``, as checkpoints store them."""
        return {"success": self.success, "lap_time": self.lap_time, "iteration": self.iteration}

    @classmethod
    def from_json(cls, data: dict) -> EvalScore:
        """The score :meth:`to_json` wrote."""
        lap = data.get("lap_time")
        return cls(data["success"], -lap if lap is not None else -math.inf, data["iteration"])


class Selection:
    """Races the learner's candidate policy in a non-resetting ``eval_env`` (every slot a learner: a self-match in
    multi-drone stages) and keeps the moving average of its weights (``cfg.average`` > 0) that is the candidate."""

    def __init__(self, eval_env: RaceEnv, runner: OnPolicyRunner, cfg: SelectionCfg, *, device: str) -> None:
        self.eval_env, self.runner, self.cfg, self.device = eval_env, runner, cfg, device
        self.average: PolicyAverage | None = None
        """Moving average of the policy's weights: the candidate selection races (``selection.average`` > 0)."""

    def start_average(self, state: dict[str, torch.Tensor] | None) -> None:
        """Start the moving average at the current policy, or at a saved average (no average when it is off)."""
        if self.cfg.average <= 0:
            return
        self.average = PolicyAverage(self.runner.alg.get_policy(), self.cfg.average)
        if state is not None:
            self.average.load_state_dict(state)

    def update_average(self) -> None:
        """Move the average towards the policy after a PPO update."""
        if self.average is not None:
            self.average.update(self.runner.alg.get_policy())

    def candidate_policy(self) -> Policy:
        """The learner's deterministic policy that selection and promotion race: the moving average of its weights
        (``selection.average``), else the current one."""
        if self.average is not None:
            return self.average.policy()
        return self.runner.get_inference_policy(device=self.device)

    def evaluate(self, iteration: int, policy: Policy | None = None) -> EvalScore:
        """Race ``policy`` (the candidate by default) from seeded start-box placements."""
        score = race_score(self.eval_env, self.candidate_policy() if policy is None else policy, iteration)
        self.runner.alg.train_mode()
        return score

    def evaluate_pair(self, iteration: int, other: Policy) -> tuple[EvalScore, EvalScore]:
        """Scores of the candidate and of ``other`` from the same fresh start placements.

        A paired comparison: the best's score is not the lucky draw that got it promoted.
        """
        scores = paired_scores(self.eval_env, self.candidate_policy(), other, iteration)
        self.runner.alg.train_mode()
        return scores


def race_score(env: RaceEnv, policy: Policy, iteration: int = -1) -> EvalScore:
    """Success ratio of the drones present and mean lap of those that finished, ``policy`` flying every learner slot
    of ``env`` from its next seeded placements."""
    res = run_races(env, policy)  # reduced here: its tensors view the env's buffers, which the next race overwrites
    laps = res.lap_time[res.finished]
    lap = float(laps.mean()) if laps.numel() else math.inf
    return EvalScore(float(res.finished[res.present].float().mean()), -lap, iteration)


def paired_scores(env: RaceEnv, policy: Policy, other: Policy, iteration: int = -1) -> tuple[EvalScore, EvalScore]:
    """:func:`race_score` of ``policy`` and of ``other`` from the same fresh start placements of ``env``."""
    state = env.generator.get_state()
    own = race_score(env, policy, iteration)
    env.generator.set_state(state)
    return own, race_score(env, other, iteration)
