"""Batched quadrotor racing simulator in Warp kernels (no torch here)."""

from __future__ import annotations

from spiral.sim.state import COLLISION_KINDS, QuadParams, QuadState, RaceCounters, TrackArrays
from spiral.sim.world import World

__all__ = ["COLLISION_KINDS", "QuadParams", "QuadState", "RaceCounters", "TrackArrays", "World"]
