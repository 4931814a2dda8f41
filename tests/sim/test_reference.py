"""The numpy reference against the Warp kernels: trajectories, optional terms, contacts, gate crossings, health."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from spiral.config import SimCfg
from spiral.sim.collisions import detect_collisions_and_gate_passes
from spiral.sim.reference import GateArrays, ReferenceSim, contact_bits, segment_gate_crossing

EPS32 = float(np.finfo(np.float32).eps)
STATE = ("pos", "vel", "quat", "omega", "thrust")


def state_of(arrays: dict[str, np.ndarray], kf: float) -> dict[str, np.ndarray]:
    """Rigid-body state in float64, with motor thrusts kf·rpm² in place of rpm.

    Thrust, not rpm: rpm = sqrt(f/kf) is not Lipschitz at f = 0, where the mixer often clips, so a rounding-size
    difference in f becomes a large one in rpm while the force it produces stays rounding-size.
    """
    out = {k: np.asarray(arrays[k], np.float64) for k in ("pos", "vel", "quat", "omega")}
    out["thrust"] = kf * np.asarray(arrays["rpm"], np.float64) ** 2
    return out


def compare(world, ref: ReferenceSim, cmds: np.ndarray) -> dict[str, float]:
    """Step both under ``cmds``; return, per state array, the largest error over its float32 rounding bound.

    The bound after N substeps is N·ε₃₂·X, X the largest magnitude the quantity reaches in the run: each substep
    rounds every quantity at about ε₃₂ of its scale, and the closed loop is stable, so these differences add up
    about linearly instead of growing exponentially. The float64 reference adds no rounding of its own at this scale.
    """
    kf = world.airframe.kf
    errors, peak = {k: [] for k in STATE}, dict.fromkeys(STATE, 0.0)
    for cmd in cmds:
        world.cmd.assign(cmd)
        world.step()
        ref.step(cmd)
        names = ("pos", "vel", "quat", "omega", "rpm")
        got = state_of({k: getattr(world.state, k).numpy() for k in names}, kf)
        want = state_of({k: getattr(ref, k) for k in names}, kf)
        for k in STATE:
            errors[k].append(np.abs(got[k] - want[k]).max())
            peak[k] = max(peak[k], float(np.abs(want[k]).max()))
    substeps = world.sim.substeps * np.arange(1, len(cmds) + 1)
    return {k: float(np.max(np.array(errors[k]) / np.maximum(substeps * EPS32 * peak[k], 1e-30))) for k in STATE}


def paired(make_world, track, *, world_count: int, drones: int, pos: np.ndarray, yaw: np.ndarray, **sim):
    """A Warp world and a float64 reference of the same configuration, reset to the same state."""
    world = make_world(track=track, world_count=world_count, drones=drones, **sim)
    ref = ReferenceSim(world.airframe, world.sim, world.drone_count, track=track, drones_per_world=drones)
    world.reset_all(pos, yaw)
    ref.reset(pos.astype(np.float32), yaw.astype(np.float32))
    return world, ref


def test_warp_matches_reference_over_2s_of_random_targets(make_world, circuit6, targets):
    """Agree with the float64 reference within N·ε₃₂·max|x| on every state over 2 s, with the same events."""
    rng = np.random.default_rng(0)
    pos = rng.uniform([-2.5, -3.0, 0.8], [3.5, 2.0, 2.5], (16, 3))
    world, ref = paired(make_world, circuit6, world_count=4, drones=4, pos=pos, yaw=rng.uniform(-3, 3, 16),
                        freeze_crashed=False)
    cmds = targets(rng, 96, 16, lo=(-2.5, -3.0, 0.8), hi=(3.5, 2.0, 2.5))
    worst = compare(world, ref, cmds)
    assert max(worst.values()) < 1.0, worst
    assert np.array_equal(world.race.out.numpy(), ref.out)  # exact: integer events
    assert np.array_equal(world.race.gates_passed.numpy(), ref.gates_passed)  # exact: integer events
    assert np.array_equal(world.race.next_gate.numpy(), ref.next_gate)  # exact: integer events
    crashed = ref.out == 1
    assert crashed.any()  # gates and contacts were exercised
    np.testing.assert_allclose(world.race.crash_time.numpy()[crashed], ref.crash_time[crashed], atol=1e-6)
    np.testing.assert_allclose(world.rpy.numpy(), ref.rpy, atol=1e-4)


def test_warp_matches_reference_with_optional_terms(make_world, gate_track):
    """Agree within the same bound with ground effect, downwash and motor lag on, drones stacked near the ground."""
    pos = np.array([[-2.0, 1.0, 0.15], [-2.0, 1.02, 0.55], [-1.0, 2.0, 0.3], [-0.98, 2.0, 0.7]])
    world, ref = paired(make_world, gate_track, world_count=2, drones=2, pos=pos, yaw=np.zeros(4),
                        ground_effect=True, downwash=True, motor_lag=True, freeze_crashed=False)
    shift = np.array([0.5, 0.0, 0.1])
    cmds = np.tile(np.c_[pos + shift, np.full(4, 0.5)].astype(np.float32), (48, 1, 1))
    worst = compare(world, ref, cmds)
    # four times the bound: the downwash reaches three weights here and cancels against thrust, so velocity
    # increments are rounded at the scale of these gross forces (≈ 30 m/s² · dt) rather than of |v| (≤ 0.6 m/s)
    assert max(worst.values()) < 4.0, worst
    calm = make_world(track=gate_track, world_count=2, drones=2, freeze_crashed=False)
    calm.reset_all(pos)
    calm.cmd.assign(cmds[0])
    for _ in range(48):
        calm.step()
    assert np.abs(world.state.pos.numpy() - calm.state.pos.numpy()).max() > 1e-3  # the optional terms did act


def test_reference_free_fall_is_exact(cf2x_no_drag):
    """Fall along z_N = z0 − g·dt²·N(N+1)/2 to float64 precision."""
    ref = ReferenceSim(cf2x_no_drag, SimCfg(control_mode="rpm"), 1)
    ref.reset(np.array([[0.0, 0.0, 3.0]]))
    for _ in range(20):
        ref.step(np.zeros((1, 4)))
    n = 100
    assert ref.pos[0, 2] == pytest.approx(3.0 - 9.81 * n * (n + 1) / 2 / 240**2, abs=1e-12)


def test_reference_contacts_match_kernel(kernels, make_world, circuit6):
    """Give the same collision bits as the Warp kernel for 3000 random spheres around circuit6's gates."""
    rng = np.random.default_rng(1)
    centers = circuit6.gate_centers()
    pos = (centers[rng.integers(0, len(centers), 3000)] + rng.uniform(-0.5, 0.5, (3000, 3))).astype(np.float32)
    pos[:40, 2] = rng.uniform(0.0, 0.1, 40)  # some near the ground
    pos[40:80, 0] = rng.uniform(4.3, 4.7, 40)  # some near the x bound (4.5 m)
    crashed = (rng.random(3000) < 0.1).astype(np.int32)
    world = make_world(track=circuit6, drones=3)
    dev = world.device
    out = wp.zeros(3000, dtype=wp.int32, device=dev)
    p = wp.array(pos, dtype=wp.vec3, device=dev)
    counters = [wp.zeros(3000, dtype=wp.int32, device=dev) for _ in range(3)]  # next gate, gates passed, step passes
    wp.launch(detect_collisions_and_gate_passes, 3000,
              inputs=[p, p, wp.array(crashed, dtype=wp.int32, device=dev), world.track, world.params,
                      wp.zeros(1000, dtype=wp.int32, device=dev), wp.zeros(1000, dtype=wp.int32, device=dev), 3, 0,
                      1.0 / 240.0],
              outputs=[out, *counters, wp.zeros(3000, dtype=wp.float32, device=dev)], device=dev)
    expected = out.numpy()
    assert not counters[1].numpy().any()  # standing still, nobody passes a gate
    got = contact_bits(pos, crashed, GateArrays(circuit6, np.float32), np.float32(world.airframe.radius), 3)
    np.testing.assert_array_equal(got, expected)  # exact: integer contact bits
    assert {0, 1, 2, 4, 8} <= set(expected.tolist())  # no contact and each kind alone all occur


