"""Export a checkpoint's actor for deployment: TorchScript or ONNX, observation normaliser included.

The network is rsl-rl's export module (``MLPModel.as_jit()`` / ``as_onnx()``): normaliser, MLP and the
deterministic output, mapping a float32 observation batch ``(B, obs_dim)`` to actions ``(B, 4)`` in the policy's
output range (the env clips to [−1, 1]). The batch size is free in both formats. The observation layout and the
checkpoint's provenance are stored inside the file: TorchScript extra file ``spiral.json``, ONNX metadata ``spiral``.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import logging
import os
import tempfile
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

import torch

from spiral.core.checkpoint import FrozenPolicy, load_policy
from spiral.core.errors import UsageError
from spiral.core.files import atomic_write_bytes, file_sha256

__all__ = ["EXPORT_FORMATS", "export_metadata", "export_policy", "load_torchscript"]

EXPORT_FORMATS = ("onnx", "torchscript")
"""Formats of :func:`export_policy`."""

ExportFormat = Literal["onnx", "torchscript"]


def export_metadata(policy: FrozenPolicy, checkpoint: Path) -> dict[str, Any]:
    """What an exported file records about its policy: I/O names and shapes, layout and provenance."""
    meta = policy.meta
    return {"input": "obs", "output": "actions", "obs_dim": meta["obs_layout"]["obs_dim"], "action_dim": 4,
            "obs_layout": meta["obs_layout"], "action": meta["env"]["action"],
            "checkpoint": {"file": Path(checkpoint).name, "sha256": file_sha256(Path(checkpoint)),
                           "stage": meta.get("stage"), "iteration": meta.get("iteration"), "track": meta.get("track")}}


def export_policy(checkpoint: Path, out: Path, *, fmt: ExportFormat) -> Path:
    """Write the actor of ``checkpoint`` to ``out`` as TorchScript or ONNX (atomically) and return ``out``.

    Raises:
        ValueError: for an unknown format.
        CheckpointError: for a missing, corrupt or incompatible checkpoint.
    """
    if fmt not in EXPORT_FORMATS:
        raise UsageError(f"--format: expected one of {', '.join(EXPORT_FORMATS)}, got {fmt!r}")
    policy = load_policy(Path(checkpoint), device="cpu")
    meta = json.dumps(export_metadata(policy, Path(checkpoint)), indent=2, default=str)
    out = Path(out)
    if fmt == "torchscript":
        buf = io.BytesIO()
        with _quiet_exporter():  # recent torch flags TorchScript as deprecated; libtorch still loads it
            torch.jit.save(torch.jit.script(policy.actor.as_jit().cpu().eval()), buf,
                           _extra_files={"spiral.json": meta})
        atomic_write_bytes(out, buf.getvalue())
    else:
        _export_onnx(policy, out, meta)
    return out


def _export_onnx(policy: FrozenPolicy, out: Path, meta: str) -> None:
    """torch.export-based ONNX export (needs ``onnx`` and ``onnxscript``) with a free batch dimension."""
    missing = [name for name in ("onnx", "onnxscript") if importlib.util.find_spec(name) is None]
    if missing:
        raise UsageError(f"ONNX export needs {' and '.join(missing)}: pip install 'spiral[onnx]'")
    model = policy.actor.as_onnx(verbose=False).cpu().eval()
    with _quiet_exporter():
        program = torch.onnx.export(model, model.get_dummy_inputs(), dynamo=True, opset_version=18,
                                    input_names=model.input_names, output_names=model.output_names,
                                    dynamic_shapes=({0: torch.export.Dim("batch")},), verbose=False)
    if program is None:
        raise RuntimeError("torch.onnx.export returned no program")
    program.model.metadata_props["spiral"] = meta
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out.parent, prefix=f".{out.name}.", suffix=".tmp")
    os.close(fd)
    try:
        program.save(tmp)
        os.replace(tmp, out)
    finally:
        Path(tmp).unlink(missing_ok=True)


@contextlib.contextmanager
def _quiet_exporter() -> Iterator[None]:
    """Silence the exporters' notes about optional packages (torchvision ops) and their deprecation warnings."""
    logger = logging.getLogger("torch.onnx")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        logger.setLevel(level)


def load_torchscript(path: Path) -> tuple[torch.jit.ScriptModule, dict[str, Any]]:
    """Load an exported TorchScript policy and the metadata stored with it."""
    extra = {"spiral.json": ""}
    with _quiet_exporter():
        module = torch.jit.load(str(path), map_location="cpu", _extra_files=extra)
    return module, json.loads(extra["spiral.json"] or "{}")
