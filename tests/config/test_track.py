"""Track geometry: rotation convention, gate frames, passing directions, centreline, summary."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from spiral.config import TrackSpec, gate_rotation

ROOT = Path(__file__).resolve().parents[2]


def _oval4_with(**gate0: object) -> TrackSpec:
    """oval4 with extra fields on its first gate."""
    data = yaml.safe_load((ROOT / "tracks" / "oval4.yaml").read_text())
    data["gates"][0] = {**data["gates"][0], **gate0}
    return TrackSpec.model_validate(data)


def test_rotation_is_yaw_after_pitch_after_roll_on_a_hand_case():
    """Map x to y, y to z and z to x for roll 90 then yaw 90 (R = Rz·Ry·Rx)."""
    # Rx(90): y -> z, z -> -y; then Rz(90): x -> y, y -> -x. Columns are the images of x, y, z.
    expected = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert np.allclose(gate_rotation((90.0, 0.0, 90.0)), expected, atol=1e-12)


def test_positive_pitch_tilts_the_normal_down():
    """Give circuit6's G2 (pitch 30, yaw 90) the normal (0, cos 30, −sin 30)."""
    normal = gate_rotation((0.0, 30.0, 90.0))[:, 0]
    assert np.allclose(normal, [0.0, math.cos(math.radians(30)), -0.5], atol=1e-12)


def test_gate_frames_are_outer_squares_in_the_gate_plane(circuit6):
    """Place each gate's four corners 0.7 m apart (0.6 opening + 2 × 0.05 bar) in the plane normal to n."""
    normals = circuit6.gate_rotations()[:, :, 0]
    for i, centre in enumerate(circuit6.gate_centers()):
        corners = circuit6.gate_corners(i)
        assert np.allclose((corners - centre) @ normals[i], 0.0, atol=1e-12)
        sides = [np.linalg.norm(corners[a] - corners[b]) for a, b in ((0, 1), (1, 3), (3, 2), (2, 0))]
        assert np.allclose(sides, 0.7)


def test_each_circuit6_gate_is_entered_from_the_previous_and_left_towards_the_next(circuit6):
    """Point every forward vector along both the incoming and the outgoing centreline segment."""
    c, fwd = circuit6.gate_centers(), circuit6.gate_forward()
    incoming = np.einsum("gi,gi->g", fwd, c - np.roll(c, 1, axis=0))
    outgoing = np.einsum("gi,gi->g", fwd, np.roll(c, -1, axis=0) - c)
    assert (incoming > 0).all() and (outgoing > 0).all()


def test_given_direction_overrides_the_inferred_one():
    """Flip oval4's first gate when it says direction −1, and keep the inferred sign otherwise."""
    assert _oval4_with().gate_directions()[0] == 1
    flipped = _oval4_with(direction=-1)
    assert flipped.gate_directions().tolist() == [-1, 1, 1, 1]
    assert np.allclose(flipped.gate_forward()[0], [0.0, -1.0, 0.0], atol=1e-12)


def test_per_gate_opening_override_changes_only_that_gate():
    """Give gate 0 a 0.8 m opening (0.9 m outside) and leave the others at the track's 0.6 m."""
    track = _oval4_with(opening=0.8)
    assert track.gate_size(0) == pytest.approx(0.9)
    assert track.gate_size(1) == pytest.approx(0.7)


def test_centreline_points_close_the_loop(circuit6):
    """Return the six gate centres in order followed by the first one again."""
    points = circuit6.centreline_points()
    assert points.shape == (7, 3)
    np.testing.assert_allclose(points[:6], circuit6.gate_centers(), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(points[-1], points[0], rtol=1e-6, atol=1e-9)


def test_centreline_length_of_two_gates_is_twice_their_distance(oval2):
    """Measure 2 m there and 2 m back between gates at y = −1 and y = +1."""
    assert oval2.centreline_length() == pytest.approx(4.0)


def test_summary_lists_gates_with_passing_directions(circuit6):
    """Report six gates with their inferred signs, unit forward vectors and 0.7 m frames, as plain JSON."""
    info = json.loads(json.dumps(circuit6.summary()))
    assert info["gate_count"] == 6
    assert [g["direction"] for g in info["gates"]] == [-1, -1, -1, -1, 1, -1]
    assert all(g["direction_inferred"] for g in info["gates"])
    assert np.allclose(np.linalg.norm([g["forward"] for g in info["gates"]], axis=1), 1.0, atol=1e-5)
    assert [g["outer_size"] for g in info["gates"]] == pytest.approx([0.7] * 6)
    assert set(info["bounds"]) == {"min", "max"}
    assert info["bounds"]["min"] == pytest.approx([-3.5, -4.0, 0.0])
    assert info["bounds"]["max"] == pytest.approx([4.5, 3.0, 3.0])
