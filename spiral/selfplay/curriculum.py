"""Run one curriculum stage: solo selection, or self-play against the pool, or PPO against a frozen opponent."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch

from spiral.config.stage import StageSpec
from spiral.core.checkpoint import CheckpointError, FrozenPolicy, load_checkpoint, load_policy
from spiral.core.errors import UsageError
from spiral.core.scenario import SCENARIO_DRONES
from spiral.core.seeds import stream_seed
from spiral.env.observations import other_drone_columns
from spiral.env.setting import RaceSetting
from spiral.selfplay.final import pick_final
from spiral.selfplay.matchmaking import Matchmaker
from spiral.selfplay.opponents import OpponentDraws, PoolOpponents, StageOpponents
from spiral.selfplay.pool import INITIAL_RATING, Pool
from spiral.selfplay.promotion import PromotionSelector
from spiral.train.runner import StageStart, StageTrainer, TrainResult
from spiral.train.selection import EvalScore

__all__ = ["StageSources", "published_opponents", "run_stage", "stage_opponents"]


@dataclass(frozen=True)
class StageSources:
    """Where a stage's policies come from, as files."""

    pool_dir: Path
    """The pool folder: in ``pool`` mode the opponents come from it and every promoted policy joins it."""
    init_checkpoint: Path | None = None
    """The checkpoint of the policy the stage starts from and its first best (multi-drone stages need one)."""
    opponent_checkpoint: Path | None = None
    """In ``frozen`` mode the checkpoint of the one opponent policy (the initial policy when None)."""


def run_stage(setting: RaceSetting, stage: StageSpec, run_dir: Path, *, sources: StageSources, device: str = "cpu",
              seed: int = 0, log: Callable[[str], None] = print, progress: bool = True) -> TrainResult:
    """Train ``stage`` from ``sources`` and return its result; ``run_dir/best.pt`` is its best policy.

    A multi-drone stage promotes its learner against its best (:class:`PromotionSelector`); in ``pool`` mode it
    races the pool, in ``frozen`` mode one policy, which leaves the pool alone.
    """
    run_dir = Path(run_dir)
    if stage.scenario == "solo":
        trainer = StageTrainer(setting, stage, run_dir, start=StageStart(sources.init_checkpoint), device=device,
                               seed=seed, log=log, progress=progress)
        return trainer.train()
    init_checkpoint = _multi_drone_init(stage, sources)
    best_path = _first_best(run_dir, init_checkpoint)
    pool = Pool(sources.pool_dir, log=log) if stage.selfplay.mode == "pool" else None
    opponents = stage_opponents(stage, pool, init_checkpoint, sources.opponent_checkpoint, device=device, seed=seed)
    selector = PromotionSelector(stage, setting, best_path=best_path, pool=pool, opponents=opponents, device=device,
                                 seed=seed, log=log)
    trainer = StageTrainer(setting, stage, run_dir, start=StageStart(init_checkpoint, opponents.worlds),
                           device=device, seed=seed, log=log, progress=progress)
    result = trainer.train(selector, interval=selector.interval)
    chosen = pick_final(stage, setting, run_dir, device=device, log=log)
    if chosen is None:
        return result
    return replace(result, best=EvalScore(chosen.score, float("-inf"), iteration=chosen.iteration))


def _multi_drone_init(stage: StageSpec, sources: StageSources) -> Path:
    """The checkpoint multi-drone ``stage`` starts from, once ``sources`` are known to suit its self-play mode."""
    if sources.init_checkpoint is None:
        raise UsageError(f"stage {stage.name!r}: a {stage.scenario} stage needs an earlier stage to start from")
    if sources.opponent_checkpoint is not None and stage.selfplay.mode != "frozen":
        raise UsageError(f"stage {stage.name!r}: an opponent checkpoint is for frozen opponents; pool mode races "
                         "the pool")
    return sources.init_checkpoint


