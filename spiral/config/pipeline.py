"""Pipeline spec (``kind: pipeline``): track, airframe, device, seed and the curriculum's stages."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, field_validator, model_validator

from spiral.config.airframe import AirframeSel
from spiral.config.base import NonNegInt, PosInt, StrictModel
from spiral.config.env import SeparationCfg
from spiral.config.generate import TrackGenCfg
from spiral.config.sim import SimCfg
from spiral.config.stage import StageSpec
from spiral.core.device import canonical_device

__all__ = ["PIPELINE_VERSION", "EvaluationCfg", "PipelineSpec", "RacingCfg", "ReportCfg", "TrackSetCfg",
           "UnseenTracksCfg"]

PIPELINE_VERSION = 2
"""Schema version of pipeline files; a file of another version is refused, naming what changed since it."""

_CHANGED_SINCE = {
    1: "stages' selfplay.promotion.formats is now selfplay.promotion.scenarios, and report.racing.planner_formats "
       "is now report.racing.planner_scenarios",
}
"""What changed in the schema after each older version."""


class EvaluationCfg(StrictModel):
    """Evaluation of every stage's best policy: seeded races from the start box, the same placements per method."""

    runs: PosInt = Field(default=50, description="Races per scenario")
    seed: int = Field(default=0, ge=0, description="Seed of the start placements")
    holdout_runs: int = Field(
        default=0, ge=0,
        description="Races of the report's held-out check: the learned methods' self-matches and head-to-head again "
        "from placements no setting was chosen on (0: off)",
    )
    holdout_seed: int = Field(default=1, ge=0, description="Seed of the held-out start placements")
    sides: Literal["a", "both"] = Field(
        default="both",
        description="Head-to-head races of the report: 'both' races every placement twice with the teams' start "
        "slots swapped, 'a' with the row method on team A's slots only",
    )

    @model_validator(mode="after")
    def _holdout_differs(self) -> EvaluationCfg:
        if self.holdout_runs and self.holdout_seed == self.seed:
            raise ValueError(f"holdout_seed: {self.holdout_seed} is the evaluation's own seed; held-out placements "
                             "need another")
        return self


class TrackSetCfg(StrictModel):
    """Generated tracks (:mod:`spiral.config.generate`, each one the point-mass reference laps within its time limit)
    that every stage trains, selects and promotes on, a track per world, instead of the pipeline's ``track``; and
    tracks of other generator seeds held out from all of that, written beside them for the evaluation."""

    generator: TrackGenCfg = Field(default_factory=TrackGenCfg, description="Ranges the tracks are drawn in")
    train_seeds: tuple[NonNegInt, PosInt] = Field(
        default=(0, 64), description="First generator seed and count of the training tracks")
    held_out_seeds: tuple[NonNegInt, PosInt] = Field(
        default=(10_000, 20), description="First generator seed and count of the held-out tracks")
    gate_counts: list[Annotated[int, Field(ge=3, le=16)]] = Field(
        default=[], description="Gate counts the circuits take in turn: generator seed s draws a circuit of "
        "gate_counts[s mod len] gates; empty: the generator's gates for every seed")

    @model_validator(mode="after")
    def _held_out_apart(self) -> TrackSetCfg:
        (a, n), (b, m) = self.train_seeds, self.held_out_seeds
        if a < b + m and b < a + n:
            raise ValueError(f"held_out_seeds: seeds {b}..{b + m - 1} overlap the training seeds {a}..{a + n - 1}")
        return self

    def seeds(self, which: Literal["train", "held_out"]) -> range:
        """The generator seeds of the training or the held-out tracks."""
        first, count = self.train_seeds if which == "train" else self.held_out_seeds
        return range(first, first + count)

    def generator_for(self, seed: int) -> TrackGenCfg:
        """The generator's ranges for ``seed``'s circuit: its gate count from ``gate_counts``."""
        if not self.gate_counts:
            return self.generator
        return self.generator.model_copy(update={"gates": self.gate_counts[seed % len(self.gate_counts)]})


