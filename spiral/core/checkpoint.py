"""The checkpoint format (atomic, checksummed, with spiral metadata), frozen policies and loading them."""

from __future__ import annotations

import copy
import hashlib
import io
import json
import re
from collections.abc import Callable
from importlib import metadata
from pathlib import Path
from typing import Any

import torch
from rsl_rl.models import MLPModel
from rsl_rl.modules.normalization import EmpiricalNormalization
from tensordict import TensorDict

from spiral.core.files import atomic_write_bytes, file_sha256
from spiral.core.inputs import silence_inputs, unused_inputs

__all__ = [
    "FORMAT",
    "LEGACY_DEFAULTS",
    "CheckpointError",
    "FrozenPolicy",
    "copy_checkpoint",
    "list_checkpoints",
    "load_checkpoint",
    "load_policy",
    "newest_valid_checkpoint",
    "save_checkpoint",
    "upgrade_meta",
    "with_legacy_defaults",
]

FORMAT = "spiral-checkpoint-2"
"""Value of ``meta["format"]`` in every spiral checkpoint this version writes."""

_FORMAT_1 = "spiral-checkpoint-1"
_FORMAT_1_LAYOUT = {"teammates": False, "priority": False, "closest_approach": False, "approach_horizon_s": 0.5}
"""Observation options that a format-1 checkpoint's ``obs_layout`` left out when they were off, with the values they
then had; format 2 stores every option."""
REMOVED_ENV_OPTIONS: dict[tuple[str, ...], Any] = {
    ("shield",): None, ("reward", "intervention"): 0.0, ("reward", "proximity_leader"): 1.0,
    ("reward", "closing_miss"): 0.0, ("reward", "closing_neighbours"): 1, ("reward", "forfeit"): False,
    ("reward", "contact"): 0.0, ("reward", "overtake"): 0.0, ("episode", "contact_margin"): 0.0,
    ("obs", "priority"): False, ("obs", "history_stride"): 1, ("episode", "file_start_prob"): 0.0,
    ("episode", "passage_starts", "pack"): 0.0, ("critic",): "policy"}
"""Env options of earlier versions, by their path in the env settings, with the value that left them off (tried, never
in a shipped pipeline): a checkpoint saved with them off reads as today's. The observation's own (``obs.*``) leave its
``obs_layout`` too."""
LEGACY_DEFAULTS: dict[tuple[str, ...], Any] = {
    ("env", "obs", "history_len"): 50, ("env", "obs", "gate_normals"): False, ("env", "obs", "pid_integral"): False,
    ("env", "obs", "opponent_velocity"): False, ("env", "obs", "teammates"): False,
    ("env", "obs", "closest_approach"): False,
    ("env", "reward", "proximity"): 0.0, ("env", "reward", "closing"): 0.0, ("env", "reward", "win"): 0.0,
    ("env", "episode", "track_start_prob"): 0.5, ("env", "episode", "passage_starts"): None,
    ("env", "episode", "passage_starts", "share_end"): 0.5,
    ("ppo", "entropy_coef"): 0.005, ("ppo", "bound_loss_coef"): 0.0,
    ("selection", "average"): 0.0, ("selection", "final"): None,
    ("selfplay", "p_self"): 0.0, ("selfplay", "p_latest"): 0.5, ("selfplay", "sampling"): "prioritized",
    ("selfplay", "opponent_offset"): 0.0, ("selfplay", "opponent_blind"): 0.0,
    ("selfplay", "promotion", "max_success_drop"): 0.02, ("selfplay", "promotion", "track_starts"): False}
"""The defaults these fields of a stage had before the schema's defaults became the shipped recipe's (the paper's
values, mostly), by their path in a stage spec: settings stored without a field (saved before it existed) were
trained with its old default, which :func:`with_legacy_defaults` fills in."""


class CheckpointError(Exception):
    """A checkpoint is missing, truncated, corrupt or of an incompatible layout."""


