"""Self-play: the opponent pool, matchmaking, promotion and the curriculum's stages."""

from __future__ import annotations

from spiral.selfplay.curriculum import StageSources, run_stage
from spiral.selfplay.matchmaking import Matchmaker
from spiral.selfplay.opponents import OpponentDraws, PoolOpponents
from spiral.selfplay.pool import INITIAL_RATING, Pool, PoolMember
from spiral.selfplay.promotion import HeadToHead, PromotionSelector, elo_update, head_to_head, should_promote

__all__ = [
    "INITIAL_RATING",
    "HeadToHead",
    "Matchmaker",
    "OpponentDraws",
    "Pool",
    "PoolMember",
    "PoolOpponents",
    "PromotionSelector",
    "StageSources",
    "elo_update",
    "head_to_head",
    "run_stage",
    "should_promote",
]
