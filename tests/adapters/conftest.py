"""Adapter fixtures: the ecosystem tests' random policy checkpoint and its small env settings."""

from __future__ import annotations

from tests.ecosystem.conftest import policy_checkpoint, small_env  # noqa: F401  (fixtures of the adapter tests)
