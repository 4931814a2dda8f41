"""Warp structs and buffers: static parameters, track geometry and per-drone state, kept apart."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import warp as wp

from spiral.config.airframe import AirframeCfg
from spiral.config.sim import SimCfg
from spiral.config.track import TrackSpec

__all__ = [
    "COLLISION_BOUNDS",
    "COLLISION_DRONE",
    "COLLISION_GATE",
    "COLLISION_GROUND",
    "COLLISION_KINDS",
    "QuadParams",
    "QuadState",
    "RaceCounters",
    "TrackArrays",
    "make_quad_params",
    "make_track_arrays",
]

COLLISION_GROUND = wp.constant(1)
COLLISION_BOUNDS = wp.constant(2)
COLLISION_GATE = wp.constant(4)
COLLISION_DRONE = wp.constant(8)
COLLISION_KINDS: dict[str, int] = {"ground": 1, "bounds": 2, "gate": 4, "drone": 8}
"""Bit of each collision kind in the per-drone collision masks."""


@wp.struct
class QuadParams:
    """Airframe, controller gains and simulator switches, in SI units."""

    mass: wp.float32
    inertia: wp.vec3
    arm_xy: wp.float32  # arm projected on the body x and y axes (X frame): arm / sqrt(2)
    kf: wp.float32
    km: wp.float32
    drag: wp.vec3
    max_rpm: wp.float32
    hover_rpm: wp.float32
    radius: wp.float32
    motor_tau: wp.float32
    prop_radius: wp.float32
    gravity: wp.float32
    pos_p: wp.vec3
    pos_i: wp.vec3
    pos_d: wp.vec3
    pos_i_limit: wp.float32
    att_p: wp.vec3
    att_d: wp.vec3
    tan_max_tilt: wp.float32
    max_accel: wp.float32
    ground_effect: wp.int32
    downwash: wp.int32
    motor_lag: wp.int32
    freeze_crashed: wp.int32


@wp.struct
class TrackArrays:
    """Gate frames and arena bounds of one or more tracks. The gate arrays run over the gates of every track, track
    after track: gate ``g`` of track ``t`` is entry ``track_first[t] + g``. ``gate_rot`` columns are the gate's local
    x (normal), y and z axes."""

    gate_center: wp.array[wp.vec3]
    gate_rot: wp.array[wp.mat33]
    gate_dir: wp.array[wp.float32]
    gate_half_opening: wp.array[wp.float32]
    gate_bar: wp.array[wp.float32]
    track_first: wp.array[wp.int32]
    """Entry of each track's first gate."""
    track_gates: wp.array[wp.int32]
    """Gates of each track."""
    bounds_min: wp.array[wp.vec3]
    """Arena bounds of each track."""
    bounds_max: wp.array[wp.vec3]


def make_quad_params(airframe: AirframeCfg, sim: SimCfg) -> QuadParams:
    """Convert an airframe and sim config to the kernel struct (once, at world construction)."""
    p = QuadParams()
    p.mass, p.inertia = airframe.mass, wp.vec3(*airframe.inertia)
    p.arm_xy = airframe.arm / math.sqrt(2.0)
    p.kf, p.km, p.drag = airframe.kf, airframe.km, wp.vec3(*airframe.drag)
    p.max_rpm, p.hover_rpm = airframe.max_rpm, airframe.hover_rpm
    p.radius, p.motor_tau, p.prop_radius = airframe.radius, airframe.motor_tau, airframe.prop_radius
    p.gravity = sim.gravity
    gains = airframe.pid
    p.pos_p, p.pos_i, p.pos_d = wp.vec3(*gains.pos_p), wp.vec3(*gains.pos_i), wp.vec3(*gains.pos_d)
    p.pos_i_limit, p.att_p, p.att_d = gains.pos_i_limit, wp.vec3(*gains.att_p), wp.vec3(*gains.att_d)
    p.tan_max_tilt, p.max_accel = math.tan(math.radians(gains.max_tilt_deg)), gains.max_accel
    p.ground_effect, p.downwash = int(sim.ground_effect), int(sim.downwash)
    p.motor_lag, p.freeze_crashed = int(sim.motor_lag), int(sim.freeze_crashed)
    return p