def stage_opponents(stage: StageSpec, pool: Pool | None, init_checkpoint: Path, opponent_checkpoint: Path | None = None,
                    *, device: str = "cpu", seed: int = 0) -> StageOpponents:
    """The opponents ``stage`` trains against: ``pool``'s members in pool mode (a new pool first receives
    ``init_checkpoint``), else ``opponent_checkpoint``'s policy (``init_checkpoint``'s when None).

    Raises:
        ValueError: no policy of the stage's observation layout in the pool.
    """
    init_meta = load_checkpoint(init_checkpoint)["spiral"]
    generator = torch.Generator(device=device).manual_seed(stream_seed(seed, "matchmaking"))
    members, latest, best_rating = _opponent_policies(stage, pool, init_meta, init_checkpoint, opponent_checkpoint,
                                                      device=device)
    if not members:
        raise UsageError(f"stage {stage.name!r}: no usable policy in the pool {pool.root if pool else None}")
    matchmaker = Matchmaker(len(members), latest=latest, p_latest=stage.selfplay.p_latest,
                            mode=stage.selfplay.sampling, device=device)
    return StageOpponents(members, matchmaker, _world_opponents(stage, members, matchmaker, generator), best_rating,
                          device)


def published_opponents(stage: StageSpec, init_checkpoint: Path, scratch: Path, *, pool_dir: Path | None = None,
                        opponent_checkpoint: Path | None = None, device: str = "cpu", seed: int = 0) -> StageOpponents:
    """The opponents ``stage`` trains against in a pipeline, from published checkpoints, leaving them untouched: in
    pool mode a copy of ``pool_dir`` in ``scratch`` (a new pool there of the initial policy when None), in frozen
    mode ``opponent_checkpoint``'s policy (the initial policy's when None). For measuring a stage (the profile)."""
    pool = None
    if stage.selfplay.mode == "pool":
        if pool_dir is not None:
            shutil.copytree(pool_dir, scratch / "pool")
        pool = Pool(scratch / "pool", log=lambda _: None)
    return stage_opponents(stage, pool, init_checkpoint, opponent_checkpoint, device=device, seed=seed)


def _world_opponents(stage: StageSpec, members: list[FrozenPolicy], matchmaker: Matchmaker,
                     generator: torch.Generator) -> dict[str, PoolOpponents]:
    """The opponents of each part of the stage's training worlds that has opponent slots, drawing from ``members``
    through one matchmaker and one generator."""
    sp = stage.selfplay
    draws = OpponentDraws(p_self=sp.mirror_share, offset=sp.opponent_offset, blind=sp.opponent_blind,
                          unseen=other_drone_columns(stage.env.obs))
    return {
        part.scenario: PoolOpponents(members, matchmaker, world_count=part.worlds,
                                     per_world=SCENARIO_DRONES[part.scenario] - len(part.learner_slots),
                                     generator=generator, draws=draws)
        for part in stage.world_parts() if part.opponents
    }


def _first_best(run_dir: Path, init_checkpoint: Path) -> Path:
    """``run_dir/best.pt``: the stage's best so far, the initial policy until the learner is promoted."""
    best_path = run_dir / "best.pt"
    if not best_path.exists():
        run_dir.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(init_checkpoint, best_path)
        shutil.copyfile(init_checkpoint.with_suffix(".json"), best_path.with_suffix(".json"))
    return best_path


def _opponent_policies(stage: StageSpec, pool: Pool | None, init_meta: dict[str, Any], init_checkpoint: Path,
                       opponent_checkpoint: Path | None, *, device: str) -> tuple[list[FrozenPolicy], int, float]:
    """The opponents a multi-drone stage starts with (one list, shared by every scenario's opponents), which of them
    is the latest best, and its rating.

    ``init_meta`` is the initial policy's spiral metadata (its observation layout is the stage's). Pool mode: the
    pool's valid members of this observation layout (a new pool starts with the initial policy).
    Frozen mode: ``opponent_checkpoint``'s policy, else the initial policy's.
    """
    layout = init_meta["obs_layout"]
    if pool is None:
        frozen = load_policy(opponent_checkpoint or init_checkpoint, device=device)
        if frozen.obs_layout != layout:
            raise CheckpointError(f"{opponent_checkpoint}: observation layout {frozen.obs_layout} differs from this "
                                  "stage's")
        return [frozen], 0, INITIAL_RATING
    if not pool.members:
        pool.add(init_checkpoint, stage=stage.init_from or "init", iteration=0, evaluation={})
    policies = pool.load_policies(layout, device=device)
    ids = list(policies)
    if not ids:
        return [], 0, INITIAL_RATING
    latest = ids.index(pool.latest_best) if pool.latest_best in policies else len(ids) - 1
    return [policies[i] for i in ids], latest, pool.member(ids[latest]).rating

