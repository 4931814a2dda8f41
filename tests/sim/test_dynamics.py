"""Rigid-body dynamics in rpm mode: closed forms of the integrator, hover, pure yaw torque, optional terms."""

from __future__ import annotations

import math

import numpy as np

G = 9.81
DT = 1.0 / 240.0


def test_free_fall_matches_semi_implicit_euler(make_world, cf2x_no_drag, run):
    """Fall with zero rpm and no drag along z_N = z0 − g·dt²·N(N+1)/2 and v_N = −g·dt·N."""
    world = make_world(airframe=cf2x_no_drag, control_mode="rpm", freeze_crashed=False)
    world.reset_all(np.array([[0.5, -1.0, 3.0]]))
    out = run(world, np.zeros((20, 1, 4)))
    n = 5 * np.arange(1, 21)
    z_expected = 3.0 - G * DT**2 * n * (n + 1) / 2
    # float32 rounding of p += v·dt over 100 substeps at |z| ≤ 3 m: ≤ 100 · 2.4e-7 m
    np.testing.assert_allclose(out["pos"][:, 0, 2], z_expected, atol=3e-5, rtol=0)
    np.testing.assert_allclose(out["vel"][:, 0, 2], -G * DT * n, atol=1e-5, rtol=0)
    np.testing.assert_allclose(  # no force moves x, y: kept
        out["pos"][:, 0, :2], np.tile([0.5, -1.0], (20, 1)).astype(np.float32), rtol=1e-6, atol=1e-9)
    # no rotation: x, y, z stay at 0; w may sit one float32 step below 1, since the sim modules compile with
    # -freciprocal-math and the renormalisation's division by |q| = 1 then becomes a product with 1/|q| ≈ 1 − 2⁻²⁴
    np.testing.assert_allclose(out["quat"][:, 0, :3], 0.0, rtol=0, atol=1e-12)  # no torque: x, y, z kept at 0
    np.testing.assert_allclose(out["quat"][:, 0, 3], 1.0, atol=float(np.finfo(np.float32).epsneg), rtol=0)


def test_hover_rpm_holds_altitude(make_world, cf2x, run):
    """Keep altitude within 1 mm over 2 s at hover rpm: thrust m·g gives zero acceleration."""
    world = make_world(control_mode="rpm")
    world.reset_all(np.array([[0.0, 0.0, 1.0]]))
    out = run(world, np.full((96, 1, 4), cf2x.hover_rpm))
    assert np.abs(out["pos"][:, 0, 2] - 1.0).max() < 1e-3
    assert np.abs(out["pos"][:, 0, :2]).max() < 1e-6
    assert np.abs(out["vel"][-1, 0]).max() < 1e-3


def test_pure_yaw_torque_leaves_position(make_world, cf2x, run):
    """Spin up yaw at hover thrust without moving: opposite pairs at m·g/4 ∓ δ give τz only."""
    world = make_world(airframe=cf2x, control_mode="rpm")
    world.reset_all(np.array([[0.0, 0.0, 1.0]]))
    f_hover, delta = cf2x.mass * G / 4, 0.05 * cf2x.mass * G / 4
    rpm = np.sqrt(np.array([f_hover - delta, f_hover + delta, f_hover - delta, f_hover + delta]) / cf2x.kf)
    out = run(world, np.tile(rpm, (24, 1, 1)))
    yaw_acc = 4 * delta * cf2x.km / cf2x.kf / cf2x.inertia[2]
    n = 24 * 5  # semi-implicit Euler: ω_N = α·dt·N, ψ_N = α·dt²·N(N+1)/2
    assert math.isclose(out["omega"][-1, 0, 2], yaw_acc * DT * n, rel_tol=1e-5)
    assert math.isclose(out["rpy"][-1, 0, 2], yaw_acc * DT**2 * n * (n + 1) / 2, rel_tol=1e-4)
    # rounding of the four rpm to float32 leaves |τx|, |τy| ~ 1e-7 of the thrust torque: drift ≪ 1e-5 m in 0.5 s
    assert np.abs(out["pos"][:, 0] - [0.0, 0.0, 1.0]).max() < 1e-5
    assert np.abs(out["rpy"][:, 0, :2]).max() < 1e-4


def test_quaternion_stays_unit_under_random_commands(make_world, run, targets):
    """Keep |q| = 1 within 1e-5 over 4 s of random PID targets in 4 worlds × 2 drones."""
    world = make_world(world_count=4, drones=2, freeze_crashed=False)
    rng = np.random.default_rng(3)
    world.reset_all(rng.uniform([-2, -2, 1], [2, 2, 2], (8, 3)), rng.uniform(-3, 3, 8))
    out = run(world, targets(rng, 192, 8, hold=6))
    norms = np.linalg.norm(out["quat"].astype(np.float64), axis=2)
    assert np.abs(norms - 1.0).max() < 1e-5
    assert np.abs(out["omega"]).max() > 1.0  # the commands did rotate the drones


