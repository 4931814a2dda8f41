"""Head-to-head races against the current best, the promotion rule and Elo ratings."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path

from spiral.config.env import EnvCfg
from spiral.config.stage import PromotionCfg, StageSpec
from spiral.core.checkpoint import FrozenPolicy, copy_checkpoint, load_policy
from spiral.core.outcome import race_winner
from spiral.core.policy import Policy
from spiral.core.scenario import SCENARIO_DRONES, Scenario
from spiral.core.seeds import stream_seed
from spiral.env.race_env import RaceEnv
from spiral.env.racing import run_races
from spiral.env.setting import RaceSetting
from spiral.selfplay.opponents import StageOpponents
from spiral.selfplay.pool import Pool
from spiral.train.runner import StageTrainer
from spiral.train.selection import paired_scores

__all__ = ["ELO_K", "PROMOTED_DIR", "HeadToHead", "PromotionSelector", "elo_update", "head_to_head", "keep_promoted",
           "self_match_env", "self_match_envs", "should_promote"]

PROMOTED_DIR = "promoted"
"""Folder beside a stage's ``best.pt`` with a copy of every policy the stage promoted."""
ELO_K = 16.0
"""Elo K-factor of the ratings in ``pool.json``, applied once per promotion check (score: (wins + draws / 2) /
races)."""


@dataclass
class HeadToHead:
    """Outcome of ``races`` races of team A (the challenger) against team B."""

    races: int
    wins: int
    losses: int
    draws: int
    a_success: float
    b_success: float

    @property
    def win_rate(self) -> float:
        """Races won by team A over all races (draws count as not won)."""
        return self.wins / self.races if self.races else 0.0

    @property
    def score(self) -> float:
        """Match score of team A: wins plus half the draws, over all races."""
        return (self.wins + 0.5 * self.draws) / self.races if self.races else 0.5


def head_to_head(env: RaceEnv, challenger: Policy, holder: Policy) -> HeadToHead:
    """Race ``challenger`` (the env's learner slots) against ``holder`` (its opponent slots) once per world."""
    env.set_opponent_policy(holder)
    res = run_races(env, challenger)
    env.set_opponent_policy(None)
    winners = race_winner(res.finished, res.lap_time, [env.learner_slots, env.opponent_slots])
    a = res.finished[:, env.learner_slots].float().mean()
    b = res.finished[:, env.opponent_slots].float().mean()
    return HeadToHead(races=len(winners), wins=int((winners == 0).sum()), losses=int((winners == 1).sum()),
                      draws=int((winners == -1).sum()), a_success=float(a), b_success=float(b))


def should_promote(result: HeadToHead, cfg: PromotionCfg, self_match: tuple[float, float] | None = None,
                   scenarios: Mapping[str, tuple[float, float]] | None = None) -> bool:
    """Whether the learner (team A of ``result``) replaces the best.

    Faster: win rate at least ``min_win_rate`` with success not below the best's by more than ``max_success_drop``
    (and, given ``self_match = (learner, best)`` self-match success ratios and ``cfg.self_match``, self-match success
    not below the best's by more than that either). Safer (with ``cfg.self_match`` and ``cfg.self_match_gain``):
    self-match success at least ``self_match_gain`` above the best's and head-to-head success not below the best's
    by more than ``max_success_drop``. Either way, given ``scenarios`` (key → (learner, best) success ratios in the
    other self-matches of :func:`self_match_envs`), none of them more than ``max_success_drop`` below the best's.
    """
    if any(own < best - cfg.max_success_drop for own, best in (scenarios or {}).values()):
        return False
    as_safe = result.a_success >= result.b_success - cfg.max_success_drop
    faster = as_safe and result.win_rate >= cfg.min_win_rate
    if not cfg.self_match or self_match is None:
        return faster
    own, best = self_match
    safer = cfg.self_match_gain is not None and as_safe and own >= best + cfg.self_match_gain
    return (faster and own >= best - cfg.max_success_drop) or safer


def self_match_envs(stage: StageSpec, setting: RaceSetting, *, device: str, seed: int) -> dict[str, RaceEnv]:
    """The self-match races a promotion also weighs, by key: each other scenario of the stage's mix from the start
    box (``promotion.scenarios``; key: the scenario) and, with ``promotion.track_starts``, the stage's scenario and
    those from track starts (key: ``track-<scenario>``). Each has ``promotion.races`` worlds and a seed of its own."""
    cfg = stage.selfplay.promotion
    runs = [(scenario, "box") for scenario in sorted(stage.mix)] if cfg.scenarios else []
    if cfg.track_starts:
        runs += [(scenario, "track") for scenario in [stage.scenario, *(sorted(stage.mix) if cfg.scenarios else [])]]
    return {scenario if starts == "box" else f"track-{scenario}": self_match_env(
                setting, stage.env.with_eval_starts(starts), scenario, races=cfg.races, device=device,
                seed=stream_seed(seed, "scenarios", i))
            for i, (scenario, starts) in enumerate(runs)}