class RacingCfg(StrictModel):
    """The report's racing section: each learned method's final policy in races of several laps from the held-out
    placements (``evaluation.holdout_runs`` of ``evaluation.holdout_seed``), from the start box and from points along
    the track, with the racing metrics; SPIRAL's duels against PPO without self-play and against SE-IBR."""

    laps: PosInt = Field(default=3, description="Laps of every race of the section")
    starts: list[Literal["box", "track"]] = Field(
        default=["box", "track"], min_length=1,
        description="Where the races start: the start box, and/or random points along the track (moving)",
    )
    planner_runs: int = Field(
        default=8, ge=0,
        description="Placements (the held-out seed's first) of SPIRAL's duels against SE-IBR, each raced from both "
        "sides (with report.se_ibr; the planner takes about 20 s of a CPU core per drone and 3-lap race); 0: none",
    )
    planner_scenarios: list[Literal["1v1", "2v2"]] = Field(
        default=["1v1"], min_length=1, description="Scenarios of SPIRAL's duels against SE-IBR",
    )


class UnseenTracksCfg(StrictModel):
    """The report's section on tracks no training step flew: each learned method's final policy in self-matches of
    every scenario on the held-out generated tracks (with ``training_tracks``), on the pipeline's ``track`` when it
    trained on generated ones, and on ``tracks``; its lap beside the point-mass reference of each track."""

    tracks: list[Path] = Field(default=[], description="Further track files, relative to the pipeline file")
    races: PosInt = Field(default=64, description="Races per track and scenario")
    laps: PosInt = Field(default=3, description="Laps of every race")
    seed: int = Field(default=1, ge=0, description="Seed of the start placements")
    head_to_head: bool = Field(
        default=True, description="Also race the first learned method (SPIRAL) against each other one in 1v1 and 2v2 "
        "duels on every track, from both sides")
    specialists: dict[str, Path] = Field(
        default={}, description="Policies trained on one track, raced beside the final policies on it: track name "
        "-> checkpoint file, relative to the pipeline file (e.g. circuit6: ../checkpoints/full/spiral.pt)")


class ReportCfg(StrictModel):
    """The pipeline's report (``runs/<name>/report/results.md`` and figures) and the steps that race for it."""

    enabled: bool = Field(default=True, description="Add the report and its races (`eval:report`, `report`)")
    se_ibr: bool = Field(default=False, description="Race the SE-IBR planner for the tables in steps of its own "
                         "(`eval:se-ibr`, `eval:se-ibr-vs-<stage>`; minutes each on a CPU)")
    cross_play: bool = Field(default=True, description="Cross-play win-rate matrices")
    separation: SeparationCfg | None = Field(
        default=None,
        description="A separation filter raced as an extra row under each table (`+ separation filter`), with the "
        "same checkpoints: an opt-in deployment layer, never part of what the methods learned; null: no such rows",
    )
    robustness: bool = Field(
        default=True,
        description="Sections on each method's final policy in every scenario, racing strangers and downwash",
    )
    racing: RacingCfg | None = Field(
        default=None, description="A racing section of races of several laps (needs evaluation.holdout_runs); null: "
        "none",
    )
    unseen_tracks: UnseenTracksCfg | None = Field(
        default=None, description="A section racing the final policies on tracks no training step flew; null: none")


