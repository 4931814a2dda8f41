"""Declarative, resumable pipelines: steps with fingerprints, manifests, a lock and resume."""

from __future__ import annotations

from spiral.pipeline.graph import PipelinePlan, select_steps
from spiral.pipeline.lock import PipelineLock, PipelineLockedError
from spiral.pipeline.manifest import fingerprint, step_state
from spiral.pipeline.runner import PipelineRunner, StepStatus
from spiral.pipeline.step import PipelineError, Step, StepContext

__all__ = [
    "PipelineError",
    "PipelineLock",
    "PipelineLockedError",
    "PipelinePlan",
    "PipelineRunner",
    "Step",
    "StepContext",
    "StepStatus",
    "fingerprint",
    "select_steps",
    "step_state",
]
