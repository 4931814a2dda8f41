"""Plain-numpy reference of the simulator: same dynamics, controller, gate test and contacts, vectorised over drones.

It mirrors the Warp kernels operation by operation (``pid.py``, ``dynamics.py``, ``gates.py``, ``collisions.py``,
launch order of ``World._simulate``), so it serves as the test oracle and as the benchmark's baseline. The default
dtype is float64: as an oracle it then measures the float32 rounding of the Warp kernels rather than adding its own.
The benchmark runs it in float32, its faster setting, so that it moves the same bytes as Warp and the reported
speed-up is not flattered.
"""

from __future__ import annotations

import math

import numpy as np

from spiral.config.airframe import AirframeCfg
from spiral.config.sim import SimCfg
from spiral.config.track import TrackSpec
from spiral.sim.state import COLLISION_KINDS

__all__ = [
    "GateArrays",
    "ReferenceSim",
    "body_wrench",
    "contact_bits",
    "mix",
    "quat_integrate",
    "quat_to_matrix",
    "quat_to_rpy",
    "segment_gate_crossing",
]


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product of ``(n, 3)`` arrays (column sums beat einsum and ``sum(axis=1)`` here)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _dot4(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product of ``(n, 4)`` arrays; NaN rows give NaN, which compares false."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2] + a[:, 3] * b[:, 3]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of ``(n, 3)`` arrays."""
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(n, 3, 3)`` of unit quaternions ``(n, 4)`` in (x, y, z, w) order."""
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    rot = np.empty((len(q), 3, 3), q.dtype)
    rot[:, 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    rot[:, 0, 1] = 2.0 * (x * y - z * w)
    rot[:, 0, 2] = 2.0 * (x * z + y * w)
    rot[:, 1, 0] = 2.0 * (x * y + z * w)
    rot[:, 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    rot[:, 1, 2] = 2.0 * (y * z - x * w)
    rot[:, 2, 0] = 2.0 * (x * z - y * w)
    rot[:, 2, 1] = 2.0 * (y * z + x * w)
    rot[:, 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return rot


def quat_integrate(q: np.ndarray, omega_body: np.ndarray, dt: float) -> np.ndarray:
    """Rotate ``q`` by body rates held for ``dt``: q ⊗ (½·ω·dt, 1), renormalised (as ``rotations.quat_integrate``)."""
    h = omega_body * (0.5 * dt)
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    hx, hy, hz = h[:, 0], h[:, 1], h[:, 2]
    out = np.stack(
        [x + w * hx + y * hz - z * hy, y + w * hy - x * hz + z * hx, z + w * hz + x * hy - y * hx,
         w - x * hx - y * hy - z * hz],
        axis=1,
    )
    return out / np.sqrt(_dot4(out, out))[:, None]


def quat_to_rpy(q: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw ``(n, 3)`` [rad] of R = Rz(yaw)·Ry(pitch)·Rx(roll)."""
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    roll = np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2.0 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return np.stack([roll, pitch, yaw], axis=1)


def mix(thrust: np.ndarray, torque: np.ndarray, kf: float, km: float, arm_xy: float, max_rpm: float) -> np.ndarray:
    """Motor speeds ``(n, 4)`` for collective thrusts ``(n,)`` and body torques ``(n, 3)``, clipped (``pid.mix``)."""
    tx = torque[:, 0] / arm_xy
    ty = torque[:, 1] / arm_xy
    tz = torque[:, 2] * (kf / km)
    f = 0.25 * np.stack([thrust - tx - ty - tz, thrust - tx + ty + tz, thrust + tx + ty - tz, thrust + tx - ty + tz],
                        axis=1)
    return np.sqrt(np.minimum(np.maximum(f, 0.0), kf * max_rpm * max_rpm) / kf)


def body_wrench(rpm: np.ndarray, kf: float, km: float, arm_xy: float) -> np.ndarray:
    """Collective thrust [N] and body torques [N·m] ``(n, 4)`` of motor speeds ``(n, 4)`` (``dynamics.body_wrench``)."""
    f = kf * rpm * rpm
    f1, f2, f3, f4 = f[:, 0], f[:, 1], f[:, 2], f[:, 3]
    return np.stack([f1 + f2 + f3 + f4, arm_xy * (-f1 - f2 + f3 + f4), arm_xy * (-f1 + f2 + f3 - f4),
                     (km / kf) * (-f1 + f2 - f3 + f4)], axis=1)


class GateArrays:
    """Gate geometry of a track as arrays of one dtype."""

    def __init__(self, track: TrackSpec, dtype: type) -> None:
        count = len(track.gates)
        self.center = track.gate_centers().astype(dtype)
        self.rot = track.gate_rotations().astype(dtype)
        self.normal = self.rot[:, :, 0] * track.gate_directions().astype(dtype)[:, None]
        self.half = np.array([track.gate_opening(i) / 2 for i in range(count)], dtype)
        self.bar = np.array([track.gate_bar(i) for i in range(count)], dtype)
        self.bounds_min = np.asarray(track.bounds.min, dtype)
        self.bounds_max = np.asarray(track.bounds.max, dtype)


def segment_gate_crossing(p0: np.ndarray, p1: np.ndarray, gate: np.ndarray, gates: GateArrays) -> np.ndarray:
    """Fraction in [0, 1] of each segment p0 → p1 where it passes its ``gate`` forward through the opening, else −1."""
    c, rot = gates.center[gate], gates.rot[gate]
    normal = gates.normal[gate]
    s0 = _dot(normal, p0 - c)
    s1 = _dot(normal, p1 - c)
    crosses = (s0 < 0.0) & (s1 >= 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = s0 / (s0 - s1)
    hit = p0 + (p1 - p0) * t[:, None] - c
    ly = _dot(rot[:, :, 1], hit)
    lz = _dot(rot[:, :, 2], hit)
    half = gates.half[gate]
    inside = crosses & (np.abs(ly) < half) & (np.abs(lz) < half)
    return np.where(inside, t, -1.0).astype(p0.dtype)


def _sphere_box(local: np.ndarray, radius: float, box_center: np.ndarray, half: np.ndarray) -> np.ndarray:
    d = local - box_center
    gap = d - np.minimum(np.maximum(d, -half), half)
    return _dot(gap, gap) < radius * radius


def _gate_hits(pos: np.ndarray, gates: GateArrays, radius: float) -> np.ndarray:
    """Whether each drone's sphere touches a bar of any gate (``collisions.sphere_gate_overlap``)."""
    dtype = pos.dtype
    hit = np.zeros(len(pos), bool)
    for g in range(len(gates.half)):  # loop over gates (a handful), vectorised over drones
        h, b = gates.half[g], gates.bar[g]
        reach = h + b + radius
        rel = pos - gates.center[g]
        near = np.flatnonzero(_dot(rel, rel) <= 2.0 * reach * reach)  # the kernel's early-out
        local = rel[near] @ gates.rot[g]  # Rᵀ·(p − c) for the drones near the frame
        mid = h + dtype.type(0.5) * b
        flat = np.array([0.5 * b, h + b, 0.5 * b], dtype)
        tall = np.array([0.5 * b, 0.5 * b, h], dtype)
        touch = np.zeros(len(near), bool)
        for center, half in (((0, 0, mid), flat), ((0, 0, -mid), flat), ((0, mid, 0), tall), ((0, -mid, 0), tall)):
            touch |= _sphere_box(local, radius, np.asarray(center, dtype), half)
        hit[near[touch]] = True
    return hit


def contact_bits(pos: np.ndarray, out: np.ndarray, gates: GateArrays, radius: float,
                 drones_per_world: int) -> np.ndarray:
    """Collision bits ``(n,)`` of each racing drone's sphere (``collisions.collision_bits``); 0 for drones out of the
    race."""
    bits = np.where(pos[:, 2] < radius, COLLISION_KINDS["ground"], 0)
    outside = (pos < gates.bounds_min).any(axis=1) | (pos > gates.bounds_max).any(axis=1)
    bits |= np.where(outside, COLLISION_KINDS["bounds"], 0)
    hit_gate = _gate_hits(pos, gates, radius)
    bits |= np.where(hit_gate, COLLISION_KINDS["gate"], 0)
    if drones_per_world > 1:
        p = pos.reshape(-1, drones_per_world, 3)
        d = p[:, :, None, :] - p[:, None, :, :]
        close = d[..., 0] ** 2 + d[..., 1] ** 2 + d[..., 2] ** 2 < 4.0 * radius * radius
        close &= ~np.eye(drones_per_world, dtype=bool)[None]
        close &= (out.reshape(-1, drones_per_world) == 0)[:, None, :]
        bits |= np.where(close.any(axis=2).reshape(-1), COLLISION_KINDS["drone"], 0)
    return np.where(out == 0, bits, 0).astype(np.int32)


class ReferenceSim:
    """Numpy twin of :class:`spiral.sim.World` for ``drone_count`` drones (``drone_count // drones_per_world`` worlds).

    Gate crossings and contacts run only when a ``track`` is given. Arrays are public and writable, as in World:
    ``pos``, ``vel``, ``quat`` (x, y, z, w), ``omega``, ``rpm``, ``integral`` and the race bookkeeping.
    """

    def __init__(
        self,
        airframe: AirframeCfg,
        sim: SimCfg,
        drone_count: int,
        *,
        track: TrackSpec | None = None,
        drones_per_world: int = 1,
        dtype: type = np.float64,
    ) -> None:
        if drone_count % drones_per_world:
            raise ValueError("drone_count must be a multiple of drones_per_world")
        self.sim, self.dtype = sim, np.dtype(dtype)
        self.drone_count, self.drones_per_world = drone_count, drones_per_world
        self.world_count = drone_count // drones_per_world
        f = self.dtype.type
        self.mass, self.kf, self.km = f(airframe.mass), f(airframe.kf), f(airframe.km)
        self.arm_xy, self.radius = f(airframe.arm / math.sqrt(2.0)), f(airframe.radius)
        self.inertia, self.drag = np.asarray(airframe.inertia, dtype), np.asarray(airframe.drag, dtype)
        self.max_rpm, self.hover_rpm = f(airframe.max_rpm), f(airframe.hover_rpm)
        self.motor_tau, self.prop_radius, self.gravity = f(airframe.motor_tau), f(airframe.prop_radius), f(sim.gravity)
        gains = airframe.pid
        self.pos_p, self.pos_i, self.pos_d = (np.asarray(v, dtype) for v in (gains.pos_p, gains.pos_i, gains.pos_d))
        self.att_p, self.att_d = np.asarray(gains.att_p, dtype), np.asarray(gains.att_d, dtype)
        self.pos_i_limit, self.max_accel = f(gains.pos_i_limit), f(gains.max_accel)
        self.tan_max_tilt = f(math.tan(math.radians(gains.max_tilt_deg)))
        self.dt = f(sim.dt)
        self.gates = GateArrays(track, self.dtype) if track is not None else None
        n = drone_count
        self.pos, self.vel, self.omega = np.zeros((n, 3), dtype), np.zeros((n, 3), dtype), np.zeros((n, 3), dtype)
        self.quat = np.tile(np.array([0.0, 0.0, 0.0, 1.0], dtype), (n, 1))
        self.rpm, self.integral = np.zeros((n, 4), dtype), np.zeros((n, 3), dtype)
        self.prev_pos = np.zeros((n, 3), dtype)
        self.next_gate, self.gates_passed = np.zeros(n, np.int32), np.zeros(n, np.int32)
        self.step_passes, self.pass_time = np.zeros(n, np.int32), np.zeros(n, dtype)
        self.step_collision, self.out = np.zeros(n, np.int32), np.zeros(n, np.int32)
        self.crash_time = np.zeros(n, dtype)
        self.world_substeps = np.zeros(self.world_count, np.int32)
        self.world_nonfinite = np.zeros(self.world_count, np.int32)

    def reset(self, pos: np.ndarray, yaw: np.ndarray | None = None, *, vel: np.ndarray | None = None,
              next_gate: np.ndarray | None = None, world_mask: np.ndarray | None = None) -> None:
        """Reset the masked worlds (all by default) as ``World.reset``: level, at hover rpm, with a fresh race."""
        n = self.drone_count
        mask = np.ones(self.world_count, bool) if world_mask is None else np.asarray(world_mask) != 0
        d = np.repeat(mask, self.drones_per_world)
        yaw = np.zeros(n, self.dtype) if yaw is None else np.asarray(yaw, self.dtype)
        half = yaw * 0.5
        self.pos[d] = np.asarray(pos, self.dtype)[d]
        self.prev_pos[d] = self.pos[d]
        self.vel[d] = 0.0 if vel is None else np.asarray(vel, self.dtype)[d]
        self.quat[d] = np.stack([np.zeros(n), np.zeros(n), np.sin(half), np.cos(half)], axis=1).astype(self.dtype)[d]
        self.omega[d], self.rpm[d], self.integral[d] = 0.0, self.hover_rpm, 0.0
        self.next_gate[d] = 0 if next_gate is None else np.asarray(next_gate)[d]
        self.gates_passed[d], self.out[d] = 0, 0
        self.world_substeps[mask], self.world_nonfinite[mask] = 0, 0

    @property
    def rpy(self) -> np.ndarray:
        """Roll, pitch, yaw [rad] of every drone."""
        return quat_to_rpy(self.quat)

    def step(self, cmd: np.ndarray) -> None:
        """Advance one control step of ``sim.substeps`` physics steps under ``cmd`` ``(n, 4)`` (pid or rpm)."""
        cmd = np.asarray(cmd, self.dtype)
        self.step_passes[:] = 0
        self.step_collision[:] = 0
        with np.errstate(all="ignore"):
            for k in range(self.sim.substeps):
                ext_force = self._downwash() if self.sim.downwash else None
                self._control_and_integrate(cmd, ext_force)
                if self.gates is not None:
                    contact = contact_bits(self.pos, self.out, self.gates, self.radius, self.drones_per_world)
                    self._gate_crossing(k)
                    self._apply_contacts(contact, k)
        self.world_substeps += self.sim.substeps

    def _pid(self, cmd: np.ndarray, rot: np.ndarray, live: np.ndarray) -> np.ndarray:
        """Position PID → thrust and attitude → geometric attitude PD → mixer (``pid.pid_position_control``)."""
        g = self.gravity
        err = cmd[:, :3] - self.pos
        integ = np.minimum(np.maximum(self.integral + err * self.dt, -self.pos_i_limit), self.pos_i_limit)
        self.integral[live] = integ[live]
        acc = self.pos_p * err + self.pos_i * integ - self.pos_d * self.vel
        acc[:, 2] += g
        acc += self.drag * self.vel / self.mass
        az = np.maximum(acc[:, 2], 0.3 * g)
        h_norm = np.sqrt(acc[:, 0] * acc[:, 0] + acc[:, 1] * acc[:, 1])
        h_max = az * self.tan_max_tilt
        acc[:, :2] *= np.where(h_norm > h_max, h_max / h_norm, 1.0)[:, None]
        acc[:, 2] = az
        norm = np.sqrt(_dot(acc, acc))
        acc *= np.where(norm > self.max_accel, self.max_accel / norm, 1.0)[:, None]
        x_b, y_b, z_b = rot[:, :, 0], rot[:, :, 1], rot[:, :, 2]
        thrust = self.mass * np.maximum(_dot(acc, z_b), 0.0)
        z_des = acc / np.sqrt(_dot(acc, acc))[:, None]
        yaw = cmd[:, 3]
        x_c = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], axis=1)
        y_des = _cross(z_des, x_c)
        y_des /= np.sqrt(_dot(y_des, y_des))[:, None]
        x_des = _cross(y_des, z_des)
        # e_R = ½·vee(M − Mᵀ) with M = R_dᵀ·R, i.e. M_ik = (column i of R_d)·(column k of R)
        e_rot = 0.5 * np.stack([_dot(z_des, y_b) - _dot(y_des, z_b), _dot(x_des, z_b) - _dot(z_des, x_b),
                                _dot(y_des, x_b) - _dot(x_des, y_b)], axis=1)
        ang_acc = -self.att_p * e_rot - self.att_d * self.omega
        torque = self.inertia * ang_acc + _cross(self.omega, self.inertia * self.omega)
        return mix(thrust, torque, self.kf, self.km, self.arm_xy, self.max_rpm)

    def _control_and_integrate(self, cmd: np.ndarray, ext_force: np.ndarray | None) -> None:
        """Controller and semi-implicit Euler step in place (``dynamics.control_and_integrate``)."""
        dt, m = self.dt, self.mass
        self.prev_pos[:] = self.pos
        frozen = (self.out != 0) & self.sim.freeze_crashed
        live = ~frozen
        rot = quat_to_matrix(self.quat)
        if self.sim.control_mode == "pid":
            motor = self._pid(cmd, rot, live)
        else:
            motor = np.minimum(np.maximum(cmd, 0.0), self.max_rpm)
        if self.sim.motor_lag:
            motor = self.rpm + (motor - self.rpm) * (1.0 - np.exp(-dt / self.motor_tau))
        wrench = body_wrench(motor, self.kf, self.km, self.arm_xy)
        z_body = rot[:, :, 2]
        thrust = wrench[:, 0]
        if self.sim.ground_effect:
            ratio = self.prop_radius / (4.0 * np.maximum(self.pos[:, 2], 0.5 * self.prop_radius))
            thrust = thrust * np.where(z_body[:, 2] <= 0.0, 1.0, 1.0 / (1.0 - ratio * ratio))
        force = z_body * thrust[:, None] - self.drag * self.vel
        force[:, 2] -= m * self.gravity
        if ext_force is not None:
            force += ext_force
        vel = self.vel + force * (dt / m)
        w = self.omega
        omega = w + (wrench[:, 1:] - _cross(w, self.inertia * w)) / self.inertia * dt
        pos = self.pos + vel * dt
        quat = quat_integrate(self.quat, omega, dt)
        # a sum is non-finite iff a term is (barring overflow past 3e38, which no flying state reaches); a quaternion
        # whose norm overflowed normalises to zero (in float32), which the kernel also counts as non-finite
        ok = np.isfinite(pos.sum(axis=1) + vel.sum(axis=1) + omega.sum(axis=1)) & (_dot4(quat, quat) > 0.5)
        bad_worlds = (live & ~ok).reshape(-1, self.drones_per_world).any(axis=1)
        self.world_nonfinite[bad_worlds] = 1
        write = live & ok
        self.pos[write], self.vel[write], self.quat[write] = pos[write], vel[write], quat[write]
        self.omega[write], self.rpm[write] = omega[write], motor[write]
        self.vel[frozen], self.omega[frozen] = 0.0, 0.0

    def _downwash(self) -> np.ndarray:
        """Downward force of every other flying drone of the world (``dynamics.drone_downwash``)."""
        d = self.drones_per_world
        p = self.pos.reshape(-1, d, 3)
        dz = p[:, None, :, 2] - p[:, :, None, 2]  # [w, i, j]: height of j above i
        dxy = np.sqrt((p[:, None, :, 0] - p[:, :, None, 0]) ** 2 + (p[:, None, :, 1] - p[:, :, None, 1]) ** 2)
        dz_c = np.maximum(dz, 2.0 * self.radius)
        alpha = 2267.18 * (self.prop_radius / (4.0 * dz_c)) ** 2
        beta = 0.16 * dz_c - 0.11
        force = alpha * np.exp(-0.5 * (dxy / beta) ** 2)
        other = ~np.eye(d, dtype=bool)[None] & (self.out.reshape(-1, d) == 0)[:, None, :] & (dz > 0.0)
        ext = np.zeros_like(self.pos)
        ext[:, 2] = -np.where(other, force, 0.0).sum(axis=2).reshape(-1)
        return ext

    def _gate_crossing(self, substep: int) -> None:
        """Advance the next gate of each flying drone that passed it (``gates.pass_next_gate``)."""
        t = segment_gate_crossing(self.prev_pos, self.pos, self.next_gate, self.gates)
        passed = (t >= 0.0) & (self.out == 0)
        self.next_gate[passed] = (self.next_gate[passed] + 1) % len(self.gates.half)
        self.gates_passed[passed] += 1
        self.step_passes[passed] += 1
        ticks = (np.repeat(self.world_substeps, self.drones_per_world) + substep).astype(self.dtype)
        self.pass_time[passed] = ((ticks + t) * self.dt)[passed]

    def _apply_contacts(self, contact: np.ndarray, substep: int) -> None:
        """Record the substep's contacts and crash the drones that had any (``collisions.apply_contacts``)."""
        self.step_collision |= contact
        new = (contact != 0) & (self.out == 0)
        self.out[new] = 1
        ticks = (np.repeat(self.world_substeps, self.drones_per_world) + substep + 1).astype(self.dtype)
        self.crash_time[new] = (ticks * self.dt)[new]
