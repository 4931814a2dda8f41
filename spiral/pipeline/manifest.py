"""Step fingerprints and manifests: a step is complete only when its manifest matches and its outputs verify."""

from __future__ import annotations

import functools
import hashlib
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import BaseModel

import spiral
from spiral.core.files import atomic_write_bytes, file_sha256

__all__ = ["MANIFEST", "Fingerprint", "StepState", "fingerprint", "read_manifest", "source_hash", "step_state",
           "write_manifest"]

MANIFEST = "manifest.json"


@functools.cache
def source_hash() -> str:
    """SHA-256 of the spiral package's Python source: every ``*.py`` file under it, by relative path and content."""
    root = Path(spiral.__file__).resolve().parent
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


@dataclass(frozen=True)
class Fingerprint:
    """A step's fingerprint: ``full`` sees the spiral source as well, ``spec`` only the spec and inputs."""

    full: str
    spec: str

    def spec_matches(self, recorded: object) -> bool:
        """Whether a recorded spec fingerprint is this one's."""
        return recorded == self.spec


def _digest(blob: dict[str, Any]) -> str:
    """SHA-256 of ``blob`` as sorted JSON; pydantic models in it are dumped without their default fields."""

    def encode(value: Any) -> Any:
        if isinstance(value, BaseModel):
            return value.model_dump(exclude_defaults=True)
        return str(value)

    return hashlib.sha256(json.dumps(blob, sort_keys=True, default=encode).encode()).hexdigest()


def fingerprint(name: str, section: Any, inputs: list[Fingerprint], *, source: str | None = None) -> Fingerprint:
    """Hash of the step name, its spec section, its inputs' fingerprints and the spiral version; the ``full`` one
    also of the package source (:func:`source_hash` when None), so that a code change reruns it.

    Pydantic models in ``section`` are hashed by the fields that differ from their defaults: a new option with a
    default leaves the fingerprint of a step that does not set it unchanged. A changed default is a change of the
    source, which the ``full`` fingerprint sees: ``--accept-code-changes`` keeps, knowingly, a step that left the
    field unset (and ran with the old default), while a step whose value is the old default or the new one hashes
    differently, and reruns, even where its value is the one it ran with.
    """
    base = {"step": name, "spec": section, "version": spiral.__version__}
    full = {**base, "inputs": [i.full for i in inputs], "source": source or source_hash()}
    return Fingerprint(full=_digest(full), spec=_digest({**base, "inputs": [i.spec for i in inputs]}))


def write_manifest(step_dir: Path, name: str, fp: Fingerprint, outputs: dict[str, Path],
                   info: dict[str, Any]) -> None:
    """Record the outputs' checksums and the fingerprint, atomically, after every output is persisted."""
    data = {
        "step": name,
        "fingerprint": fp.full,
        "spec_fingerprint": fp.spec,
        "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "outputs": {key: {"path": str(p), "sha256": file_sha256(p)} for key, p in outputs.items()},
        "info": info,
    }
    atomic_write_bytes(step_dir / MANIFEST, json.dumps(data, indent=2, default=str).encode())


def read_manifest(step_dir: Path) -> dict[str, Any] | None:
    """The step's manifest, or None when absent or unreadable."""
    try:
        return json.loads((step_dir / MANIFEST).read_text())
    except (OSError, json.JSONDecodeError):
        return None


@dataclass
class StepState:
    """Where a step stands: ``complete``, ``stale`` (with the reason), ``partial`` or ``missing``."""

    status: str
    reason: str = ""


def step_state(step_dir: Path, fp: Fingerprint, *, accept_code_changes: bool = False) -> StepState:
    """Compare a step's folder against the fingerprint it should have.

    A step that ran with other spiral source but the same spec and inputs is stale, unless ``accept_code_changes``
    (then it is complete: its results are kept knowingly).
    """
    manifest = read_manifest(step_dir)
    if manifest is None:
        return StepState("partial", "started, no manifest") if step_dir.exists() else StepState("missing")
    if manifest.get("fingerprint") != fp.full:
        if not fp.spec_matches(manifest.get("spec_fingerprint")):
            return StepState("stale", "its spec, an input or the spiral version changed")
        if not accept_code_changes:
            return StepState("stale", "the spiral source changed since it ran (--accept-code-changes keeps it)")
    for key, out in manifest.get("outputs", {}).items():
        path = Path(out["path"])
        if not path.is_file():
            return StepState("stale", f"output {key} is missing: {path}")
        if file_sha256(path) != out["sha256"]:
            return StepState("stale", f"output {key} does not match its checksum: {path}")
    return StepState("complete")
