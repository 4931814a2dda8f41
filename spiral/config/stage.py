"""Stage spec: one step of the curriculum (solo, 1v1, 2v2) with its PPO, environment and budget."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from pydantic import Field, model_validator

from spiral.config.base import PosInt, StrictModel
from spiral.config.env import EnvCfg
from spiral.config.ppo import PPOCfg
from spiral.core.scenario import SCENARIO_DRONES, Scenario, learner_slots

__all__ = ["FinalPickCfg", "PromotionCfg", "SelectionCfg", "SelfPlayCfg", "StageSpec", "WorldPart"]


@dataclass(frozen=True)
class WorldPart:
    """A group of a stage's training worlds that race alike."""

    scenario: str
    worlds: int
    learner_slots: list[int]
    opponents: bool
    """Whether the other slots are opponents (pool or frozen policies); otherwise the scenario has none."""


class FinalPickCfg(StrictModel):
    """After a multi-drone stage's training, every policy it promoted races self-matches on validation placements
    and the one racing best becomes the stage's best (not in the paper)."""

    laps: PosInt = Field(default=3, description="Laps of each race")
    races: PosInt = Field(default=256, description="Races per scenario and start (validation placements)")
    seed: int = Field(default=2, description="Seed of the validation placements: none the pipeline reports on")
    starts: list[Literal["box", "track"]] = Field(default=["box", "track"], min_length=1,
                                                  description="Where the races start")
    candidates: PosInt = Field(default=4, description="How many of the latest promoted policies race (each costs "
                               "a self-match per scenario and start)")


class SelectionCfg(StrictModel):
    """Periodic evaluation during training that keeps the best checkpoint (success first, then lap time)."""

    interval: PosInt = Field(default=25, description="Iterations between evaluations (solo stages; a multi-drone "
                             "stage evaluates at each promotion)")
    races: PosInt = Field(default=64, description="Seeded races from the start box per evaluation (solo stages; a "
                          "multi-drone stage races promotion.races)")
    average: float = Field(
        default=0.98, ge=0, lt=1,
        description="Decay d of the moving average of the policy's weights (θ̄ ← d·θ̄ + (1 − d)·θ after every PPO "
        "update) that selection and promotion race and best.pt keeps; 0: the current policy",
    )
    final: FinalPickCfg | None = Field(
        default_factory=FinalPickCfg,
        description="Multi-drone stages: after training, the policy the stage promoted that races best in "
        "self-matches of its scenario and each of its mix's, from `starts`, over `laps` laps, on validation "
        "placements, becomes the stage's best (highest mean success; ties: the later); null: the last promoted "
        "(solo stages: unused)",
    )


class PromotionCfg(StrictModel):
    """When the learner replaces the current best: head-to-head races against it every ``interval`` iterations."""

    interval: PosInt = Field(default=25, description="Iterations between head-to-head evaluations")
    races: PosInt = Field(default=64, description="Seeded races per evaluation (M): the head to head's, the "
                          "self-match's and each of `scenarios` and `track_starts`")
    min_win_rate: float = Field(default=0.55, ge=0, le=1, description="Win rate needed over the current best")
    max_success_drop: float = Field(default=0.05, ge=0, le=1, description="Largest success-ratio drop allowed")
    self_match: bool = Field(
        default=True,
        description="Also race the learner in a self-match (every drone runs it): its success may not be more than "
        "max_success_drop below the best's, and a safer learner can be promoted (self_match_gain)",
    )
    self_match_gain: float | None = Field(
        default=0.05, ge=0, le=1,
        description="Promote as well a learner whose self-match success beats the best's by at least this much "
        "while its head-to-head success is not below the best's by more than max_success_drop; null: never",
    )
    scenarios: bool = Field(
        default=False,
        description="Also race the learner and the best in a self-match of each other scenario of the stage's "
        "`mix` (`races` races each, the same placements for both): a learner whose success in one of them is more "
        "than max_success_drop below the best's is not promoted, so that the stage's best races every scenario it "
        "trains",
    )
    track_starts: bool = Field(
        default=True,
        description="Also race the learner and the best in self-matches from track starts (every drone at a random "
        "point between two gates; the stage's scenario and, with `scenarios`, each other scenario of its `mix`; "
        "`races` races each, the same placements for both): a learner more than max_success_drop below the best's in "
        "one of them is not promoted, so that the stage's best still races from anywhere on the track (not in the "
        "paper)",
    )


