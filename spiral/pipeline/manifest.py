"""Step fingerprints and manifests: a step is complete only when its manifest matches and its outputs verify."""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import spiral
from spiral.train.checkpoint import atomic_write_bytes, file_sha256

__all__ = ["MANIFEST", "StepState", "fingerprint", "read_manifest", "step_state", "write_manifest"]

MANIFEST = "manifest.json"


def fingerprint(name: str, section: Any, input_fingerprints: list[str]) -> str:
    """Hash of the step name, its resolved spec section, its inputs' fingerprints and the spiral version."""
    blob = json.dumps({"step": name, "spec": section, "inputs": input_fingerprints, "version": spiral.__version__},
                      sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()


def write_manifest(step_dir: Path, name: str, fp: str, outputs: dict[str, Path], info: dict[str, Any]) -> None:
    """Record the outputs' checksums and the fingerprint, atomically, after every output is persisted."""
    data = {
        "step": name,
        "fingerprint": fp,
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


def step_state(step_dir: Path, fp: str) -> StepState:
    """Compare a step's folder against the fingerprint it should have."""
    manifest = read_manifest(step_dir)
    if manifest is None:
        return StepState("partial", "started, no manifest") if step_dir.exists() else StepState("missing")
    if manifest.get("fingerprint") != fp:
        return StepState("stale", "its spec, an input or the spiral version changed")
    for key, out in manifest.get("outputs", {}).items():
        path = Path(out["path"])
        if not path.is_file():
            return StepState("stale", f"output {key} is missing: {path}")
        if file_sha256(path) != out["sha256"]:
            return StepState("stale", f"output {key} does not match its checksum: {path}")
    return StepState("complete")
