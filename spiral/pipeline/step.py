"""A pipeline step: a function with declared inputs (upstream steps) and a resolved spec section; the error a
failed step raises."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["PipelineError", "Step", "StepContext"]


class PipelineError(Exception):
    """A step failed; the message names it and the command that resumes."""


@dataclass
class StepContext:
    """What a running step gets: its folder, its upstream steps' manifests, and a logger."""

    step_dir: Path
    inputs: dict[str, dict[str, Any]]
    log: Callable[[str], None]
    progress: bool = True


@dataclass
class Step:
    """``fn(ctx) -> (outputs, info)``: outputs are files to checksum; info goes into the manifest."""

    name: str
    fn: Callable[[StepContext], tuple[dict[str, Path], dict[str, Any]]]
    inputs: list[str] = field(default_factory=list)
    spec_section: Any = None
    resumable: bool = False
    """Whether an interrupted run keeps its folder and picks up from there (training steps)."""

    @property
    def dirname(self) -> str:
        """Folder name of the step under the run folder (``train:solo`` -> ``train-solo``)."""
        return self.name.replace(":", "-")
