"""Stage spec: one step of the curriculum (solo, 1v1, 2v2)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from spiral.config.base import PosInt, StrictModel

__all__ = ["StageSpec"]


class StageSpec(StrictModel):
    """One training stage."""

    name: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$", description="Stage name")
    scenario: Literal["solo", "1v1", "2v2"] = Field(default="solo", description="Race format")
    iterations: PosInt = Field(default=100, description="PPO iterations")
