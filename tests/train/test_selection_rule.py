"""Which evaluation a solo stage keeps as its best (success first, then the faster lap), and paired races of two
policies from the same placements."""

from __future__ import annotations

import math

import pytest
import torch

from spiral.config import AIRFRAMES, SimCfg, StageSpec
from spiral.core.checkpoint import load_checkpoint
from spiral.env import RaceSetting
from spiral.train import StageTrainer
from spiral.train.selection import EvalScore, paired_scores
from tests.env.helpers import make_env, waypoint_policy

# (iteration, success, lap) of a solo stage's evaluations: an early 1.00 at a slow lap, then faster laps at
# 0.95-0.98 with two collapses (the selection evaluations of a bfloat16 draw, seed 0, from iteration 99 on)
EVALS = [(99, 1.0, 5.14), (119, 1.0, 4.87), (139, 1.0, 4.57), (159, 1.0, 4.66), (179, 0.969, 4.58),
         (199, 0.953, 4.39), (219, 0.969, 4.21), (239, 0.984, 4.13), (259, 0.484, 3.96), (279, 0.953, 4.02),
         (299, 0.969, 3.96)]


def kept(evals):
    best = EvalScore(-1.0, -math.inf)
    for it, success, lap in evals:
        best = max(best, EvalScore(success, -lap, it))
    return best


def test_the_highest_success_wins_then_the_shorter_lap():
    assert kept(EVALS).iteration == 139


def test_a_score_survives_a_checkpoint_round_trip():
    best = kept(EVALS)
    assert EvalScore.from_json(best.to_json()) == best
    assert EvalScore.from_json({"success": 0.5, "lap_time": 4.0, "iteration": 3, "top_success": 0.6}).iteration == 3


def test_a_solo_stage_writes_its_best_evaluations_policy_as_best_pt(oval2, tmp_path):
    """The trainer's default selector keeps the highest success, then the shorter lap: the 139 evaluation's."""
    stage = StageSpec.model_validate({
        "name": "tiny", "worlds": 4, "iterations": 1, "env": {"obs": {"history_len": 1}},
        "ppo": {"num_steps_per_env": 4, "actor_hidden_dims": [8], "critic_hidden_dims": [8]},
        "selection": {"races": 2}})
    trainer = StageTrainer(RaceSetting(oval2, AIRFRAMES["cf2x"], SimCfg()), stage, tmp_path, progress=False)
    scores = iter(EvalScore(s, -lap, it) for it, s, lap in EVALS)
    trainer.selection.evaluate = lambda it: next(scores)
    for it, _, _ in EVALS:
        trainer.select_by_solo_eval(it)
    meta = load_checkpoint(tmp_path / "best.pt")["spiral"]
    assert meta["eval"]["iteration"] == 139
    assert meta["best"] == pytest.approx({"success": 1.0, "lap_time": 4.57, "iteration": 139})


def test_a_self_match_pair_scores_each_policy_on_its_own_races(oval2):
    """The promotion's format check races two policies from the same placements: a scripted lap finishes every race
    and a drone that dives into the ground none, in either order (the first score is not the second race's)."""
    env = make_env(oval2, worlds=2, training=False)
    lap, dive = waypoint_policy(env), (lambda obs: torch.tensor([[0.0, 0.0, -1.0, 0.0]]).expand(2, 4))
    assert tuple(score.success for score in paired_scores(env, lap, dive)) == pytest.approx((1.0, 0.0))
    assert tuple(score.success for score in paired_scores(env, dive, lap)) == pytest.approx((0.0, 1.0))