def test_reference_gate_crossing_matches_kernel(kernels, make_world, circuit6):
    """Give the same crossing fractions as the Warp function for 3000 random segments through circuit6's gates."""
    rng = np.random.default_rng(2)
    gate = rng.integers(0, len(circuit6.gates), 3000)
    c = circuit6.gate_centers()[gate]
    p0 = c + rng.uniform(-0.5, 0.5, (3000, 3))
    p1 = c + rng.uniform(-0.5, 0.5, (3000, 3))
    world = make_world(track=circuit6)
    expected = kernels.segment_crossing(world, p0, p1, gate)
    gates = GateArrays(circuit6, np.float32)
    got = segment_gate_crossing(p0.astype(np.float32), p1.astype(np.float32), gate, gates)
    np.testing.assert_allclose(got, expected, atol=1e-5)
    assert 100 < (expected >= 0).sum() < 2900


def test_reference_flags_nonfinite_world(cf2x, gate_track):
    """Flag the world of a NaN velocity and keep that drone's stored pose, as the kernel does."""
    ref = ReferenceSim(cf2x, SimCfg(), 4, track=gate_track, drones_per_world=2)
    start = np.array([[-2.0, 1.0, 1.0], [-2.0, 2.0, 1.0], [-3.0, 1.0, 1.0], [-3.0, 2.0, 1.0]])
    ref.reset(start)
    ref.vel[3, 1] = np.nan
    ref.step(np.c_[start, np.zeros(4)])
    assert ref.world_nonfinite.tolist() == [0, 1]
    np.testing.assert_allclose(ref.pos[3], start[3], rtol=1e-6, atol=1e-9)  # the stored pose is kept
    assert np.isfinite(ref.pos).all() and np.isfinite(ref.quat).all()
