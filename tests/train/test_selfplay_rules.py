"""Self-play rules on scripted numbers: matchmaking frequencies, promotion, Elo, pool integrity."""

from __future__ import annotations

import json

import pytest
import torch
from pydantic import ValidationError

from spiral.config import PromotionCfg, SelfPlayCfg, StageSpec
from spiral.selfplay import HeadToHead, Matchmaker, Pool, elo_update, should_promote
from spiral.train.selection import paired_scores
from tests.env.test_race_env import make_env, waypoint_policy


def test_matchmaking_draws_the_latest_best_with_probability_p():
    """Draw the latest member about p of the time and the others uniformly otherwise."""
    mm = Matchmaker(4, latest=3, p_latest=0.5, mode="uniform")
    draws = mm.draw(40_000, torch.Generator().manual_seed(0))
    freq = torch.bincount(draws, minlength=4).float() / draws.numel()
    assert freq[3].item() == pytest.approx(0.5 + 0.5 / 4, abs=0.01)
    assert freq[:3].tolist() == pytest.approx([0.125] * 3, abs=0.01)


def test_matchmaking_keeps_a_share_for_the_pools_first_member():
    """Draw the first member about q of the time on top of its share of the other draws, and refuse p + q > 1."""
    mm = Matchmaker(4, latest=3, p_latest=0.3, p_first=0.2, mode="uniform")
    draws = mm.draw(40_000, torch.Generator().manual_seed(2))
    freq = torch.bincount(draws, minlength=4).float() / draws.numel()
    assert freq.tolist() == pytest.approx([0.2 + 0.5 / 4, 0.125, 0.125, 0.3 + 0.5 / 4], abs=0.01)
    with pytest.raises(ValueError, match="exceeds 1"):
        Matchmaker(2, latest=1, p_latest=0.7, p_first=0.4)
    with pytest.raises(ValidationError, match="p_first"):
        SelfPlayCfg(p_latest=0.7, p_first=0.4)


def test_matchmaking_without_a_first_member_share_draws_as_before():
    """With p_first = 0 a seed gives the draws it gave before p_first existed (a uniform number for the latest
    best, then a pool sample, per world), so earlier runs reproduce."""
    g = torch.Generator().manual_seed(3)
    u = torch.rand(1000, generator=g)
    sampled = torch.multinomial(torch.full((5,), 0.2), 1000, replacement=True, generator=g)
    before = torch.where(u < 0.5, torch.full_like(sampled, 4), sampled)
    now = Matchmaker(5, latest=4, p_latest=0.5, mode="uniform").draw(1000, torch.Generator().manual_seed(3))
    assert torch.equal(now, before)  # exact: integer draws


def test_prioritized_matchmaking_favours_members_the_learner_loses_to():
    """Weight members by the learner's smoothed loss rate against them."""
    mm = Matchmaker(2, latest=0, p_latest=0.0, mode="prioritized")
    mm.record(torch.tensor([0] * 8 + [1] * 8), torch.tensor([True] * 8 + [False] * 8))
    assert mm.weights().tolist() == pytest.approx([0.1, 0.9])
    draws = mm.draw(20_000, torch.Generator().manual_seed(1))
    assert (draws == 1).float().mean().item() == pytest.approx(0.9, abs=0.01)


def test_promotion_rule_on_scripted_results():
    """Promote on win rate ≥ 0.55 over ≥ 64 races unless success drops by more than 0.02."""
    cfg = PromotionCfg()
    assert should_promote(HeadToHead(64, 36, 20, 8, 0.95, 0.96), cfg)
    assert not should_promote(HeadToHead(64, 35, 20, 9, 0.95, 0.96), cfg)  # 0.547 < 0.55
    assert not should_promote(HeadToHead(64, 40, 20, 4, 0.90, 0.96), cfg)  # success drop 0.06
    assert not should_promote(HeadToHead(32, 30, 2, 0, 1.0, 1.0), cfg)  # too few races


def test_promotion_also_needs_a_self_match_no_worse_than_the_best():
    """Refuse a winner whose self-match success is more than 0.02 below the best's, unless the check is off."""
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


def test_a_safer_learner_that_loses_the_duel_clearly_can_be_refused():
    """With safer_min_win_rate a safer learner must also win that share of the duel (draws are not wins)."""
    cfg = PromotionCfg(safer_min_win_rate=0.45)
    assert not should_promote(HeadToHead(64, 5, 40, 19, 0.72, 0.72), cfg, (0.84, 0.78))  # wins 0.08
    assert not should_promote(HeadToHead(64, 28, 30, 6, 0.72, 0.72), cfg, (0.84, 0.78))  # wins 0.44
    assert should_promote(HeadToHead(64, 29, 33, 2, 0.72, 0.72), cfg, (0.84, 0.78))  # wins 0.45
    assert should_promote(HeadToHead(64, 40, 20, 4, 0.95, 0.96), cfg, (0.80, 0.81))  # faster: rule unchanged


