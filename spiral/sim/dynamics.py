"""Rigid-body quadrotor dynamics, integrated with semi-implicit Euler, behind the low-level controller."""

from __future__ import annotations

import warp as wp

from spiral.sim.options import MODULE_OPTIONS
from spiral.sim.pid import pid_position_control, rpm_passthrough
from spiral.sim.rotations import quat_integrate
from spiral.sim.state import QuadParams

__all__ = ["all_finite", "body_wrench", "control_and_integrate", "downwash_force", "drone_downwash",
           "ground_effect_factor"]

wp.set_module_options(MODULE_OPTIONS)

FLOAT32_MAX = wp.constant(wp.float32(3.4028234663852886e38))


@wp.func
def all_finite(v: wp.vec3) -> bool:
    """Whether every component is finite: |x| <= the largest float32 is false for ±inf and for NaN (a comparison
    with NaN is false). Three comparisons where ``wp.isfinite`` calls out of the kernel once per component (on the
    CPU, through a function pointer, with a conversion to double)."""
    return wp.abs(v[0]) <= FLOAT32_MAX and wp.abs(v[1]) <= FLOAT32_MAX and wp.abs(v[2]) <= FLOAT32_MAX


@wp.func
def body_wrench(rpm: wp.vec4, p: QuadParams) -> wp.vec4:
    """Collective thrust [N] and body torques [N·m] of four motor speeds: (T, τx, τy, τz)."""
    f1 = p.kf * rpm[0] * rpm[0]
    f2 = p.kf * rpm[1] * rpm[1]
    f3 = p.kf * rpm[2] * rpm[2]
    f4 = p.kf * rpm[3] * rpm[3]
    tau_x = p.arm_xy * (-f1 - f2 + f3 + f4)
    tau_y = p.arm_xy * (-f1 + f2 + f3 - f4)
    tau_z = p.km / p.kf * (-f1 + f2 - f3 + f4)
    return wp.vec4(f1 + f2 + f3 + f4, tau_x, tau_y, tau_z)


@wp.func
def ground_effect_factor(height: wp.float32, tilt_cos: wp.float32, p: QuadParams) -> wp.float32:
    """Thrust gain in ground effect, Cheeseman–Bennett: T_IGE / T_OGE = 1 / (1 − (R / 4z)²), z ≥ R/2."""
    if tilt_cos <= 0.0:
        return 1.0
    ratio = p.prop_radius / (4.0 * wp.max(height, 0.5 * p.prop_radius))
    return 1.0 / (1.0 - ratio * ratio)


@wp.func
def downwash_force(pos: wp.vec3, other: wp.vec3, p: QuadParams) -> wp.float32:
    """Downward force [N] from a drone above (empirical model of gym-pybullet-drones, fitted on Crazyflies)."""
    dz = other[2] - pos[2]
    if dz <= 0.0:
        return 0.0
    dz = wp.max(dz, 2.0 * p.radius)
    dxy = wp.length(wp.vec3(other[0] - pos[0], other[1] - pos[1], 0.0))
    alpha = 2267.18 * (p.prop_radius / (4.0 * dz)) * (p.prop_radius / (4.0 * dz))
    beta = 0.16 * dz - 0.11
    return alpha * wp.exp(-0.5 * (dxy / beta) * (dxy / beta))


@wp.kernel
def control_and_integrate(
    pos: wp.array[wp.vec3],
    vel: wp.array[wp.vec3],
    quat: wp.array[wp.quat],
    omega: wp.array[wp.vec3],
    rpm: wp.array[wp.vec4],
    cmd: wp.array[wp.vec4],
    heading: wp.array[wp.vec2],
    integral: wp.array[wp.vec3],
    out: wp.array[wp.int32],
    ext_force: wp.array[wp.vec3],
    params: QuadParams,
    control_mode: wp.int32,
    drones_per_world: wp.int32,
    dt: wp.float32,
    prev_pos: wp.array[wp.vec3],
    world_nonfinite: wp.array[wp.int32],
):
    """Run the low-level controller and advance each drone one physics step, in place.

    The controller (``pid.py``) and the rigid body share one launch: both read the same state, and fusing them
    saves about a third of the substep's time on a CPU. Each thread touches only its own drone, so the in-place
    update is race-free; cross-drone reads (contacts, downwash) happen in separate launches. ``heading`` holds
    (cos ψ*, sin ψ*) of the commanded yaw (``pid.command_heading``, once per control step; unused in rpm mode).

    Newton: m·a = R·(0, 0, T) − K_d·v − m·g·z (+ ground effect, + ``ext_force`` from downwash). Euler:
    I·ω̇ = τ − ω × I·ω. Semi-implicit Euler: v and ω first, then p and q with the new rates. A non-finite
    result is not written; the world is flagged instead.
    """
    tid = wp.tid()
    p0 = pos[tid]
    prev_pos[tid] = p0
    if out[tid] != 0 and params.freeze_crashed != 0:
        vel[tid] = wp.vec3(0.0)
        omega[tid] = wp.vec3(0.0)
        return
    q = quat[tid]
    rot = wp.quat_to_matrix(q)
    v = vel[tid]
    w = omega[tid]
    motor = wp.vec4(0.0)
    if control_mode == 0:
        motor = pid_position_control(p0, v, rot, w, cmd[tid], heading[tid], integral, tid, params, dt)
    else:
        motor = rpm_passthrough(cmd[tid], params)
    if params.motor_lag != 0:
        motor = rpm[tid] + (motor - rpm[tid]) * (1.0 - wp.exp(-dt / params.motor_tau))
    wrench = body_wrench(motor, params)
    z_body = wp.vec3(rot[0, 2], rot[1, 2], rot[2, 2])
    thrust = wrench[0]
    if params.ground_effect != 0:
        thrust = thrust * ground_effect_factor(p0[2], z_body[2], params)
    force = z_body * thrust - wp.cw_mul(params.drag, v) - wp.vec3(0.0, 0.0, params.mass * params.gravity)
    if params.downwash != 0:
        force = force + ext_force[tid]
    v_new = v + force * (dt / params.mass)
    torque = wp.vec3(wrench[1], wrench[2], wrench[3])
    w_new = w + wp.cw_div(torque - wp.cross(w, wp.cw_mul(params.inertia, w)), params.inertia) * dt
    p_new = p0 + v_new * dt
    q_new = quat_integrate(q, w_new, dt)
    # a quaternion whose norm overflowed normalises to (0, 0, 0, 0), which is finite: count it as non-finite too
    ok = all_finite(p_new) and all_finite(v_new) and all_finite(w_new) and wp.length_sq(q_new) > 0.5
    if not ok:
        world_nonfinite[tid / drones_per_world] = 1
        return
    pos[tid] = p_new
    vel[tid] = v_new
    quat[tid] = q_new
    omega[tid] = w_new
    rpm[tid] = motor


@wp.kernel
def drone_downwash(
    pos: wp.array[wp.vec3],
    out: wp.array[wp.int32],
    params: QuadParams,
    drones_per_world: wp.int32,
    ext_force: wp.array[wp.vec3],
):
    """Sum the downwash of every other flying drone of the world on each drone (before the dynamics launch)."""
    tid = wp.tid()
    first = (tid / drones_per_world) * drones_per_world
    force = wp.vec3(0.0)
    for j in range(first, first + drones_per_world):
        if j != tid and out[j] == 0:
            force = force - wp.vec3(0.0, 0.0, downwash_force(pos[tid], pos[j], params))
    ext_force[tid] = force
