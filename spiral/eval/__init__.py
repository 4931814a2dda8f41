"""Evaluation outputs: races, metrics, the lap-time reference, tables, figures and replays.

Plots and the lap-time reference import eagerly; the race-based parts (evaluation, report, replays) load the
simulator and torch, so they are imported on first use and ``spiral track show`` stays quick.
"""

from __future__ import annotations

import importlib
from typing import Any

from spiral.eval.bound import AccelLimits, LapBound, lap_time_bound
from spiral.eval.plots import plot_learning_curves, plot_speed_vs_reliability, plot_track

_LAZY = {
    "RaceSet": "spiral.eval.evaluate",
    "evaluate_methods": "spiral.eval.evaluate",
    "build_report": "spiral.eval.report",
    "record_race": "spiral.eval.replay",
    "render_race": "spiral.eval.replay",
}
"""Public names defined in modules that import the simulator, by module."""

__all__ = [
    "AccelLimits",
    "LapBound",
    "RaceSet",
    "build_report",
    "evaluate_methods",
    "lap_time_bound",
    "plot_learning_curves",
    "plot_speed_vs_reliability",
    "plot_track",
    "record_race",
    "render_race",
]


def __getattr__(name: str) -> Any:
    """Import a race-based public name on first use."""
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'spiral.eval' has no attribute {name!r}")