def test_frozen_opponents_refuse_mirror_self_play():
    """PPO without self-play never races the learner itself: p_self > 0 with frozen opponents is an error."""
    with pytest.raises(ValidationError, match="p_self"):
        SelfPlayCfg(mode="frozen", p_self=0.5)
    assert SelfPlayCfg(mode="pool", p_self=0.5).p_self == pytest.approx(0.5)


def test_only_frozen_opponents_name_the_stage_they_come_from():
    """opponent_from picks the frozen opponent; in pool mode (opponents are the pool) it is an error."""
    assert SelfPlayCfg(mode="frozen", opponent_from="solo").opponent_from == "solo"
    assert SelfPlayCfg(mode="frozen").opponent_from is None
    with pytest.raises(ValidationError, match="opponent_from"):
        SelfPlayCfg(mode="pool", opponent_from="solo")


def test_opponent_offsets_apply_to_both_branches_and_must_lie_in_the_action_range():
    """Offsets apply to pool and frozen opponents alike; a negative or beyond-action offset names the field."""
    assert SelfPlayCfg(mode="frozen", opponent_offset=0.1).opponent_offset == pytest.approx(0.1)
    assert SelfPlayCfg().opponent_offset == pytest.approx(0.0)
    for bad in (-0.1, 1.5):
        with pytest.raises(ValidationError, match="opponent_offset"):
            SelfPlayCfg(opponent_offset=bad)


def test_elo_update_is_zero_sum_and_follows_the_expected_score():
    """Move equal ratings by K·(S − ½) and keep the sum."""
    a, b = elo_update(1000.0, 1000.0, 1.0, 16.0)
    assert (a, b) == pytest.approx((1008.0, 992.0))
    a, b = elo_update(1200.0, 1000.0, 0.5, 16.0)
    assert a + b == pytest.approx(2200.0) and a < 1200.0


def test_pool_skips_a_member_whose_checksum_fails(tmp_path):
    """Report and skip a corrupted member instead of failing."""
    pool = Pool(tmp_path)
    pool.members = []
    (tmp_path / "pool.json").write_text(json.dumps({"latest_best": "x", "members": [
        {"id": "x", "file": "x.pt", "stage": "solo", "iteration": 0, "sha256": "00"}]}))
    (tmp_path / "x.pt").write_bytes(b"garbage")
    logs: list[str] = []
    assert Pool(tmp_path, log=logs.append).load_policies({"obs_dim": 1}) == {}
    assert "pool member x skipped" in logs[0]


def test_opponent_blind_is_a_probability_and_off_by_default():
    assert SelfPlayCfg().opponent_blind == pytest.approx(0.0)
    assert SelfPlayCfg(opponent_blind=0.3).opponent_blind == pytest.approx(0.3)
    for bad in (-0.1, 1.5):
        with pytest.raises(ValidationError, match="opponent_blind"):
            SelfPlayCfg(opponent_blind=bad)


def test_opponent_pace_lies_in_zero_to_one_and_needs_relative_targets():
    """A pace below 0 or at 1 (an opponent that stops) names the field; absolute action targets refuse a pace."""
    assert SelfPlayCfg(opponent_pace=0.3).opponent_pace == pytest.approx(0.3)
    assert SelfPlayCfg().opponent_pace == pytest.approx(0.0)
    for bad in (-0.1, 1.0):
        with pytest.raises(ValidationError, match="opponent_pace"):
            SelfPlayCfg(opponent_pace=bad)
    spec = {"name": "1v1", "scenario": "1v1", "iterations": 1, "selfplay": {"opponent_pace": 0.3}}
    assert StageSpec.model_validate(spec).selfplay.opponent_pace == pytest.approx(0.3)
    with pytest.raises(ValidationError, match=r"selfplay\.opponent_pace"):
        StageSpec.model_validate({**spec, "env": {"action": {"mode": "absolute"}}})


def test_a_self_match_pair_scores_each_policy_on_its_own_races(oval2):
    """The promotion's format check races two policies from the same placements: a scripted lap finishes every race
    and a drone that dives into the ground none, in either order (the first score is not the second race's)."""
    env = make_env(oval2, worlds=2, auto_reset=False)
    lap, dive = waypoint_policy(env), (lambda obs: torch.tensor([[0.0, 0.0, -1.0, 0.0]]).expand(2, 4))
    assert tuple(score.success for score in paired_scores(env, lap, dive)) == pytest.approx((1.0, 0.0))
    assert tuple(score.success for score in paired_scores(env, dive, lap)) == pytest.approx((0.0, 1.0))
