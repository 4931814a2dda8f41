"""Gate crossing: swept segment through the opening, forward only, in order, with the time interpolated."""

from __future__ import annotations

import numpy as np
import pytest

from spiral.sim.state import COLLISION_KINDS

DT = 1.0 / 240.0


def gate_frame(track, g: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Centre, passing direction, local y and local z axes of gate ``g``."""
    rot = track.gate_rotations()[g]
    return track.gate_centers()[g], track.gate_forward()[g], rot[:, 1], rot[:, 2]


def test_segment_crossing_on_hand_made_paths(kernels, make_world, gate_track):
    """Pass forward through the opening at the right fraction; reject backward, beside, bar, short, wrong-gate paths."""
    world = make_world()
    c, fwd, y, z = gate_frame(gate_track, 0)
    half, bar = gate_track.opening / 2, gate_track.bar
    paths = {  # name: (p0, p1, gate, expected fraction)
        "forward centre": (c - 0.03 * fwd, c + 0.09 * fwd, 0, 0.25),
        "forward near corner": (c - 0.1 * fwd + 0.28 * y - 0.28 * z, c + 0.1 * fwd + 0.28 * y - 0.28 * z, 0, 0.5),
        "backward": (c + 0.1 * fwd, c - 0.1 * fwd, 0, -1.0),
        "beside the frame": (c - 0.1 * fwd + 0.6 * y, c + 0.1 * fwd + 0.6 * y, 0, -1.0),
        "above the frame": (c - 0.1 * fwd + 0.6 * z, c + 0.1 * fwd + 0.6 * z, 0, -1.0),
        "through the side bar": (c - 0.1 * fwd + (half + bar / 2) * y, c + 0.1 * fwd + (half + bar / 2) * y, 0, -1.0),
        "through the top bar": (c - 0.1 * fwd + (half + bar / 2) * z, c + 0.1 * fwd + (half + bar / 2) * z, 0, -1.0),
        "stops short": (c - 0.1 * fwd, c - 0.01 * fwd, 0, -1.0),
        "starts past": (c + 0.01 * fwd, c + 0.1 * fwd, 0, -1.0),
        "ends on the plane": (c - 0.1 * fwd, c, 0, 1.0),
        "through gate 0 testing gate 1": (c - 0.1 * fwd, c + 0.1 * fwd, 1, -1.0),
    }
    p0, p1, gate, expected = (np.array(v) for v in zip(*paths.values(), strict=True))
    got = kernels.segment_crossing(world, p0, p1, gate)
    for name, g, e in zip(paths, got, expected, strict=True):
        assert g == pytest.approx(e, abs=1e-5), name


def test_reversed_gate_is_passed_along_minus_x(kernels, make_world, gate_track):
    """Pass gate 1 (direction −1) only when moving along −x."""
    world = make_world()
    c = gate_track.gate_centers()[1]
    step = np.array([0.1, 0.0, 0.0])
    east, west = c - step, c + step
    got = kernels.segment_crossing(world, np.array([east, west]), np.array([west, east]), np.array([1, 1]))
    np.testing.assert_allclose(got, [-1.0, 0.5], atol=1e-6)


def test_rotated_gates_of_circuit6(kernels, make_world, circuit6):
    """Pass every tilted, yawed gate of circuit6 along its forward axis only, inside the opening only."""
    world = make_world(track=circuit6)
    p0, p1, gate, expected = [], [], [], []
    for g in range(len(circuit6.gates)):
        c, fwd, y, z = gate_frame(circuit6, g)
        offset = 0.2 * y - 0.25 * z
        for a, b, e in ((c - 0.06 * fwd + offset, c + 0.18 * fwd + offset, 0.25),
                        (c + 0.06 * fwd + offset, c - 0.18 * fwd + offset, -1.0),
                        (c - 0.06 * fwd + 0.45 * z, c + 0.18 * fwd + 0.45 * z, -1.0)):
            p0.append(a), p1.append(b), gate.append(g), expected.append(e)
    got = kernels.segment_crossing(world, np.array(p0), np.array(p1), np.array(gate))
    np.testing.assert_allclose(got, expected, atol=1e-5)


def fly_straight(make_world, cf2x_no_drag, start: list[float], vel: list[float], *, steps: int = 1, drones: int = 1):
    """A world whose drones coast in a straight line: hover rpm cancels gravity, drag is off."""
    world = make_world(airframe=cf2x_no_drag, drones=drones, control_mode="rpm")
    world.reset_all(np.array(start).reshape(-1, 3))
    world.state.vel.assign(np.array(vel, np.float32).reshape(-1, 3))
    world.cmd.fill_(cf2x_no_drag.hover_rpm)
    for _ in range(steps):
        world.step()
    return world


def test_world_reports_forward_pass_with_interpolated_time(make_world, cf2x_no_drag):
    """Report a pass of gate 0 at t = 0.12 m / 12 m/s = 10 ms, inside substep 3 of the first control step."""
    world = fly_straight(make_world, cf2x_no_drag, [-0.12, 0.1, 1.4], [12.0, 0.0, 0.0])
    r = world.race
    assert r.step_passes.numpy()[0] == 1
    assert r.gates_passed.numpy()[0] == 1
    assert r.next_gate.numpy()[0] == 1
    assert r.pass_time.numpy()[0] == pytest.approx(0.01, abs=1e-6)
    assert r.step_collision.numpy()[0] == 0
    assert r.out.numpy()[0] == 0


def test_world_ignores_backward_beside_and_bar_paths(make_world, cf2x_no_drag):
    """Pass nothing flying backward, beside the frame or into a bar; the bar alone is a gate collision."""
    gate = COLLISION_KINDS["gate"]
    start = [[0.12, 0.0, 1.5], [-0.12, 0.8, 1.5], [-0.14, 0.325, 1.5]]  # backward, beside, into the side bar
    vel = [[-12.0, 0.0, 0.0], [12.0, 0.0, 0.0], [12.0, 0.0, 0.0]]
    worlds = [fly_straight(make_world, cf2x_no_drag, s, v) for s, v in zip(start, vel, strict=True)]
    assert [w.race.gates_passed.numpy()[0] for w in worlds] == [0, 0, 0]
    assert [w.race.next_gate.numpy()[0] for w in worlds] == [0, 0, 0]
    assert [w.race.step_collision.numpy()[0] for w in worlds] == [0, 0, gate]
    bar_world = worlds[2]
    assert bar_world.race.out.numpy()[0] == 1
    # x = −0.14 + 0.05·k; the sphere (r = 0.06) touches the bar (faces at x = ±0.025) once x > −0.085: k = 2
    assert bar_world.race.crash_time.numpy()[0] == pytest.approx(2 * DT, abs=1e-6)


def test_gates_count_in_order_only(make_world, cf2x_no_drag):
    """Skip a pass of gate 1 while gate 0 is next, then count gate 0 and gate 1 in turn."""
    world = fly_straight(make_world, cf2x_no_drag, [0.12, 3.0, 1.5], [-12.0, 0.0, 0.0])  # gate 1 first
    assert world.race.gates_passed.numpy()[0] == 0
    world = fly_straight(make_world, cf2x_no_drag, [[-0.12, 0.0, 1.5], [0.12, 3.0, 1.5]],
                         [[12.0, 0.0, 0.0], [-12.0, 0.0, 0.0]], drones=2)
    assert world.race.gates_passed.numpy().tolist() == [1, 0]
    world.state.pos.assign(np.float32([[0.12, 3.0, 1.5], [0.3, -2.0, 1.5]]))  # drone 0 now lines up for gate 1
    world.state.vel.assign(np.float32([[-12.0, 0.0, 0.0], [0.0, 0.0, 0.0]]))
    world.step()
    assert world.race.gates_passed.numpy().tolist() == [2, 0]
    assert world.race.next_gate.numpy().tolist() == [0, 0]


def test_crashed_drone_passes_no_gate(make_world, cf2x_no_drag):
    """Ignore a crashed drone's path through the opening."""
    world = make_world(airframe=cf2x_no_drag, control_mode="rpm", freeze_crashed=False)
    world.reset_all(np.array([[-0.12, 0.0, 1.5]]))
    world.state.vel.assign(np.float32([[12.0, 0.0, 0.0]]))
    world.race.out.fill_(1)
    world.cmd.fill_(cf2x_no_drag.hover_rpm)
    world.step()
    assert world.state.pos.numpy()[0, 0] > 0.1  # it did fly through
    assert world.race.gates_passed.numpy()[0] == 0