class SelfPlayCfg(StrictModel):
    """Where opponents come from in multi-drone stages.

    ``pool``: SPIRAL — the pool of past bests, promoted policies join it. ``frozen``: PPO without self-play —
    one fixed policy (``opponent_from``'s best, else the stage's initial policy), never updated, nothing added
    to the pool.
    """

    mode: Literal["pool", "frozen"] = Field(default="pool")
    opponent_from: str | None = Field(
        default=None, pattern=r"^[A-Za-z0-9_.-]+$",
        description="Frozen mode: the earlier stage whose best policy every opponent runs (in full.yaml the solo "
        "stage); the stage's initial policy when absent",
    )
    p_self: float = Field(
        default=0.6, ge=0, le=1,
        description="Probability that a world's opponents are the learner's current policy (mirror self-play, "
        "pool mode only: frozen mode ignores the default and refuses a value above 0); the rest are drawn from the "
        "pool",
    )
    opponent_offset: float = Field(
        default=0.1, ge=0, le=1,
        description="Largest constant offset added to an opponent's actions for a whole episode, drawn per world "
        "uniformly in [-x, x] per axis of the position target (action units): opponents fly other lines than "
        "their policy's own (robustness to strangers); 0: off",
    )
    opponent_blind: float = Field(
        default=0.3, ge=0, le=1,
        description="Probability that a world's opponents fly blind for an episode: their observation shows no other "
        "drone, so they race their own line and never make room (mirror copies and pool members alike), and the "
        "learner has to follow or pass drones that ignore it; 0: off",
    )
    p_latest: float = Field(default=0.0, ge=0, le=1, description="Probability of racing the latest best (the "
                            "paper: 1)")
    sampling: Literal["uniform", "prioritized"] = Field(default="uniform", description="Other draws")
    promotion: PromotionCfg = Field(default_factory=PromotionCfg)

    @model_validator(mode="after")
    def _mirror_needs_pool(self) -> SelfPlayCfg:
        if self.mode == "frozen" and "p_self" in self.model_fields_set and self.p_self > 0:
            raise ValueError("p_self: frozen opponents (PPO without self-play) cannot race the learner itself")
        if self.mode == "pool" and self.opponent_from is not None:
            raise ValueError("opponent_from: only frozen opponents come from one stage; pool opponents are the pool")
        return self

    @property
    def mirror_share(self) -> float:
        """Share of worlds whose opponents are the learner itself: ``p_self`` in pool mode, none in frozen mode."""
        return self.p_self if self.mode == "pool" else 0.0


