"""Rotation helpers shared by the kernels."""

from __future__ import annotations

import warp as wp

__all__ = ["quat_integrate", "quat_to_rpy", "yaw_quat"]


@wp.func
def quat_integrate(q: wp.quat, omega_body: wp.vec3, dt: wp.float32) -> wp.quat:
    """Rotate ``q`` by body rates held for ``dt``: q ⊗ (½·ω·dt, 1), renormalised.

    Matches the exact exponential map to O((|ω|·dt)³) per step: below 1e-5 rad at 240 Hz and 10 rad/s.
    """
    h = omega_body * (0.5 * dt)
    return wp.normalize(q * wp.quat(h[0], h[1], h[2], 1.0))


@wp.func
def quat_to_rpy(q: wp.quat) -> wp.vec3:
    """Roll, pitch, yaw [rad] of R = Rz(yaw)·Ry(pitch)·Rx(roll)."""
    x, y, z, w = q[0], q[1], q[2], q[3]
    roll = wp.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = wp.asin(wp.clamp(2.0 * (w * y - z * x), -1.0, 1.0))
    yaw = wp.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return wp.vec3(roll, pitch, yaw)


@wp.func
def yaw_quat(yaw: wp.float32) -> wp.quat:
    """Level attitude with heading ``yaw`` [rad]."""
    return wp.quat_from_axis_angle(wp.vec3(0.0, 0.0, 1.0), yaw)