def self_match_env(setting: RaceSetting, env_cfg: EnvCfg, scenario: Scenario, *, races: int, device: str,
                   seed: int) -> RaceEnv:
    """An evaluation env of ``races`` worlds of ``scenario`` in which every drone is a learner drone (a
    self-match of whatever policy races it)."""
    drones = SCENARIO_DRONES[scenario]
    return RaceEnv(setting, env_cfg, world_count=races, drones_per_world=drones, learner_slots=list(range(drones)),
                   device=device, seed=seed, training=False)


def keep_promoted(best: Path, iteration: int) -> Path:
    """Copy the just promoted ``best`` (with its metadata) into ``promoted/`` beside it, named for ``iteration``: the
    stage's candidates for its final pick (:mod:`spiral.selfplay.final`)."""
    folder = best.parent / PROMOTED_DIR
    folder.mkdir(exist_ok=True)
    copy = folder / f"best-{iteration:05d}.pt"
    copy_checkpoint(best, copy)
    return copy


def elo_update(rating_a: float, rating_b: float, score_a: float, k: float) -> tuple[float, float]:
    """Elo update for a match in which A scored ``score_a`` in [0, 1] against B."""
    expected = 1.0 / (1.0 + 10.0 ** ((rating_b - rating_a) / 400.0))
    delta = k * (score_a - expected)
    return rating_a + delta, rating_b - delta


class PromotionSelector:
    """Stage selection for multi-drone stages: promote the learner when it beats the current best.

    In ``pool`` mode a promoted learner also joins the pool and the stage's training ``opponents``; in ``frozen``
    mode only the stage's best changes. The best starts with the rating of the opponents' latest best.
    """

    def __init__(self, stage: StageSpec, setting: RaceSetting, *, best_path: Path, pool: Pool | None,
                 opponents: StageOpponents, device: str, seed: int, log: Callable[[str], None] = print) -> None:
        self.cfg, self.stage, self.pool, self.device = stage.selfplay.promotion, stage, pool, device
        self.best_path, self.best_rating, self.opponents, self.log = best_path, opponents.best_rating, opponents, log
        self.best: FrozenPolicy = load_policy(best_path, device=device)
        d = stage.drones_per_world
        self.env = RaceEnv(setting, stage.env, world_count=self.cfg.races, drones_per_world=d,
                           learner_slots=stage.learner_slots(), device=device, seed=stream_seed(seed, "promotion"),
                           training=False)
        self.interval = self.cfg.interval
        self.other_self_matches = self_match_envs(stage, setting, device=device, seed=seed)

    def __call__(self, trainer: StageTrainer, it: int) -> dict[str, float]:
        """Race the learner against the best and in a self-match; promote it when the rule holds."""
        own, best_own = trainer.selection.evaluate_pair(it, self.best)
        learner = trainer.selection.candidate_policy()
        result = head_to_head(self.env, learner, self.best)
        scenarios = {key: tuple(score.success for score in paired_scores(env, learner, self.best))
                   for key, env in self.other_self_matches.items()}
        trainer.runner.alg.train_mode()
        learner_rating, best_rating = elo_update(self.best_rating, self.best_rating, result.score, ELO_K)
        row = {"h2h/win_rate": result.win_rate, "h2h/draws": result.draws / max(result.races, 1),
               "h2h/learner_success": result.a_success, "h2h/best_success": result.b_success,
               "h2h/promoted": 0.0, "eval/success": own.success,
               "eval/lap_time": own.lap_time if own.lap_time is not None else float("nan"),
               "eval/best_success": best_own.success}
        for key, (mine, theirs) in scenarios.items():
            row[f"scenarios/{key}_success"], row[f"scenarios/{key}_best_success"] = mine, theirs
        if should_promote(result, self.cfg, (own.success, best_own.success), scenarios):
            path = trainer.save_best(it)
            keep_promoted(path, it)
            if self.pool is not None:
                if self.pool.latest_best is not None:
                    self.pool.member(self.pool.latest_best).rating = best_rating
                self.pool.add(path, stage=self.stage.name, iteration=it, evaluation=asdict(result),
                              rating=learner_rating)
            self.best, self.best_rating = load_policy(path, device=self.device), learner_rating
            if self.pool is not None:
                self.opponents.add(path)
            self.log(f"iteration {it}: promoted (win rate {result.win_rate:.2f}, success "
                     f"{result.a_success:.2f} vs {result.b_success:.2f}, self-match {own.success:.2f})")
            row["h2h/promoted"] = 1.0
        return row
