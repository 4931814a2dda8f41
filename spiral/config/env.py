"""Race environment settings: observation layout, action mapping, reward weights and episodes."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from spiral.config.base import NonNegFloat, PosFloat, PosInt, StrictModel

__all__ = ["EVAL_REWARD", "ActionCfg", "EnvCfg", "EpisodeCfg", "HardTracksCfg", "ObsCfg", "PassageStartsCfg",
           "RewardCfg", "SeparationCfg"]


class ObsCfg(StrictModel):
    """Observation layout: 12-D ego state plus a history of [2 nearest drones, next 2 gates, own action].

    The defaults are the shipped recipe's compact layout: the current step only and every extra (55 inputs). The
    paper's layout is ``history_len: 50`` with every extra off (12 + 2 presence flags + 50·16 = 814 inputs); it is
    far costlier for PPO on a CPU and learns slower (pipelines/paper.yaml spells it).
    """

    history_len: PosInt = Field(default=1, description="Control steps K kept in the history buffer (the paper: 50)")
    gate_normals: bool = Field(default=True, description="Add the passing direction of the next 2 gates")
    pid_integral: bool = Field(default=True, description="Add the position controller's integral state")
    opponent_velocity: bool = Field(default=True, description="Add the relative velocity of the 2 nearest drones")
    teammates: bool = Field(
        default=True,
        description="Add whether each of the 2 nearest drones is a team mate (2v2: slots 0, 1 against 2, 3), so a "
        "policy shared by a team can treat its team mate otherwise than an opponent (not in the paper)",
    )
    closest_approach: bool = Field(
        default=True,
        description="Add, for each of the 2 nearest drones, where it will be relative to the drone at their closest "
        "approach within approach_horizon_s if both keep their velocities (3) and when, as a fraction of the horizon "
        "(1): a time-to-collision sensor (not in the paper)",
    )
    approach_horizon_s: PosFloat = Field(default=0.5, description="Look-ahead of the closest-approach inputs [s]")


class SeparationCfg(StrictModel):
    """Separation filter between the policy and the position controller (not in the paper).

    Every control step each racing drone's position target is shifted away from every other racing drone of its
    world whose closest approach within ``horizon_s`` (both keeping their velocities) comes nearer than
    ``distance``: by ``gain`` · (1 − d/distance) along the predicted separation, d the predicted distance. Like
    the PID it belongs to the flight stack, so every drone flies with it, whichever policy or planner commands it.
    """

    distance: PosFloat = Field(default=0.25, description="Predicted distance below which a target is shifted [m]")
    horizon_s: NonNegFloat = Field(default=0.4, description="Look-ahead for the closest approach [s]")
    gain: PosFloat = Field(default=1.5, description="Target shift at zero predicted distance [m]")


class ActionCfg(StrictModel):
    """How a 4-D action in [−1, 1] becomes a PID target (position and yaw)."""

    mode: Literal["relative", "absolute"] = Field(
        default="relative", description="relative: offset from the drone; absolute: point in the arena (paper)"
    )
    pos_scale: PosFloat = Field(default=2.0, description="Target offset at action 1 in relative mode [m]")
    yaw_scale_deg: PosFloat = Field(default=45.0, description="Yaw offset at action 1 in relative mode [deg]")
    separation: SeparationCfg | None = Field(
        default=None, description="Separation filter on the position targets (none in the paper's stack)"
    )
    separation_team: Literal["all", "a", "b"] = Field(
        default="all",
        description="Drones whose targets the separation filter shifts: every drone, or only race team A's or B's "
        "(a deployment layer on one team's drones racing drones without it); every racing drone is avoided either way",
    )

    @model_validator(mode="after")
    def _team_needs_filter(self) -> ActionCfg:
        if self.separation_team != "all" and self.separation is None:
            raise ValueError(f"separation_team: {self.separation_team!r} names the drones of a separation filter, but "
                             "separation is null")
        return self


class RewardCfg(StrictModel):
    """Weights of the reward terms: the paper's (progress, gate, collision, alignment, lap) and three of the shipped
    recipe's that act only between drones (proximity, closing, win: zero in a solo race; 0 turns one off, and with
    all three at 0 the reward is the paper's). Each term is logged as ``Episode_Reward/<term>``."""

    progress: NonNegFloat = Field(default=1.0, description="Per metre of progress towards the next gate")
    progress_lateral: float = Field(
        default=2.0, ge=1.0,
        description="Funnel factor κ of the progress distance sqrt(a² + κ²·l²) to the next gate (a along its "
        "normal, l across it); 1 is the plain distance to the gate centre",
    )
    gate: NonNegFloat = Field(default=2.0, description="Per gate passed in order")
    collision: NonNegFloat = Field(
        default=2.0, description="Penalty C once, at the step of a collision (a crash also ends the race)"
    )
    alignment: NonNegFloat = Field(default=0.002, description="Weight ζ of max(0, cos θ − cos θ_th) per step")
    alignment_threshold_deg: float = Field(default=60.0, gt=0, le=180, description="θ_th [deg]")
    lap: NonNegFloat = Field(default=1.0, description="Weight of 100 / lap_time at a completed lap")
    proximity: NonNegFloat = Field(
        default=0.1,
        description="Weight of the per-step penalty max(0, 1 − d/proximity_distance), d the distance to the nearest "
        "other drone (not in the paper; 0: off)",
    )
    proximity_distance: PosFloat = Field(default=0.5, description="Distance where the proximity penalty starts [m]")
    closing: NonNegFloat = Field(
        default=0.5,
        description="Weight of a per-step penalty for closing in on the nearest other racing drone: the rate r at "
        "which the two close in [m/s] times the drone's share of it (the share of the closing speed it flies into "
        "the other) times max(0, 1 − d/closing_distance); the drone that runs up on a slower one ahead pays, the "
        "one ahead does not, whether or not it makes room (not in the paper; 0: off)",
    )
    closing_distance: PosFloat = Field(default=1.0, description="Distance where the closing penalty starts [m]")
    win: NonNegFloat = Field(
        default=3.0,
        description="Weight of the race outcome, at the step a drone first completes the lap: +1 to its team's "
        "drones, -1 to the other team's drones still racing (start-box races against opponents only; not in the "
        "paper; 0: off)",
    )


