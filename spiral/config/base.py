"""Strict pydantic base model and shared field types."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["NonNegFloat", "NonNegInt", "PosFloat", "PosInt", "StrictModel", "Vec3"]


class StrictModel(BaseModel):
    """Base of every spec: unknown keys are errors, values are frozen, NaN and inf are rejected."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, validate_default=True)


Vec3 = tuple[float, float, float]
"""A 3-vector given in YAML as ``[x, y, z]``."""

PosFloat = Annotated[float, Field(gt=0)]
NonNegFloat = Annotated[float, Field(ge=0)]
PosInt = Annotated[int, Field(gt=0)]
NonNegInt = Annotated[int, Field(ge=0)]