def make_track_arrays(tracks: Sequence[TrackSpec], device: str) -> TrackArrays:
    """Copy the gate geometry and bounds of ``tracks`` to ``device``, one after another."""
    t = TrackArrays()
    counts = [len(track.gates) for track in tracks]
    cat = lambda part, dtype: np.concatenate([part(track) for track in tracks]).astype(dtype)  # noqa: E731
    t.gate_center = wp.array(cat(TrackSpec.gate_centers, np.float32), dtype=wp.vec3, device=device)
    t.gate_rot = wp.array(cat(TrackSpec.gate_rotations, np.float32), dtype=wp.mat33, device=device)
    t.gate_dir = wp.array(cat(TrackSpec.gate_directions, np.float32), dtype=wp.float32, device=device)
    half = cat(lambda track: [track.gate_opening(i) / 2 for i in range(len(track.gates))], np.float32)
    bar = cat(lambda track: [track.gate_bar(i) for i in range(len(track.gates))], np.float32)
    t.gate_half_opening = wp.array(half, dtype=wp.float32, device=device)
    t.gate_bar = wp.array(bar, dtype=wp.float32, device=device)
    t.track_first = wp.array(np.cumsum([0, *counts[:-1]]).astype(np.int32), dtype=wp.int32, device=device)
    t.track_gates = wp.array(np.asarray(counts, np.int32), dtype=wp.int32, device=device)
    bounds = [(track.bounds.min, track.bounds.max) for track in tracks]
    t.bounds_min = wp.array(np.asarray([lo for lo, _ in bounds], np.float32), dtype=wp.vec3, device=device)
    t.bounds_max = wp.array(np.asarray([hi for _, hi in bounds], np.float32), dtype=wp.vec3, device=device)
    return t


class QuadState:
    """Rigid-body state of every drone, flat over worlds: drone ``i`` lives in world ``i // drones_per_world``."""

    def __init__(self, drone_count: int, device: str) -> None:
        self.pos = wp.zeros(drone_count, dtype=wp.vec3, device=device)
        """Position in the world frame [m]."""
        self.vel = wp.zeros(drone_count, dtype=wp.vec3, device=device)
        """Velocity in the world frame [m/s]."""
        self.quat = wp.array(np.tile([0.0, 0.0, 0.0, 1.0], (drone_count, 1)).astype(np.float32), dtype=wp.quat,
                             device=device)
        """Body-to-world rotation, Warp's (x, y, z, w) order."""
        self.omega = wp.zeros(drone_count, dtype=wp.vec3, device=device)
        """Body rates in the body frame [rad/s]."""
        self.rpm = wp.zeros(drone_count, dtype=wp.vec4, device=device)
        """Motor speeds [rpm]."""
        self.prev_pos = wp.zeros(drone_count, dtype=wp.vec3, device=device)
        """Position before the last substep, for swept gate tests [m]."""


class RaceCounters:
    """Per-drone race bookkeeping and per-world clocks and health flags."""

    def __init__(self, world_count: int, drone_count: int, device: str) -> None:
        zeros_i = lambda n: wp.zeros(n, dtype=wp.int32, device=device)  # noqa: E731
        self.next_gate = zeros_i(drone_count)
        """Gate each drone must pass next, numbered within its world's track."""
        self.gates_passed = zeros_i(drone_count)
        """Gates passed in order since the last reset."""
        self.step_passes = zeros_i(drone_count)
        """Gates passed during the last control step."""
        self.pass_time = wp.zeros(drone_count, dtype=wp.float32, device=device)
        """Time of the latest gate crossing, interpolated inside the substep [s]."""
        self.contact = zeros_i(drone_count)
        """Collision bits found in the current substep."""
        self.step_collision = zeros_i(drone_count)
        """Collision bits found during the last control step."""
        self.out = zeros_i(drone_count)
        """1 once a drone is out of the race since its reset: the simulator sets it at a collision, the race env also
        for a drone that finished or whose slot is absent. Out drones are no obstacle, make no gate passes and, with
        ``freeze_crashed``, hold still."""
        self.crash_time = wp.zeros(drone_count, dtype=wp.float32, device=device)
        """Time of the first collision [s]."""
        self.world_substeps = zeros_i(world_count)
        """Physics substeps since each world's reset: world time = substeps · dt, kept exact."""
        self.world_nonfinite = zeros_i(world_count)
        """1 when a drone of the world produced a non-finite state since its reset."""
        self.world_track = zeros_i(world_count)
        """Track each world races (an index into :attr:`World.tracks`)."""
