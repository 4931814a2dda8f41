"""Typed, strict specs for tracks, airframes, the simulator and pipelines."""

from __future__ import annotations

from spiral.config.airframe import AIRFRAMES, AirframeCfg, AirframeSel, PIDCfg, resolve_airframe
from spiral.config.base import StrictModel
from spiral.config.env import (
    ActionCfg,
    EnvCfg,
    EpisodeCfg,
    HardTracksCfg,
    ObsCfg,
    PassageStartsCfg,
    RewardCfg,
    SeparationCfg,
)
from spiral.config.errors import SpecError
from spiral.config.load import KINDS, load_pipeline, load_spec, load_track
from spiral.config.pipeline import EvaluationCfg, PipelineSpec, ReportCfg
from spiral.config.ppo import PPOCfg
from spiral.config.sim import SimCfg
from spiral.config.stage import FinalPickCfg, PromotionCfg, SelectionCfg, SelfPlayCfg, StageSpec
from spiral.config.track import BoundsCfg, GateSpec, StartCfg, TrackSpec, gate_rotation

__all__ = [
    "AIRFRAMES",
    "KINDS",
    "ActionCfg",
    "AirframeCfg",
    "AirframeSel",
    "BoundsCfg",
    "EnvCfg",
    "EpisodeCfg",
    "EvaluationCfg",
    "FinalPickCfg",
    "GateSpec",
    "HardTracksCfg",
    "ObsCfg",
    "PIDCfg",
    "PPOCfg",
    "PassageStartsCfg",
    "PipelineSpec",
    "PromotionCfg",
    "ReportCfg",
    "RewardCfg",
    "SelectionCfg",
    "SelfPlayCfg",
    "SeparationCfg",
    "SimCfg",
    "SpecError",
    "StageSpec",
    "StartCfg",
    "StrictModel",
    "TrackSpec",
    "gate_rotation",
    "load_pipeline",
    "load_spec",
    "load_track",
    "resolve_airframe",
]
