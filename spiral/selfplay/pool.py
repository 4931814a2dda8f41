"""The opponent pool: frozen past-best policies on disk with ``pool.json`` (checksums, evaluations, ratings)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from spiral.core.checkpoint import CheckpointError, FrozenPolicy, copy_checkpoint, load_policy
from spiral.core.files import atomic_write_bytes, file_sha256

__all__ = ["INITIAL_RATING", "Pool", "PoolMember"]

INITIAL_RATING = 1000.0


@dataclass
class PoolMember:
    """One frozen policy of the pool."""

    id: str
    file: str
    """Checkpoint file name inside the pool folder."""
    stage: str
    iteration: int
    sha256: str
    rating: float = INITIAL_RATING
    evaluation: dict[str, Any] = field(default_factory=dict)
    added: str = ""


class Pool:
    """Pool folder ``root`` with ``pool.json`` and one checkpoint (+ checksum sidecar) per member.

    Loading verifies every member's checksum and observation layout; a bad member is reported through ``log`` and
    skipped, never fatal.
    """

    def __init__(self, root: Path, *, log: Callable[[str], None] = print) -> None:
        self.root, self.log = Path(root), log
        self.members: list[PoolMember] = []
        self.latest_best: str | None = None
        """Id of the most recently promoted member."""
        self._read()

    @property
    def index_path(self) -> Path:
        """The pool's ``pool.json``."""
        return self.root / "pool.json"

    def _read(self) -> None:
        if not self.index_path.exists():
            return
        try:
            data = json.loads(self.index_path.read_text())
            self.members = [PoolMember(**m) for m in data["members"]]
            self.latest_best = data.get("latest_best")
        except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
            self.log(f"warning: {self.index_path}: unreadable pool index ({exc}); starting an empty pool")
            self.members, self.latest_best = [], None

    def save(self) -> None:
        """Write ``pool.json`` atomically."""
        data = {"latest_best": self.latest_best, "members": [asdict(m) for m in self.members]}
        atomic_write_bytes(self.index_path, json.dumps(data, indent=2).encode())

    def add(self, checkpoint: Path, *, stage: str, iteration: int, evaluation: dict[str, Any],
            rating: float = INITIAL_RATING) -> PoolMember:
        """Copy a checkpoint into the pool as its newest member and latest best."""
        member_id = f"{stage}-{iteration:05d}-{len(self.members):03d}"
        file = f"{member_id}.pt"
        copy_checkpoint(Path(checkpoint), self.root / file)
        member = PoolMember(member_id, file, stage, iteration, file_sha256(self.root / file), rating, evaluation,
                            time.strftime("%Y-%m-%dT%H:%M:%S%z"))
        self.members.append(member)
        self.latest_best = member_id
        self.save()
        return member

    def member(self, member_id: str) -> PoolMember:
        """The member with ``member_id``."""
        return next(m for m in self.members if m.id == member_id)

    def load_policies(self, obs_layout: dict[str, Any], *, device: str = "cpu") -> dict[str, FrozenPolicy]:
        """Policies of every valid member whose observation layout is ``obs_layout``; bad members are skipped."""
        policies = {}
        for m in self.members:
            path = self.root / m.file
            try:
                if file_sha256(path) != m.sha256:
                    raise CheckpointError(f"{path}: checksum differs from pool.json")
                policy = load_policy(path, device=device)
            except (OSError, CheckpointError) as exc:
                self.log(f"warning: pool member {m.id} skipped: {exc}")
                continue
            if policy.obs_layout != obs_layout:
                self.log(f"warning: pool member {m.id} skipped: observation layout differs")
                continue
            policies[m.id] = policy
        return policies
