"""A stage's training checkpoints: what they hold (rsl-rl's state, the moving average, spiral's metadata), where
they go, and the newest valid one a stage resumes from."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from rsl_rl.algorithms import PPO

from spiral.config.stage import StageSpec
from spiral.core.checkpoint import CheckpointError, load_checkpoint, newest_valid_checkpoint, save_checkpoint
from spiral.env.observations import HISTORY_FIELDS, ObservationBuilder
from spiral.env.setting import RaceSetting
from spiral.train.averaging import PolicyAverage
from spiral.train.selection import EvalScore

__all__ = ["AVERAGE_KEY", "StageCheckpoints", "stage_meta"]

AVERAGE_KEY = "average_actor_state_dict"
"""Checkpoint key of the moving average of the actor's weights (``selection.average``)."""


def stage_meta(stage: StageSpec, setting: RaceSetting, *, seed: int, obs_builder: ObservationBuilder) -> dict[str, Any]:
    """A stage's provenance, stored in every checkpoint: the observation layout (compared on load), where each
    observation term sits (``obs_slices``, ``obs_history_fields``) and the settings it trained with."""
    return {
        "stage": stage.name,
        "scenario": stage.scenario,
        "track": setting.track.name,
        "seed": seed,
        "obs_layout": obs_builder.layout(),
        "obs_slices": {name: list(span) for name, span in obs_builder.slices().items()},
        "obs_history_fields": {name: list(span) for name, span in HISTORY_FIELDS.items()},
        "airframe": setting.airframe.model_dump(),
        "sim": setting.sim.model_dump(),
        "ppo": stage.ppo.model_dump(),
        "env": stage.env.model_dump(),
    }


class StageCheckpoints:
    """Saves ``run_dir/ckpt/model_<it>.pt`` and ``run_dir/best.pt`` with ``meta`` (:func:`stage_meta`) and loads
    them back."""

    def __init__(self, run_dir: Path, alg: PPO, meta: dict[str, Any], *, device: str,
                 log: Callable[[str], None]) -> None:
        self.run_dir, self.alg, self.meta, self.device, self.log = run_dir, alg, meta, device, log

    @property
    def ckpt_dir(self) -> Path:
        """Folder of the periodic checkpoints."""
        return self.run_dir / "ckpt"

    def periodic(self, iteration: int) -> Path:
        """Path of the periodic checkpoint of ``iteration``."""
        return self.ckpt_dir / f"model_{iteration}.pt"

    def save(self, path: Path, iteration: int, best: EvalScore, score: EvalScore | None = None, *,
             average: PolicyAverage | None = None, candidate: bool = False) -> None:
        """A training checkpoint; with ``candidate`` its actor is the policy selection raced (the average, if any)."""
        state = self.alg.save()
        state["iter"] = iteration
        state["infos"] = None
        if average is not None:
            state[AVERAGE_KEY] = average.state_dict()
            if candidate:
                state["actor_state_dict"] = average.state_dict()
        meta = {"iteration": iteration, **self.meta, "best": best.to_json()}
        if score is not None:
            meta["eval"] = score.to_json()
        save_checkpoint(path, state, meta)

    def newest(self) -> tuple[Path, dict[str, Any]] | None:
        """The newest valid periodic checkpoint and its data (broken newer ones are reported), or None."""
        path = newest_valid_checkpoint(self.ckpt_dir, warn=lambda m: self.log(f"warning: {m}"))
        return None if path is None else (path, self.load(path))

    def load(self, path: Path) -> dict[str, Any]:
        """A checkpoint's data, refused when its observation layout differs from this stage's."""
        data = load_checkpoint(path, map_location=self.device)
        stored = data["spiral"]["obs_layout"]
        if stored != self.meta["obs_layout"]:
            raise CheckpointError(f"{path}: observation layout {stored} differs from this stage's")
        return data
