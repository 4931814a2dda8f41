"""A multi-drone stage's final pick (``selection.final``): every policy the stage promoted races self-matches on
validation placements, in the stage's scenario and each scenario of its mix, from the start box and from track starts,
over several laps, and the one with the highest mean success becomes the stage's ``best.pt``.

Promotion weighs one-lap races of 64 placements as training goes; the policy it promoted last is not always the one
that races best over a longer race or off the box. The validation placements are a seed of their own, so that the
placements a pipeline reports on choose nothing.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from spiral.config.stage import FinalPickCfg, StageSpec
from spiral.core.checkpoint import copy_checkpoint, load_policy
from spiral.core.files import atomic_write_bytes
from spiral.core.policy import Policy
from spiral.env.race_env import RaceEnv
from spiral.env.racing import run_races
from spiral.env.setting import RaceSetting
from spiral.selfplay.promotion import PROMOTED_DIR, self_match_env

__all__ = ["FINAL_PICK_FILE", "Candidate", "pick_final", "rank_candidates", "validation_success"]

FINAL_PICK_FILE = "final_pick.json"
"""What the final pick raced and chose, beside the stage's ``best.pt``."""


@dataclass(frozen=True)
class Candidate:
    """A promoted policy and its validation success per race (``<starts>-<scenario>`` → share of drones home)."""

    path: Path
    iteration: int
    success: dict[str, float]

    @property
    def score(self) -> float:
        """Mean success over the races."""
        return sum(self.success.values()) / len(self.success)


def rank_candidates(candidates: list[Candidate]) -> Candidate:
    """The candidate with the highest score; among equal scores the later (higher iteration)."""
    return max(candidates, key=lambda c: (c.score, c.iteration))


def _validation_envs(stage: StageSpec, setting: RaceSetting, cfg: FinalPickCfg, *, device: str) -> dict[str, RaceEnv]:
    """One self-match env per scenario (the stage's, then its mix's) and start, racing ``cfg.laps`` laps from
    ``cfg.races`` placements of ``cfg.seed``."""
    laps = setting.with_laps(cfg.laps)  # the same setting (threads too), cfg.laps laps on every track
    return {f"{starts}-{scenario}": self_match_env(laps, stage.env.with_eval_starts(starts), scenario,
                                                   races=cfg.races, device=device, seed=cfg.seed)
            for scenario in [stage.scenario, *sorted(stage.mix)] for starts in cfg.starts}


def validation_success(envs: dict[str, RaceEnv], placements: dict[str, torch.Tensor], policy: Policy
                       ) -> dict[str, float]:
    """Share of drones home in each self-match of ``envs`` (key → env) raced by ``policy``, every env's generator set
    to its state in ``placements`` first: every candidate races the same placements, a paired comparison."""
    success = {}
    for key, env in envs.items():
        env.generator.set_state(placements[key])
        success[key] = float(run_races(env, policy).finished.float().mean())
    return success


def _candidates(run_dir: Path) -> list[tuple[Path, int]]:
    """The policies the stage promoted (``promoted/best-<iteration>.pt``), oldest first."""
    paths = sorted((run_dir / PROMOTED_DIR).glob("best-*.pt"))
    return [(p, int(p.stem.split("-")[1])) for p in paths]


def pick_final(stage: StageSpec, setting: RaceSetting, run_dir: Path, *, device: str = "cpu",
               log: Callable[[str], None] = print) -> Candidate | None:
    """Race the stage's latest promoted policies as ``stage.selection.final`` says and make the best one
    ``run_dir/best.pt`` (recorded in ``final_pick.json``). None when the stage has no final pick or promoted fewer
    than two policies."""
    cfg, found = stage.selection.final, _candidates(Path(run_dir))
    if cfg is None or len(found) < 2:
        return None
    found = found[-cfg.candidates:]
    envs = _validation_envs(stage, setting, cfg, device=device)
    placements = {key: env.generator.get_state() for key, env in envs.items()}
    raced = [Candidate(path, iteration, validation_success(envs, placements, load_policy(path, device=device)))
             for path, iteration in found]
    chosen = rank_candidates(raced)
    copy_checkpoint(chosen.path, Path(run_dir) / "best.pt")
    record = {"laps": cfg.laps, "races": cfg.races, "seed": cfg.seed, "chosen": chosen.iteration,
              "candidates": [{"iteration": c.iteration, "score": c.score, "success": c.success} for c in raced]}
    atomic_write_bytes(Path(run_dir) / FINAL_PICK_FILE, json.dumps(record, indent=2).encode())
    log(f"final pick: the policy promoted at iteration {chosen.iteration} (mean success {chosen.score:.3f} over "
        f"{len(envs)} self-matches of {cfg.races} races of {cfg.laps} laps on validation placements; {len(raced)} "
        "candidates)")
    return chosen
