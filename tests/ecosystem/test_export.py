"""Policy export: TorchScript and ONNX files act like the checkpoint's torch policy, normaliser included."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from typer.testing import CliRunner

from spiral.cli import app
from spiral.train import load_policy
from spiral.train.export import export_policy, load_torchscript


def _random_obs(dim: int, batch: int = 32) -> torch.Tensor:
    return 3.0 * torch.randn(batch, dim, generator=torch.Generator().manual_seed(7)) + 1.0


def _torch_actions(policy, obs: torch.Tensor) -> torch.Tensor:
    return policy(TensorDict({"policy": obs}, batch_size=[obs.shape[0]]))


def test_torchscript_export_matches_the_torch_policy(policy_checkpoint, tmp_path):
    """Give the TorchScript module the same actions as the torch policy on random observation batches."""
    policy = load_policy(policy_checkpoint)
    assert policy.actor.obs_normalizer.mean.abs().max() > 0.5  # the normaliser changes the answer
    module, meta = load_torchscript(export_policy(policy_checkpoint, tmp_path / "policy.ts", fmt="torchscript"))
    dim = policy.obs_layout["obs_dim"]
    assert meta["obs_dim"] == dim and meta["obs_layout"] == policy.obs_layout
    for batch in (1, 32):
        obs = _random_obs(dim, batch)
        torch.testing.assert_close(module(obs), _torch_actions(policy, obs), rtol=0, atol=1e-6)


@pytest.mark.skipif(any(importlib.util.find_spec(m) is None for m in ("onnx", "onnxscript", "onnxruntime")),
                    reason="needs the onnx extra (onnx, onnxscript, onnxruntime)")
def test_onnx_export_matches_the_torch_policy_in_onnxruntime(policy_checkpoint, tmp_path):
    """Give the ONNX model, run by onnxruntime, the torch policy's actions for any batch size."""
    import onnx
    import onnxruntime

    policy = load_policy(policy_checkpoint)
    path = export_policy(policy_checkpoint, tmp_path / "policy.onnx", fmt="onnx")
    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert [i.name for i in session.get_inputs()] == ["obs"] and [o.name for o in session.get_outputs()] == ["actions"]
    for batch in (1, 32):
        obs = _random_obs(policy.obs_layout["obs_dim"], batch)
        (actions,) = session.run(None, {"obs": obs.numpy()})
        np.testing.assert_allclose(actions, _torch_actions(policy, obs).numpy(), rtol=0, atol=1e-5)
    props = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    assert '"obs_dim"' in props["spiral"]


def test_cli_export_writes_the_file_and_rejects_unknown_formats(policy_checkpoint, tmp_path):
    """Write the exported file with `spiral export`; exit 1 with an Error line for an unknown format."""
    out = tmp_path / "deploy" / "policy.pt"
    result = CliRunner().invoke(app, ["export", str(policy_checkpoint), "--format", "torchscript", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert f"wrote {out}" in result.output and out.stat().st_size > 0
    bad = CliRunner().invoke(app, ["export", str(policy_checkpoint), "--format", "tflite", "--out", str(out)])
    assert bad.exit_code == 1 and "Error: --format: expected one of onnx, torchscript" in bad.output
    missing = CliRunner().invoke(app, ["export", str(tmp_path / "nope.pt"), "--format", "onnx", "--out", str(out)])
    assert missing.exit_code == 1 and "no such checkpoint" in missing.output