def test_tumbling_overflow_is_flagged_not_stored(make_world, cf2x, run):
    """Flag a world whose open-loop tumbling overflows, and keep every stored quaternion a unit one.

    Random motor speeds spin the drones up until explicit Euler on the gyroscopic term diverges (|ω|·dt ≫ 1); the
    normalisation of the quaternion then overflows to (0, 0, 0, 0), which must count as non-finite.
    """
    world = make_world(world_count=4, drones=1, control_mode="rpm", freeze_crashed=False)
    rng = np.random.default_rng(5)
    world.reset_all(np.tile([0.0, 0.0, 2.0], (4, 1)))
    out = run(world, rng.uniform(0, cf2x.max_rpm, (1000, 4, 4)))
    flagged = world.race.world_nonfinite.numpy()
    assert flagged.sum() >= 1  # which worlds diverge first depends on rounding; with this seed, 0 and 3 here
    spun_up = np.abs(out["omega"]).max(axis=(0, 2)) > 1e3
    assert (flagged[~spun_up] == 0).all()  # only runaway worlds are flagged
    assert np.abs(np.linalg.norm(out["quat"].astype(np.float64), axis=2) - 1).max() < 1e-5
    assert all(np.isfinite(out[k]).all() for k in ("pos", "vel", "quat"))


def test_no_nan_after_1000_random_pid_steps(make_world, run, targets):
    """Stay finite, unflagged and unit-quaternion over 1000 control steps of random PID targets."""
    world = make_world(world_count=4, drones=2, freeze_crashed=False)
    rng = np.random.default_rng(11)
    world.reset_all(rng.uniform([-2, -2, 1], [2, 2, 2], (8, 3)), rng.uniform(-3, 3, 8))
    out = run(world, targets(rng, 1000, 8, hold=5, lo=(-3.0, -3.0, 0.5), hi=(3.0, 3.0, 3.0)))
    assert all(np.isfinite(v).all() for v in out.values())
    assert world.race.world_nonfinite.numpy().tolist() == [0, 0, 0, 0]
    assert np.abs(np.linalg.norm(out["quat"].astype(np.float64), axis=2) - 1).max() < 1e-5


def test_motor_lag_follows_first_order_response(make_world, cf2x, run):
    """Move each motor by (1 − e^(−dt/τ)) of the gap to its command per substep when motor lag is on."""
    world = make_world(control_mode="rpm", motor_lag=True, freeze_crashed=False)
    world.reset_all(np.array([[0.0, 0.0, 2.0]]))
    cmd = np.full((1, 1, 4), cf2x.max_rpm)
    out = run(world, cmd)
    gap = cf2x.max_rpm - cf2x.hover_rpm
    expected = cf2x.max_rpm - gap * math.exp(-5 * DT / cf2x.motor_tau)
    np.testing.assert_allclose(out["rpm"][0, 0], expected, rtol=1e-5)


def test_ground_effect_adds_thrust_near_ground(make_world, cf2x, run):
    """Accelerate up at g·(k − 1) at hover rpm, k = 1 / (1 − (R/4z)²) (Cheeseman–Bennett), first substep."""
    world = make_world(control_mode="rpm", ground_effect=True, freeze_crashed=False, physics_hz=240, ctrl_hz=240)
    z = 0.08
    world.reset_all(np.array([[0.0, 0.0, z]]))
    out = run(world, np.full((1, 1, 4), cf2x.hover_rpm))
    k = 1.0 / (1.0 - (cf2x.prop_radius / (4 * z)) ** 2)
    assert math.isclose(out["vel"][0, 0, 2], G * (k - 1) * DT, rel_tol=1e-3)
    far = make_world(control_mode="rpm", ground_effect=True, physics_hz=240, ctrl_hz=240)
    far.reset_all(np.array([[0.0, 0.0, 2.0]]))
    assert abs(run(far, np.full((1, 1, 4), cf2x.hover_rpm))["vel"][0, 0, 2]) < 1e-3 * G * DT


def test_downwash_pushes_lower_drone_down(make_world, cf2x, run):
    """Push the lower of two stacked drones down by α·exp(−½(dxy/β)²) and leave the upper one alone."""
    world = make_world(drones=2, control_mode="rpm", downwash=True, freeze_crashed=False, physics_hz=240, ctrl_hz=240)
    dz, dxy = 0.3, 0.02
    world.reset_all(np.array([[0.0, 0.0, 1.0], [dxy, 0.0, 1.0 + dz]]))
    out = run(world, np.full((1, 2, 4), cf2x.hover_rpm))
    alpha = 2267.18 * (cf2x.prop_radius / (4 * dz)) ** 2
    beta = 0.16 * dz - 0.11
    force = alpha * math.exp(-0.5 * (dxy / beta) ** 2)
    assert math.isclose(out["vel"][0, 0, 2], -force / cf2x.mass * DT, rel_tol=1e-4)
    assert abs(out["vel"][0, 1, 2]) < 1e-6


def test_the_finite_check_rejects_nan_and_both_infinities_and_keeps_the_largest_floats(kernels):
    """``all_finite`` (the kernel's health check) agrees with numpy on finite extremes, ±inf and NaN per component."""
    big, tiny = np.finfo(np.float32).max, np.finfo(np.float32).smallest_subnormal
    rows = np.array([[0.0, -0.0, 1.0], [big, -big, tiny], [np.inf, 0.0, 0.0], [0.0, -np.inf, 0.0],
                     [0.0, 0.0, np.nan], [np.nan, np.inf, -np.inf]], dtype=np.float32)
    np.testing.assert_array_equal(kernels.all_finite(rows), np.isfinite(rows).all(axis=1))  # exact: booleans
