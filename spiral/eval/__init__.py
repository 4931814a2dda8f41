"""Evaluation outputs: races, metrics, tables and figures."""

from __future__ import annotations

from spiral.eval.plots import plot_track

__all__ = ["plot_track"]