def _versions() -> dict[str, str]:
    out = {}
    for pkg in ("spiral", "torch", "rsl-rl-lib", "warp-lang"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "unknown"
    return out


def save_checkpoint(path: Path, state: dict[str, Any], meta: dict[str, Any]) -> None:
    """Save rsl-rl's ``state`` dict plus spiral ``meta`` atomically; a ``.json`` sidecar holds the checksum.

    The sidecar is written after the checkpoint, so a checkpoint without a matching sidecar is incomplete.
    """
    meta = {"format": FORMAT, "versions": _versions(), **meta}
    buf = io.BytesIO()
    torch.save({**state, "spiral": meta}, buf)
    atomic_write_bytes(path, buf.getvalue())
    side = {"sha256": hashlib.sha256(buf.getvalue()).hexdigest(), "size": len(buf.getvalue()), **meta}
    atomic_write_bytes(path.with_suffix(".json"), json.dumps(side, indent=2, default=str).encode())


def copy_checkpoint(src: Path, dst: Path) -> None:
    """Copy checkpoint ``src`` and its ``.json`` sidecar to ``dst`` atomically, the sidecar last (as when saved)."""
    atomic_write_bytes(dst, Path(src).read_bytes())
    atomic_write_bytes(Path(dst).with_suffix(".json"), Path(src).with_suffix(".json").read_bytes())


def load_checkpoint(path: Path, *, map_location: str = "cpu") -> dict[str, Any]:
    """Load a checkpoint after verifying its checksum against the sidecar.

    Raises:
        CheckpointError: naming the file and what is wrong.
    """
    path = Path(path)
    side_path = path.with_suffix(".json")
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint")
    if not side_path.is_file():
        raise CheckpointError(f"{path}: missing checksum file {side_path.name} (incomplete save?)")
    try:
        side = json.loads(side_path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise CheckpointError(f"{side_path}: unreadable checksum file: {exc}") from exc
    if file_sha256(path) != side.get("sha256"):
        raise CheckpointError(f"{path}: checksum mismatch (truncated or corrupt file)")
    try:
        data = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as exc:  # torch raises many kinds for bad pickles
        raise CheckpointError(f"{path}: cannot be read by torch: {exc}") from exc
    if not isinstance(data, dict) or data.get("spiral", {}).get("format") not in (FORMAT, _FORMAT_1):
        raise CheckpointError(f"{path}: not a spiral checkpoint")
    try:
        data["spiral"] = upgrade_meta(data["spiral"])
    except ValueError as exc:
        raise CheckpointError(f"{path}: {exc}") from exc
    return data


def upgrade_meta(meta: dict[str, Any]) -> dict[str, Any]:
    """A checkpoint's spiral metadata in this version's format: a format-1 layout gains the options it left out, the
    env settings lose the :data:`REMOVED_ENV_OPTIONS` (``ValueError`` if one was on), and the layout, env and PPO
    settings gain the fields they were saved without, at their :data:`LEGACY_DEFAULTS`."""
    if meta.get("format") == _FORMAT_1:
        layout = meta["obs_layout"]
        meta = {**meta, "format": FORMAT, "obs_layout": {**layout, **{k: v for k, v in _FORMAT_1_LAYOUT.items()
                                                                       if k not in layout}}}
    if "obs_layout" in meta:
        layout = _without_removed({"obs": meta["obs_layout"]})["obs"]
        meta = {**meta, "obs_layout": with_legacy_defaults(layout, ("env", "obs"))}
    if "env" in meta:
        meta = {**meta, "env": with_legacy_defaults(_without_removed(meta["env"]), ("env",))}
    if "ppo" in meta:
        meta = {**meta, "ppo": with_legacy_defaults(meta["ppo"], ("ppo",))}
    return meta


def with_legacy_defaults(block: dict[str, Any], at: tuple[str, ...]) -> dict[str, Any]:
    """A copy of ``block``, the settings at path ``at`` of a stage spec (``("env",)``, ``("ppo",)``,
    ``("env", "obs")``...) as stored, with each :data:`LEGACY_DEFAULTS` field under ``at`` that it lacks set to its
    old default."""
    block = copy.deepcopy(block)
    for path, old in LEGACY_DEFAULTS.items():
        if len(path) > len(at) and path[:len(at)] == at:
            _fill(block, path, len(at), old)
    return block


def _fill(block: dict[str, Any], path: tuple[str, ...], start: int, value: Any) -> None:
    """Set the field at ``path`` (of which ``block`` holds what follows its first ``start`` keys) to ``value`` unless
    present. A missing sub-block is added, unless it has an old default of its own; a block stored as null stays so."""
    *parents, name = path[start:]
    for depth, key in enumerate(parents, start=start + 1):
        if key not in block and path[:depth] not in LEGACY_DEFAULTS:
            block[key] = {}
        block = block.get(key)
        if not isinstance(block, dict):
            return
    block.setdefault(name, value)


def _without_removed(env: dict[str, Any]) -> dict[str, Any]:
    """``env`` (settings as saved) without the removed options, each checked to be off."""
    env = copy.deepcopy(env)
    for path, off in REMOVED_ENV_OPTIONS.items():
        *parents, name = path
        block = env
        for key in parents:
            block = block.get(key) or {}  # a block saved as null holds nothing
        if name in block:
            if block[name] != off:
                raise ValueError(f"env.{'.'.join(path)}: this checkpoint was trained with an option that no longer "
                                 f"exists ({block[name]!r}); train it again with this version")
            del block[name]
    return env


def list_checkpoints(ckpt_dir: Path) -> list[tuple[int, Path]]:
    """``(iteration, path)`` of every ``model_<it>.pt`` in ``ckpt_dir``, newest first."""
    found = []
    for p in Path(ckpt_dir).glob("model_*.pt"):
        m = re.fullmatch(r"model_(\d+)\.pt", p.name)
        if m:
            found.append((int(m.group(1)), p))
    return sorted(found, reverse=True)


def newest_valid_checkpoint(ckpt_dir: Path, *, warn: Any = None) -> Path | None:
    """The newest checkpoint whose checksum verifies; broken newer ones are reported through ``warn(msg)``."""
    for _, path in list_checkpoints(ckpt_dir):
        try:
            load_checkpoint(path)
        except CheckpointError as exc:
            if warn is not None:
                warn(f"skipping {exc}")
            continue
        return path
    return None


class FrozenPolicy(torch.nn.Module):
    """A trained actor for inference: observation TensorDict -> deterministic actions."""

    def __init__(self, actor: MLPModel, meta: dict[str, Any]) -> None:
        super().__init__()
        self.actor = actor.eval()
        self.meta = meta
        self._passes: list[tuple[Callable[..., torch.Tensor], tuple[torch.Tensor, ...]]] | None = None
        """The actor's forward pass as plain calls (:meth:`actions`), built at the first call; cleared when the
        module's tensors move (``to``) or are loaded."""
        self.register_load_state_dict_post_hook(_forget_passes)

    def _apply(self, fn: Any, recurse: bool = True) -> FrozenPolicy:
        self._passes = None
        return super()._apply(fn, recurse)

    @property
    def obs_layout(self) -> dict[str, Any]:
        """Observation layout the policy was trained with."""
        return self.meta["obs_layout"]

    @torch.no_grad()
    def forward(self, obs: TensorDict) -> torch.Tensor:
        """Mean action of the policy."""
        return self.actions(obs["policy"])

    @torch.no_grad()
    def actions(self, policy_obs: torch.Tensor) -> torch.Tensor:
        """Mean actions for rows of the ``policy`` observation group, the only group the actor reads: the actor's
        normaliser, network and mean, as its own ``forward`` runs them on a TensorDict, without building one.

        The same operations on the same tensors, to the bit, called directly rather than through each module's
        ``__call__``: a pool member often acts on a dozen rows, where the modules' call overhead was about half
        of the call (``benchmarks/pool_opponents.py``).
        """
        if self._passes is None:
            self._passes = self._plain_passes()
        x = policy_obs
        for fn, args in self._passes:
            x = fn(x, *args)
        return self.actor.distribution.deterministic_output(x)

    def _plain_passes(self) -> list[tuple[Callable[..., torch.Tensor], tuple[torch.Tensor, ...]]]:
        """The normaliser and each layer of the actor's network as ``(function, extra arguments)``."""
        norm, passes = self.actor.obs_normalizer, []
        if isinstance(norm, EmpiricalNormalization):  # its forward: (x - mean) / (std + eps)
            passes.append((_normalize, (norm._mean, norm._std + norm.eps)))
        else:
            passes.append((norm.forward, ()))
        for layer in self.actor.mlp:
            if isinstance(layer, torch.nn.Linear):
                passes.append((torch.nn.functional.linear, (layer.weight, layer.bias)))
            else:
                passes.append((layer.forward, ()))
        return passes


def _forget_passes(policy: FrozenPolicy, _incompatible: Any) -> None:
    policy._passes = None


def _normalize(x: torch.Tensor, mean: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    return (x - mean) / scale


def load_policy(path: Path, *, device: str = "cpu") -> FrozenPolicy:
    """Rebuild the actor of a checkpoint for inference (its normaliser included).

    Inputs that never varied while it trained (a solo policy's opponent slots) are silenced: the policy acts as it
    did in its own stage and ignores them (:mod:`spiral.core.inputs`).
    """
    data = load_checkpoint(path, map_location=device)
    meta = data["spiral"]
    ppo = meta["ppo"]
    dim = meta["obs_layout"]["obs_dim"]
    dummy = TensorDict({"policy": torch.zeros(1, dim), "critic": torch.zeros(1, dim)}, batch_size=[1])
    actor = MLPModel(dummy, {"actor": ["policy"], "critic": ["critic"]}, "actor", 4,
                     hidden_dims=ppo["actor_hidden_dims"], activation=ppo["activation"],
                     obs_normalization=ppo["obs_normalization"],
                     distribution_cfg={"class_name": "rsl_rl.modules.distribution.GaussianDistribution"})
    try:
        actor.load_state_dict(data["actor_state_dict"])
    except (RuntimeError, KeyError) as exc:
        raise CheckpointError(f"{path}: actor weights do not match the stored layout: {exc}") from exc
    silence_inputs(actor, unused_inputs(actor))
    return FrozenPolicy(actor.to(device), meta)
