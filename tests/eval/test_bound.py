"""Lap-time reference: acceleration limits by hand, bang-bang closed form, gate openings respected."""

from __future__ import annotations

import math

import numpy as np
import pytest

from spiral.config import AIRFRAMES, TrackSpec
from spiral.eval.bound import AccelLimits, lap_time_bound

CF2X = AIRFRAMES["cf2x"]
A_LEVEL = 9.81 * math.tan(math.radians(60.0))
"""cf2x in level flight: tilt-limited (g·tan 60° = 16.99) before thrust-limited (g·√(2.25² − 1) = 19.77)."""


def shuttle(d: float, length: float) -> TrackSpec:
    """Gate 0 at x = 0 passed eastwards, gate 1 at x = length passed westwards, start at x = −d: a straight lap."""
    return TrackSpec.model_validate({
        "kind": "track", "name": "shuttle",
        "gates": [{"position": [0.0, 0.0, 1.0], "direction": 1}, {"position": [length, 0.0, 1.0], "direction": -1}],
        "start": {"center": [-d, 0.0, 1.0], "size": [0.1, 0.1, 0.1]},
        "bounds": {"min": [-d - 1.0, -2.0, 0.0], "max": [length + 1.0, 2.0, 2.0]},
    })


def test_acceleration_limits_follow_thrust_to_weight_and_tilt():
    """Derive f_max = 2.25·g, level 16.99, up 12.26 and down g m/s² for the Crazyflie."""
    lim = AccelLimits.from_airframe(CF2X)
    assert lim.thrust == pytest.approx(2.25 * 9.81)
    assert lim.level == pytest.approx(A_LEVEL)
    assert lim.up == pytest.approx(2.25 * 9.81 - 9.81)
    assert lim.to_json()["a_max_down"] == pytest.approx(9.81)


def test_straight_shuttle_matches_the_bang_bang_closed_form():
    """Fly start → gate 0 → gate 1 → gate 0 of a straight track in 2√((L+d)/a) + 2√(L/a) (rest at each turn)."""
    # In units of a·(0.1 s)²: d = 32, L = 49 give legs of 1.8 s (accelerating past gate 0 at 0.8 s) and 1.4 s,
    # so with 32 steps per segment on average the switching instants fall on nodes and the optimum is exact.
    unit = A_LEVEL * 0.01
    d, length = 32 * unit, 49 * unit
    exact = 2 * math.sqrt((length + d) / A_LEVEL) + 2 * math.sqrt(length / A_LEVEL)
    bound = lap_time_bound(shuttle(d, length), CF2X, model="ball", steps_per_segment=32)
    assert exact == pytest.approx(3.2)
    assert bound.lap_time == pytest.approx(exact, rel=1e-6)
    assert bound.pass_times == pytest.approx([0.8, 1.8, 3.2], rel=1e-6)
    speed = np.linalg.norm(bound.velocities, axis=1)
    assert speed.max() == pytest.approx(A_LEVEL * 0.9, rel=1e-4)  # peak at the midpoint of the first leg


def test_thrust_model_passes_every_opening_forwards():
    """Pass each gate of the shuttle inside its opening shrunk by the radius, moving in its passing direction."""
    track = shuttle(1.0, 2.0)
    bound = lap_time_bound(track, CF2X, steps_per_segment=8)
    nodes = np.cumsum(bound.steps)
    half = track.opening / 2 - CF2X.radius
    for gate, k in zip(bound.gate_sequence, nodes, strict=True):
        offset = bound.positions[k] - track.gate_centers()[gate]
        forward = track.gate_forward()[gate]
        assert abs(offset @ forward) < 1e-6
        assert np.abs(offset[1:]).max() <= half + 1e-6
        assert bound.velocities[k] @ forward >= -1e-6
    # It may trade height for speed, but stays within a few percent of level-flight bang-bang.
    level = 2 * math.sqrt(3.0 / A_LEVEL) + 2 * math.sqrt(2.0 / A_LEVEL)
    assert 0.9 * level < bound.lap_time < 1.05 * level
