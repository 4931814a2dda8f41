"""Contacts: ground, arena bounds, gate bars (sphere vs boxes), other drones of the same world; crash handling."""

from __future__ import annotations

import numpy as np
import pytest

from spiral.sim.state import COLLISION_KINDS

DT = 1.0 / 240.0
R = 0.06  # cf2x collision radius
GROUND, BOUNDS, GATE, DRONE = (COLLISION_KINDS[k] for k in ("ground", "bounds", "gate", "drone"))


def one_substep(make_world, cf2x, positions: list[list[float]], *, drones: int = 1, **sim) -> object:
    """A world per ``drones`` consecutive positions, at rest at hover rpm, stepped by one physics substep."""
    world = make_world(world_count=len(positions) // drones, drones=drones, control_mode="rpm", ctrl_hz=240, **sim)
    world.reset_all(np.array(positions))
    world.cmd.fill_(cf2x.hover_rpm)
    world.step()
    return world


def test_ground_and_bounds_contacts(make_world, cf2x):
    """Flag the ground below one radius and the arena outside its box, each with its own bit and crash time."""
    positions = [[0, 1.5, R - 0.01], [0, 1.5, R + 0.01], [4.01, 1.5, 1], [-1, -4.01, 1], [-1, 1.5, 4.01], [1, 1.5, 3.9]]
    world = one_substep(make_world, cf2x, positions)
    assert world.race.step_collision.numpy().tolist() == [GROUND, 0, BOUNDS, BOUNDS, BOUNDS, 0]
    assert world.race.out.numpy().tolist() == [1, 0, 1, 1, 1, 0]
    np.testing.assert_allclose(world.race.crash_time.numpy()[[0, 2, 3, 4]], DT, rtol=1e-6)


def test_sphere_touches_gate_bars_only(kernels, make_world, gate_track):
    """Touch each of the four bars from any side up to one radius away, never from the opening's free middle."""
    world = make_world()
    c = np.array(gate_track.gates[0].position)
    h, b = gate_track.opening / 2, gate_track.bar
    edge = h + b  # outer edge of the frame
    local = {  # (x along the normal, y, z) in the gate frame: expected contact
        (0, 0, h + b / 2): 1,  # inside the top bar
        (0, 0, -(h + b / 2)): 1,  # bottom bar
        (0, h + b / 2, 0): 1,  # side bars
        (0, -(h + b / 2), 0): 1,
        (0, 0, edge + R - 0.002): 1,  # above the top bar, just within one radius
        (0, 0, edge + R + 0.002): 0,
        (0, h - R + 0.002, 0): 1,  # inside the opening, next to a side bar
        (0, h - R - 0.002, 0): 0,
        (b / 2 + R - 0.002, h + b / 2, 0): 1,  # in front of a side bar
        (b / 2 + R + 0.002, h + b / 2, 0): 0,
        (0, edge + 0.04, edge + 0.04): 1,  # outside the outer corner: 0.057 m from it
        (0, edge + 0.045, edge + 0.045): 0,  # 0.064 m from it
        (0, 0, 0): 0,
        (0.2, 0.1, -0.1): 0,
    }
    pos = c + np.array(list(local), float)  # gate 0 is axis-aligned
    got = kernels.gate_overlap(world, pos, np.zeros(len(pos), int), R)
    assert got.tolist() == list(local.values())


def test_sphere_touches_rotated_gate_bars(kernels, make_world, circuit6):
    """Find the bars of circuit6's tilted and yawed gates in their own frames."""
    world = make_world(track=circuit6)
    h, b = circuit6.opening / 2, circuit6.bar
    pos, gate, expected = [], [], []
    for g in range(len(circuit6.gates)):
        c, rot = circuit6.gate_centers()[g], circuit6.gate_rotations()[g]
        for p_local, e in (((0, 0, h + b / 2), 1), ((0, -(h + b / 2), 0), 1), ((0, 0, 0), 0),
                           ((0, h - R - 0.002, 0), 0), ((0, 0, h + b + R - 0.002), 1), ((0.12, 0, h + b / 2), 0)):
            pos.append(c + rot @ np.array(p_local)), gate.append(g), expected.append(e)
    assert kernels.gate_overlap(world, np.array(pos), np.array(gate), R).tolist() == expected


def test_drone_contact_within_world_only(make_world, cf2x):
    """Flag two drones of one world closer than two radii, and never drones of different worlds."""
    positions = [[-2, 1.5, 1], [-2, 1.5 + 2 * R - 0.005, 1],  # world 0: touching
                 [-2, 1.5, 1], [-2, 1.5 + 2 * R + 0.005, 1],  # world 1: apart
                 [-2, 1.5, 1], [-2, 1.0, 1]]  # world 2: its first drone sits where world 0's and 1's do
    world = one_substep(make_world, cf2x, positions, drones=2)
    assert world.race.step_collision.numpy().tolist() == [DRONE, DRONE, 0, 0, 0, 0]


def test_drone_contact_with_three_per_world(make_world, cf2x):
    """Flag only the touching pair among three drones of a world (any layout works)."""
    positions = [[-2, 1.5, 1], [-2, 1.6, 1], [-2, 2.5, 1]]
    world = one_substep(make_world, cf2x, positions, drones=3)
    assert world.race.step_collision.numpy().tolist() == [DRONE, DRONE, 0]


@pytest.mark.parametrize("freeze", [True, False])
def test_crashed_drones_freeze_only_when_configured(make_world, cf2x, freeze):
    """Hold a crashed drone still with zero velocity when freeze_crashed, else let it fly on; report the crash once."""
    world = make_world(world_count=2, control_mode="rpm", freeze_crashed=freeze)
    world.reset_all(np.array([[-2.0, 1.5, R + 0.01], [2.0, 1.5, 1.0]]))
    world.state.vel.assign(np.float32([[1.0, 0.0, -1.0], [1.0, 0.0, 0.0]]))
    world.cmd.fill_(cf2x.hover_rpm)
    world.step()
    assert world.race.out.numpy().tolist() == [1, 0]
    crash_pos = world.state.pos.numpy()[0].copy()
    assert world.race.crash_time.numpy()[0] == pytest.approx(3 * DT, rel=1e-6)  # z = 0.07 − k/240 < R at k = 3
    world.step()
    pos, vel = world.state.pos.numpy(), world.state.vel.numpy()
    assert world.race.step_collision.numpy().tolist() == [0, 0]  # a crashed drone has no further contacts
    if freeze:
        np.testing.assert_allclose(pos[0], crash_pos, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(vel[0], [0.0, 0.0, 0.0], rtol=0, atol=1e-12)
    else:
        assert pos[0, 0] > crash_pos[0] + 0.01
    assert pos[1, 0] > 2.03  # the other world flies on either way