class StageSpec(StrictModel):
    """One training stage."""

    name: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$", description="Stage name")
    scenario: Scenario = Field(default="solo", description="What the stage's races are: solo, 1v1 or 2v2")
    worlds: PosInt = Field(default=1024, description="Parallel worlds (races) in training")
    mix: dict[Scenario, float] = Field(
        default_factory=dict,
        description="Shares of the worlds raced in other scenarios than `scenario`, e.g. {solo: 0.1, 1v1: 0.2}, so "
        "that one policy keeps racing every scenario; opponents as in the stage's own worlds; evaluation, selection "
        "and promotion race `scenario` only",
    )
    iterations: PosInt | None = Field(default=None, description="Budget in PPO iterations")
    env_steps: PosInt | None = Field(default=None, description="Budget in learner env steps (sets iterations)")
    seed: int | None = Field(default=None, ge=0, description="Seed of this stage; the pipeline's when absent")
    env: EnvCfg = Field(default_factory=EnvCfg)
    ppo: PPOCfg = Field(default_factory=PPOCfg)
    selection: SelectionCfg = Field(default_factory=SelectionCfg)
    selfplay: SelfPlayCfg = Field(default_factory=SelfPlayCfg)
    init_from: str | None = Field(
        default=None, description="Stage whose best policy this stage starts from, or a checkpoint file (`*.pt`, "
        "relative to the pipeline file: another pipeline's policy, fine-tuned here); the previous stage when absent"
    )

    @property
    def init_file(self) -> str | None:
        """``init_from`` when it names a checkpoint file rather than a stage."""
        return self.init_from if self.init_from is not None and self.init_from.endswith(".pt") else None
    publish_as: str | None = Field(
        default=None, pattern=r"^[A-Za-z0-9_.-]+\.pt$", description="Also publish the best as checkpoints/<p>/<name>"
    )

    @model_validator(mode="after")
    def _one_budget(self) -> StageSpec:
        if (self.iterations is None) == (self.env_steps is None):
            raise ValueError("iterations: give exactly one of iterations and env_steps")
        return self

    @model_validator(mode="after")
    def _solo_races_nobody(self) -> StageSpec:
        if self.scenario != "solo":
            return self
        if "selfplay" in self.model_fields_set:
            raise ValueError("selfplay: a solo stage races no opponents")
        reward = self.env.reward  # the defaults add nothing in a solo race; a weight given for one is a mistake
        bad = [name for name in ("win", "proximity") if name in reward.model_fields_set and getattr(reward, name) > 0]
        if bad:
            raise ValueError(f"env.reward.{bad[0]}: a solo stage has no other drone for it to act on")
        return self

    @model_validator(mode="after")
    def _promotion_counts_in_multi_drone_stages(self) -> StageSpec:
        if self.scenario == "solo":
            return self
        owned = {"interval": "selfplay.promotion.interval", "races": "selfplay.promotion.races"}
        for name in (n for n in owned if getattr(self.selection, n) != SelectionCfg.model_fields[n].default):
            raise ValueError(f"selection.{name}: a multi-drone stage evaluates at each promotion, its self-match "
                             f"with the head to head; set {owned[name]}")
        return self

    @property
    def eval_races(self) -> int:
        """Worlds of the stage's self-match evaluation: ``selection.races`` in a solo stage, ``promotion.races`` in a
        multi-drone stage (where it is raced at each promotion)."""
        return self.selection.races if self.scenario == "solo" else self.selfplay.promotion.races

    @model_validator(mode="after")
    def _mix_of_other_scenarios(self) -> StageSpec:
        if not self.mix:
            return self
        if self.scenario == "solo":
            raise ValueError("mix: a solo stage has no opponents to race other scenarios with")
        if self.scenario in self.mix:
            raise ValueError(f"mix.{self.scenario}: the stage's own scenario takes the worlds the others leave")
        bad = [k for k, share in self.mix.items() if not 0 < share < 1]
        if bad:
            raise ValueError(f"mix.{bad[0]}: a share must lie strictly between 0 and 1")
        if self.world_split()[self.scenario] < 1:
            raise ValueError(f"mix: the shares leave no world for the stage's own scenario ({self.scenario})")
        return self

    def world_split(self) -> dict[str, int]:
        """Training worlds of each scenario, the stage's own first; each mixed-in scenario gets at least one."""
        other = {scenario: max(1, round(share * self.worlds)) for scenario, share in self.mix.items()}
        return {self.scenario: self.worlds - sum(other.values()), **other}

    @property
    def drones_per_world(self) -> int:
        """Drones in each world of this stage's scenario."""
        return SCENARIO_DRONES[self.scenario]

    def world_parts(self) -> list[WorldPart]:
        """The training worlds by scenario (:meth:`world_split`), the stage's own scenario first."""
        return [WorldPart(scenario, worlds, learner_slots(scenario),
                          opponents=SCENARIO_DRONES[scenario] > len(learner_slots(scenario)))
                for scenario, worlds in self.world_split().items()]

    def learner_slots(self) -> list[int]:
        """Drone slots driven by the learner (team A) in the stage's own scenario; the other slots are opponents."""
        return learner_slots(self.scenario)

    def iteration_budget(self) -> int:
        """PPO iterations of this stage, from ``iterations`` or ``env_steps``."""
        if self.iterations is not None:
            return self.iterations
        learners = sum(part.worlds * len(part.learner_slots) for part in self.world_parts())
        per_iteration = learners * self.ppo.num_steps_per_env
        return max(1, -(-(self.env_steps or 0) // per_iteration))
