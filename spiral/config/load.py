"""Read a YAML spec file into its frozen pydantic model."""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar, overload

import yaml
from pydantic import BaseModel, ValidationError

from spiral.config.airframe import resolve_airframe
from spiral.config.errors import SpecError, format_validation_error
from spiral.config.pipeline import PipelineSpec
from spiral.config.track import TrackSpec

__all__ = ["KINDS", "load_pipeline", "load_spec", "load_track"]

KINDS: dict[str, type[BaseModel]] = {"track": TrackSpec, "pipeline": PipelineSpec}
"""Spec model for each value of the top-level ``kind`` field."""

SpecT = TypeVar("SpecT", bound=BaseModel)


def _read_yaml(path: Path) -> Any:
    try:
        text = path.read_text()
    except OSError as exc:
        raise SpecError([f"{path}: cannot read: {exc.strerror or exc}"]) from exc
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        raise SpecError([f"{path}: {where}invalid YAML: {getattr(exc, 'problem', None) or exc}"]) from exc


@overload
def load_spec(path: str | Path, spec_type: type[SpecT]) -> SpecT: ...
@overload
def load_spec(path: str | Path, spec_type: None = None) -> BaseModel: ...
def load_spec(path: str | Path, spec_type: type[BaseModel] | None = None) -> BaseModel:
    """Load ``path``, dispatching on its ``kind`` field, and check it is a ``spec_type`` when given.

    Raises:
        SpecError: naming the file and the dotted field path of every problem.
    """
    path = Path(path)
    data = _read_yaml(path)
    if not isinstance(data, dict):
        raise SpecError([f"{path}: expected a mapping with a 'kind' field, got {type(data).__name__}"])
    data = {k: v for k, v in data.items() if not (isinstance(k, str) and k.startswith("x-"))}  # YAML anchors
    kind = data.get("kind")
    if kind not in KINDS:
        raise SpecError([f"{path}: kind: expected one of {', '.join(KINDS)}, got {kind!r}"])
    model = KINDS[kind]
    if spec_type is not None and model is not spec_type:
        expected = next(k for k, v in KINDS.items() if v is spec_type)
        raise SpecError([f"{path}: kind: expected {expected!r}, got {kind!r}"])
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise SpecError(format_validation_error(str(path), exc)) from exc


def load_track(path: str | Path) -> TrackSpec:
    """Load a ``kind: track`` file."""
    return load_spec(path, TrackSpec)


def load_pipeline(path: str | Path) -> tuple[PipelineSpec, TrackSpec]:
    """Load a pipeline and the track it names (relative to the pipeline file)."""
    path = Path(path)
    spec = load_spec(path, PipelineSpec)
    resolve_airframe(spec.airframe, source=str(path))  # a misspelt override fails here, naming the file
    track_path = spec.track if spec.track.is_absolute() else path.parent / spec.track
    return spec, load_track(track_path)