class PipelineSpec(StrictModel):
    """A training and evaluation pipeline."""

    kind: Literal["pipeline"]
    version: int = Field(default=PIPELINE_VERSION, description="Schema version of this file")
    name: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$", description="Pipeline name (run folder name)")
    track: Path = Field(description="Track file, relative to this pipeline file")
    training_tracks: TrackSetCfg | None = Field(
        default=None, description="Generated tracks the stages train on instead of `track` (a track per world); "
        "`track` is then raced zero-shot by the evaluation")
    airframe: AirframeSel = Field(default_factory=AirframeSel)
    device: str = Field(default="cpu", pattern=r"^(cpu|cuda(:\d+)?)$", description="cpu or cuda:N")
    seed: int = Field(default=0, ge=0, description="Base seed")
    sim: SimCfg = Field(default_factory=SimCfg)
    stages: list[StageSpec] = Field(min_length=1, description="Training stages in curriculum order")
    evaluation: EvaluationCfg = Field(default_factory=EvaluationCfg)
    report: ReportCfg = Field(default_factory=ReportCfg)

    @model_validator(mode="before")
    @classmethod
    def _this_version(cls, data: Any) -> Any:
        version = data.get("version", PIPELINE_VERSION) if isinstance(data, dict) else PIPELINE_VERSION
        if version == PIPELINE_VERSION:
            return data
        if isinstance(version, int) and 1 <= version < PIPELINE_VERSION:
            changes = "; ".join(_CHANGED_SINCE[v] for v in sorted(_CHANGED_SINCE) if v >= version)
            raise ValueError(f"version: the file is version {version}, this spiral reads version {PIPELINE_VERSION} "
                             f"({changes}); change the file, then set version: {PIPELINE_VERSION}")
        raise ValueError(f"version: {version!r} is not a version this spiral reads ({PIPELINE_VERSION}; a newer file "
                         "needs a newer spiral)")

    @field_validator("device")
    @classmethod
    def _canonical_device(cls, device: str) -> str:
        return canonical_device(device)  # cuda is cuda:0: one name, one fingerprint

    @model_validator(mode="after")
    def _stages_drive_the_pid(self) -> PipelineSpec:
        if self.sim.control_mode != "pid":
            raise ValueError("sim.control_mode: a pipeline's policies command positions through the PID ('pid'); "
                             "motor speeds ('rpm') are the simulator's alone")
        return self

    @model_validator(mode="after")
    def _stage_references(self) -> PipelineSpec:
        names = [s.name for s in self.stages]
        for i, stage in enumerate(self.stages):
            if stage.name in names[:i]:
                raise ValueError(f"stages.{i}.name: duplicate stage name {stage.name!r}")
            if stage.init_from is not None and stage.init_file is None and stage.init_from not in names[:i]:
                raise ValueError(f"stages.{i}.init_from: {stage.init_from!r} is not an earlier stage (nor a "
                                 f"checkpoint file, *.pt)")
            source = stage.selfplay.opponent_from
            if source is not None and source not in names[:i]:
                raise ValueError(f"stages.{i}.selfplay.opponent_from: {source!r} is not an earlier stage")
            if stage.env.episode.hard_tracks is not None and self.training_tracks is None:
                raise ValueError(f"stages.{i}.env.episode.hard_tracks: draws among the training tracks of a track "
                                 "per world; set training_tracks")
        if self.report.racing is not None and not self.evaluation.holdout_runs:
            raise ValueError("report.racing: races the held-out placements; set evaluation.holdout_runs")
        self._final_picks_on_their_own_placements()
        return self

    def _final_picks_on_their_own_placements(self) -> None:
        """A stage's final pick may not race the placements the pipeline reports on."""
        ev = self.evaluation
        reported = {ev.seed, *([ev.holdout_seed] if ev.holdout_runs else [])}
        for i, stage in enumerate(self.stages):
            final = stage.selection.final
            if final is not None and stage.scenario != "solo" and final.seed in reported:  # solo stages pick none
                raise ValueError(f"stages.{i}.selection.final.seed: {final.seed} is a seed the pipeline reports on "
                                 f"(evaluation: {sorted(reported)}); the final pick needs placements of its own")

    def init_stage(self, index: int) -> str | None:
        """Name of the stage whose best policy stage ``index`` starts from (None: it starts afresh or from a
        checkpoint file, ``init_file``)."""
        stage = self.stages[index]
        if stage.init_file is not None:
            return None
        if stage.init_from is not None:
            return stage.init_from
        return self.stages[index - 1].name if index > 0 else None
