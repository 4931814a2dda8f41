"""Read a YAML spec file into its frozen pydantic model."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, TypeVar, overload

import yaml
from pydantic import BaseModel, ValidationError

from spiral.config.airframe import resolve_airframe
from spiral.config.errors import SpecError, format_validation_error
from spiral.config.overrides import apply_overrides, variant_name
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
def load_spec(path: str | Path, spec_type: type[SpecT], overrides: Sequence[str] = ()) -> SpecT: ...
@overload
def load_spec(path: str | Path, spec_type: None = None, overrides: Sequence[str] = ()) -> BaseModel: ...
def load_spec(path: str | Path, spec_type: type[BaseModel] | None = None, overrides: Sequence[str] = ()) -> BaseModel:
    """Load ``path``, dispatching on its ``kind`` field, and check it is a ``spec_type`` when given; ``overrides``
    (``path.to.field=value``, :mod:`spiral.config.overrides`) are set before validation.

    Raises:
        SpecError: naming the file and the dotted field path of every problem.
    """
    path = Path(path)
    data = _read_yaml(path)
    if not isinstance(data, dict):
        raise SpecError([f"{path}: expected a mapping with a 'kind' field, got {type(data).__name__}"])
    data = {k: v for k, v in data.items() if not (isinstance(k, str) and k.startswith("x-"))}  # YAML anchors
    data = apply_overrides(data, overrides, source=str(path))
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
        where = f"{path} with --set {' --set '.join(overrides)}" if overrides else str(path)
        raise SpecError(format_validation_error(where, exc)) from exc


def load_track(path: str | Path) -> TrackSpec:
    """Load a ``kind: track`` file."""
    return load_spec(path, TrackSpec)


def load_pipeline(path: str | Path, overrides: Sequence[str] = ()) -> tuple[PipelineSpec, TrackSpec]:
    """Load a pipeline with ``overrides`` set and the track it names (relative to the pipeline file). With overrides
    the pipeline's name becomes its variant's (:func:`~spiral.config.overrides.variant_name`), so that its runs and
    checkpoints get folders of their own."""
    path = Path(path)
    spec = load_spec(path, PipelineSpec, overrides)
    if overrides:
        spec = spec.model_copy(update={"name": variant_name(spec.name, overrides)})
    resolve_airframe(spec.airframe, source=str(path))  # a misspelt override fails here, naming the file
    track_path = spec.track if spec.track.is_absolute() else path.parent / spec.track
    return spec, load_track(track_path)
