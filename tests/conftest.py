"""Shared fixtures: small hand-made tracks and the shipped ones."""

from __future__ import annotations

from pathlib import Path

import pytest

from spiral.config import TrackSpec, load_track

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def circuit6() -> TrackSpec:
    """The paper's 6-gate circuit."""
    return load_track(ROOT / "tracks" / "circuit6.yaml")


@pytest.fixture(scope="session")
def oval2() -> TrackSpec:
    """Two gates side by side: east through gate 0 at y = −1, west through gate 1 at y = +1."""
    return TrackSpec.model_validate({
        "kind": "track",
        "name": "oval2",
        "gates": [
            {"position": [0.0, -1.0, 1.0], "rpy_deg": [0, 0, 0]},
            {"position": [0.0, 1.0, 1.0], "rpy_deg": [0, 0, 180], "direction": 1},
        ],
        "start": {"center": [-1.2, -1.0, 1.0], "size": [0.4, 0.4, 0.2], "min_separation": 0.25},
        "bounds": {"min": [-3.0, -3.0, 0.0], "max": [3.0, 3.0, 2.5]},
        "time_limit_s": 10.0,
    })


@pytest.fixture(scope="session")
def line2() -> TrackSpec:
    """Two gates in a straight line ahead of the start box, both passed eastwards."""
    return TrackSpec.model_validate({
        "kind": "track",
        "name": "line2",
        "gates": [
            {"position": [0.0, 0.0, 1.0], "rpy_deg": [0, 0, 0], "direction": 1},
            {"position": [2.5, 0.0, 1.0], "rpy_deg": [0, 0, 0], "direction": 1},
        ],
        "start": {"center": [-1.0, 0.0, 1.0], "size": [0.3, 0.3, 0.2], "min_separation": 0.25},
        "bounds": {"min": [-3.0, -3.0, 0.0], "max": [5.0, 3.0, 2.5]},
        "time_limit_s": 6.0,
    })
