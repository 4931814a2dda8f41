"""The random streams of a training stage and the seed each derives from the stage's seed, in one table."""

from __future__ import annotations

from typing import Literal

__all__ = ["MIX_PART_STRIDE", "SEED_OFFSETS", "Stream", "stream_seed"]

Stream = Literal["training", "selection", "promotion", "scenarios", "matchmaking"]

SEED_OFFSETS: dict[Stream, int] = {
    "training": 0,
    "selection": 10_000,
    "promotion": 20_000,
    "scenarios": 30_000,
    "matchmaking": 30_000,
}
"""Offset of each stream from the stage's seed:

- ``training``: the training env's starts, opponents' offsets and exploration (process rank ``r`` of a distributed
  stage adds ``r``: :mod:`spiral.train.distributed`);
- ``selection``: the races that select the stage's best (:mod:`spiral.train.runner`);
- ``promotion``: promotion's head-to-head races (:mod:`spiral.selfplay.promotion`);
- ``scenarios``: promotion's other self-matches (the other scenarios of the stage's mix, then those from track starts:
  :func:`spiral.selfplay.promotion.self_match_envs`), the ``i``-th at offset + ``i``;
- ``matchmaking``: the generator that draws each opponent slot's pool member (:mod:`spiral.selfplay.curriculum`).

``scenarios`` and ``matchmaking`` share a value but feed different generators (race placements, opponent draws)."""

MIX_PART_STRIDE = 1_000
"""Seed step between the parts of a mixed env: part ``k`` races with seed + ``k`` × stride."""


def stream_seed(seed: int, stream: Stream, index: int = 0) -> int:
    """The seed of ``stream`` (its ``index``-th member) for a stage seeded ``seed``."""
    return seed + SEED_OFFSETS[stream] + index
