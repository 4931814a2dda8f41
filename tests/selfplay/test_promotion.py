"""Promotion: the rule on scripted results (win rate, self-match, other scenarios, safer learners), Elo, and a
stage's races in its mix's other scenarios."""

from __future__ import annotations

import json

import pytest

from spiral.config import PromotionCfg, SimCfg, StageSpec
from spiral.env import RaceSetting
from spiral.selfplay import HeadToHead, StageSources, elo_update, run_stage, should_promote
from spiral.selfplay.promotion import self_match_envs
from tests.selfplay.helpers import CF2X, COMMON, PERMISSIVE, SOLO


def test_promotion_rule_on_scripted_results():
    """Promote on win rate ≥ 0.55 unless success drops by more than 0.05 (the defaults)."""
    cfg = PromotionCfg()
    assert should_promote(HeadToHead(64, 36, 20, 8, 0.95, 0.96), cfg)
    assert not should_promote(HeadToHead(64, 35, 20, 9, 0.95, 0.96), cfg)  # 0.547 < 0.55
    assert not should_promote(HeadToHead(64, 40, 20, 4, 0.90, 0.96), cfg)  # success drop 0.06


def test_promotion_also_needs_a_self_match_no_worse_than_the_best():
    """Refuse a winner whose self-match success is more than 0.05 below the best's, unless the check is off."""
    win = HeadToHead(64, 50, 10, 4, 0.95, 0.90)
    assert should_promote(win, PromotionCfg(), (0.80, 0.81))
    assert not should_promote(win, PromotionCfg(), (0.70, 0.81))
    assert should_promote(win, PromotionCfg(self_match=False), (0.70, 0.81))


def test_promotion_refuses_a_learner_that_loses_another_format_of_its_stage():
    """A 2v2 learner that wins its duels but races solo at 0.09 where the best races 0.93 is not promoted, whether
    it would rise as faster or as safer; within max_success_drop (0.05) of the best in every format it is."""
    cfg = PromotionCfg(max_success_drop=0.05)
    win, slower = HeadToHead(64, 40, 20, 4, 0.98, 0.98), HeadToHead(64, 5, 40, 19, 0.98, 0.98)
    assert should_promote(win, cfg, (0.97, 0.96), {"solo": (0.90, 0.93), "1v1": (0.99, 0.97)})
    assert not should_promote(win, cfg, (0.97, 0.96), {"solo": (0.09, 0.93), "1v1": (0.99, 0.97)})
    assert should_promote(slower, cfg, (0.99, 0.90), {"solo": (1.0, 1.0)})
    assert not should_promote(slower, cfg, (0.99, 0.90), {"solo": (0.80, 1.0)})
    assert not should_promote(win, cfg.model_copy(update={"self_match": False}), None, {"1v1": (0.50, 0.97)})


def test_a_safer_learner_is_promoted_without_winning_the_duel():
    """Promote on a self-match gain of ≥ 0.05 when the duel success holds, even with few wins; not otherwise."""
    slower = HeadToHead(64, 5, 40, 19, 0.72, 0.72)
    assert should_promote(slower, PromotionCfg(), (0.84, 0.78))
    assert not should_promote(slower, PromotionCfg(), (0.81, 0.78))  # gain 0.03 < 0.05
    assert not should_promote(HeadToHead(64, 5, 40, 19, 0.60, 0.72), PromotionCfg(), (0.90, 0.78))  # duel less safe
    assert not should_promote(slower, PromotionCfg(self_match_gain=None), (0.84, 0.78))


def test_elo_update_is_zero_sum_and_follows_the_expected_score():
    """Move equal ratings by K·(S − ½) and keep the sum."""
    a, b = elo_update(1000.0, 1000.0, 1.0, 16.0)
    assert (a, b) == pytest.approx((1008.0, 992.0))
    a, b = elo_update(1200.0, 1000.0, 0.5, 16.0)
    assert a + b == pytest.approx(2200.0) and a < 1200.0


def test_promotion_with_scenarios_races_the_learner_and_the_best_in_each_other_scenario_of_the_mix(line2, tmp_path):
    """With `promotion.scenarios` a 1v1 stage mixing in solo worlds logs, at each promotion check, the solo success of
    learner and best (four one-drone races each: a multiple of 1/4), and nothing of it without the option (no
    self-matches from track starts either way)."""
    solo = StageSpec.model_validate({"name": "solo", "iterations": 1, **SOLO})
    run_stage(RaceSetting(line2, CF2X, SimCfg()), solo, tmp_path / "solo",
              sources=StageSources(pool_dir=tmp_path / "pool"), progress=False)
    logged = {}
    for scenarios in (True, False):
        duel = StageSpec.model_validate({
            "name": "1v1", "scenario": "1v1", "iterations": 1, "mix": {"solo": 0.25},
            "selfplay": {"promotion": {**PERMISSIVE["promotion"], "scenarios": scenarios, "track_starts": False}},
            **COMMON})
        run_dir = tmp_path / f"duel-{scenarios}"
        run_stage(RaceSetting(line2, CF2X, SimCfg()), duel, run_dir,
                  sources=StageSources(pool_dir=tmp_path / f"pool-{scenarios}",
                                       init_checkpoint=tmp_path / "solo" / "best.pt"), progress=False)
        row = json.loads((run_dir / "train_log.jsonl").read_text().splitlines()[-1])
        logged[scenarios] = {k: v for k, v in row.items() if k.startswith("scenarios/")}
    assert set(logged[True]) == {"scenarios/solo_success", "scenarios/solo_best_success"}
    assert all(v in (0.0, 0.25, 0.5, 0.75, 1.0) for v in logged[True].values())
    assert logged[False] == {}


def test_promotion_with_track_starts_also_races_self_matches_from_the_track(line2):
    """`promotion.track_starts` adds self-matches from track starts of the stage's scenario and, with `scenarios`, of
    each other scenario of its mix; box self-matches of the other scenarios keep their seeds. A learner that wins its
    duels but races 0.60 from the track where the best races 0.90 is not promoted."""
    spec = {"name": "1v1", "scenario": "1v1", "iterations": 1, "mix": {"solo": 0.25}, **COMMON}

    def envs(**promotion):
        stage = StageSpec.model_validate({**spec, "selfplay": {"promotion": promotion}})
        return self_match_envs(stage, RaceSetting(line2, CF2X, SimCfg()), device="cpu", seed=0)

    both = envs(scenarios=True)  # track_starts: on by default, as in the shipped recipe
    assert list(both) == ["solo", "track-1v1", "track-solo"]
    assert [both[k].drones_per_world for k in both] == [1, 2, 1]
    assert [both[k].cfg.episode.eval_starts for k in both] == ["box", "track", "track"]
    box_only = envs(scenarios=True, track_starts=False)
    assert both["solo"].generator.initial_seed() == box_only["solo"].generator.initial_seed()
    assert list(envs()) == ["track-1v1"]
    assert envs(track_starts=False) == {}
    cfg, win = PromotionCfg(max_success_drop=0.05), HeadToHead(64, 40, 20, 4, 0.98, 0.98)
    assert not should_promote(win, cfg, (0.97, 0.96), {"track-1v1": (0.60, 0.90)})
    assert should_promote(win, cfg, (0.97, 0.96), {"track-1v1": (0.88, 0.90)})