EVAL_REWARD = RewardCfg(proximity=0.0, closing=0.0, win=0.0)
"""The reward of evaluation envs: races are scored by their outcome, not by a reward, so the terms between drones (a
pass over every pair of drones at each step) are left out."""


class PassageStartsCfg(StrictModel):
    """Training episodes started from states drones had just after passing a gate earlier in the stage (kept per
    gate, perturbed): starts along the track as drones really fly it, at racing speed and heading. The share of such
    episodes moves linearly from ``share_start`` to ``share_end`` over the stage; the other episodes start as the
    rest of ``episode`` says. Until a gate has recorded states, worlds that would start behind it start so too."""

    share_start: float = Field(default=0.5, ge=0, le=1, description="Share of episodes started from passage states "
                               "at the stage's first iteration")
    share_end: float = Field(default=0.2, ge=0, le=1, description="The same share at its last iteration")
    capacity: PosInt = Field(default=512, description="Passage states kept per gate (the newest)")
    pos_noise: NonNegFloat = Field(default=0.05, description="Standard deviation of a start's position noise per "
                                   "axis [m]")
    vel_noise: NonNegFloat = Field(default=0.2, description="Standard deviation of a start's velocity noise per "
                                   "axis [m/s]")


class HardTracksCfg(StrictModel):
    """Training tracks drawn by how often the learner fails them (with a track per world, ``training_tracks``): each
    track's success is smoothed over the learner's recent episodes on it, and a share of the draws is weighted by its
    failure rate, so that the tracks the policy cannot yet fly come up more often."""

    share: float = Field(default=0.5, ge=0, le=1, description="Share of the track draws weighted by each track's "
                         "failure rate (1 − its smoothed success); the rest are uniform")
    decay: float = Field(default=0.9, gt=0, lt=1, description="Weight each training iteration leaves on the episodes "
                         "counted before it (0.9: a half-life of about 7 iterations)")


class EpisodeCfg(StrictModel):
    """Episode starts and limits in training (evaluation starts in the start box unless ``eval_starts`` says)."""

    track_start_prob: float = Field(
        default=0.3, ge=0, le=1, description="Share of episodes started at a random point along the track"
    )
    track_start_speed: NonNegFloat = Field(default=1.0, description="Largest initial speed of a track start [m/s]")
    passage_starts: PassageStartsCfg | None = Field(
        default_factory=PassageStartsCfg,
        description="Starts from recorded gate-passage states (not in the paper); null: none (the paper's)",
    )
    laps: PosInt | None = Field(
        default=None, description="Laps of a training race; the track's when absent (its time limit scaled to them)"
    )
    time_limit_s: PosFloat | None = Field(default=None, description="Episode time limit; the track's when absent")
    start_cut_prob: float = Field(
        default=0.0, ge=0, le=1,
        description="Share of start-box episodes cut after start_cut_s (a time-out: the value is bootstrapped), so "
        "that more of the samples come from the start, where the drones race as a pack",
    )
    start_cut_s: PosFloat = Field(default=1.5, description="Race time after which a cut episode ends [s]")
    hard_tracks: HardTracksCfg | None = Field(
        default=None, description="With a track per world, draw the tracks the learner fails more often (not in the "
        "paper); null: every track alike")
    eval_starts: Literal["box", "track", "file"] = Field(
        default="box",
        description="Where evaluation races start: in the start box (the protocol), every drone at its own random "
        "point along the track, or the drones of each world in single file (robustness checks; training ignores it)",
    )


class EnvCfg(StrictModel):
    """Everything the race environment needs besides the track, airframe and simulator."""

    obs: ObsCfg = Field(default_factory=ObsCfg)
    action: ActionCfg = Field(default_factory=ActionCfg)
    reward: RewardCfg = Field(default_factory=RewardCfg)
    episode: EpisodeCfg = Field(default_factory=EpisodeCfg)

    def with_eval_starts(self, starts: Literal["box", "track", "file"]) -> EnvCfg:
        """These settings with evaluation races starting where ``starts`` says (``episode.eval_starts``)."""
        return self.model_copy(update={"episode": self.episode.model_copy(update={"eval_starts": starts})})

