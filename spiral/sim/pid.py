"""Cascaded controller: position PID -> thrust vector and attitude -> attitude PD -> torques -> mixer -> rpm."""

from __future__ import annotations

import warp as wp

from spiral.sim.options import MODULE_OPTIONS
from spiral.sim.state import QuadParams

__all__ = ["attitude_torque", "command_heading", "desired_acceleration", "mix", "pid_position_control",
           "rpm_passthrough"]

wp.set_module_options(MODULE_OPTIONS)


@wp.func
def mix(thrust: wp.float32, torque: wp.vec3, p: QuadParams) -> wp.vec4:
    """Motor speeds for a collective thrust [N] and body torque [N·m], each motor clipped to its range.

    Motors (X frame, body x forward): 1 front-right, 2 back-right, 3 back-left, 4 front-left; 1 and 3 spin
    so that their reaction torque is −z. The allocation's rows are orthogonal, so its inverse is its transpose / 4.
    """
    tx = torque[0] / p.arm_xy
    ty = torque[1] / p.arm_xy
    tz = torque[2] * p.kf / p.km
    f1 = 0.25 * (thrust - tx - ty - tz)
    f2 = 0.25 * (thrust - tx + ty + tz)
    f3 = 0.25 * (thrust + tx + ty - tz)
    f4 = 0.25 * (thrust + tx - ty + tz)
    f_max = p.kf * p.max_rpm * p.max_rpm
    return wp.vec4(
        wp.sqrt(wp.clamp(f1, 0.0, f_max) / p.kf),
        wp.sqrt(wp.clamp(f2, 0.0, f_max) / p.kf),
        wp.sqrt(wp.clamp(f3, 0.0, f_max) / p.kf),
        wp.sqrt(wp.clamp(f4, 0.0, f_max) / p.kf),
    )


@wp.func
def desired_acceleration(err: wp.vec3, integral: wp.vec3, vel: wp.vec3, p: QuadParams) -> wp.vec3:
    """PID acceleration plus gravity compensation, with the tilt and norm limited so the drone cannot flip."""
    acc = wp.cw_mul(p.pos_p, err) + wp.cw_mul(p.pos_i, integral) - wp.cw_mul(p.pos_d, vel)
    acc = acc + wp.vec3(0.0, 0.0, p.gravity) + wp.cw_div(wp.cw_mul(p.drag, vel), wp.vec3(p.mass))
    az = wp.max(acc[2], 0.3 * p.gravity)
    horizontal = wp.vec3(acc[0], acc[1], 0.0)
    h_norm = wp.length(horizontal)
    h_max = az * p.tan_max_tilt
    if h_norm > h_max:
        horizontal = horizontal * (h_max / h_norm)
    acc = horizontal + wp.vec3(0.0, 0.0, az)
    norm = wp.length(acc)
    if norm > p.max_accel:
        acc = acc * (p.max_accel / norm)
    return acc


@wp.func
def attitude_torque(rot: wp.mat33, z_des: wp.vec3, heading: wp.vec2, omega: wp.vec3, p: QuadParams) -> wp.vec3:
    """Geometric attitude PD on SO(3) (Lee et al. 2010) with the gyroscopic term cancelled; ``heading`` is
    (cos ψ*, sin ψ*) of the commanded yaw ψ*."""
    x_c = wp.vec3(heading[0], heading[1], 0.0)
    y_des = wp.normalize(wp.cross(z_des, x_c))
    x_des = wp.cross(y_des, z_des)
    rot_des = wp.matrix_from_cols(x_des, y_des, z_des)
    m = wp.transpose(rot_des) * rot  # e_R = ½·vee(M − Mᵀ), M = R_dᵀ·R
    e_rot = 0.5 * wp.vec3(m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1])
    ang_acc = -wp.cw_mul(p.att_p, e_rot) - wp.cw_mul(p.att_d, omega)
    return wp.cw_mul(p.inertia, ang_acc) + wp.cross(omega, wp.cw_mul(p.inertia, omega))


@wp.func
def pid_position_control(
    pos: wp.vec3,
    vel: wp.vec3,
    rot: wp.mat33,
    omega: wp.vec3,
    cmd: wp.vec4,
    heading: wp.vec2,
    integral: wp.array[wp.vec3],
    tid: wp.int32,
    params: QuadParams,
    dt: wp.float32,
) -> wp.vec4:
    """Motor speeds that steer towards the target position of ``cmd`` and the yaw whose ``heading``
    (cos ψ*, sin ψ*) :func:`command_heading` computed; advances the position integral."""
    err = wp.vec3(cmd[0], cmd[1], cmd[2]) - pos
    lim = wp.vec3(params.pos_i_limit)
    integ = wp.min(wp.max(integral[tid] + err * dt, -lim), lim)
    integral[tid] = integ
    acc = desired_acceleration(err, integ, vel, params)
    z_body = wp.vec3(rot[0, 2], rot[1, 2], rot[2, 2])
    thrust = params.mass * wp.max(wp.dot(acc, z_body), 0.0)
    torque = attitude_torque(rot, wp.normalize(acc), heading, omega, params)
    return mix(thrust, torque, params)


@wp.kernel
def command_heading(cmd: wp.array[wp.vec4], heading: wp.array[wp.vec2]):
    """(cos ψ*, sin ψ*) of each drone's commanded yaw, once per control step: the command holds for all its
    substeps, so the controller need not take the sine and cosine in every one."""
    tid = wp.tid()
    yaw = cmd[tid][3]
    heading[tid] = wp.vec2(wp.cos(yaw), wp.sin(yaw))


@wp.func
def rpm_passthrough(cmd: wp.vec4, params: QuadParams) -> wp.vec4:
    """Direct motor-speed command, clipped to the motor range."""
    return wp.min(wp.max(cmd, wp.vec4(0.0)), wp.vec4(params.max_rpm))
