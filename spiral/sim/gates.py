"""Gate crossing: the path segment of a substep crosses the next gate's plane inside its opening."""

from __future__ import annotations

import warp as wp

from spiral.sim.options import MODULE_OPTIONS
from spiral.sim.state import TrackArrays

__all__ = ["pass_next_gate", "segment_gate_crossing"]

wp.set_module_options(MODULE_OPTIONS)


@wp.func
def segment_gate_crossing(p0: wp.vec3, p1: wp.vec3, g: wp.int32, track: TrackArrays) -> wp.float32:
    """Fraction in [0, 1] of the segment p0 → p1 where it passes gate entry ``g`` (of all tracks' gates) forward
    through the opening, else −1."""
    c = track.gate_center[g]
    rot = track.gate_rot[g]
    normal = wp.vec3(rot[0, 0], rot[1, 0], rot[2, 0]) * track.gate_dir[g]
    s0 = wp.dot(normal, p0 - c)
    s1 = wp.dot(normal, p1 - c)
    if not (s0 < 0.0 and s1 >= 0.0):
        return -1.0
    t = s0 / (s0 - s1)
    hit = p0 + (p1 - p0) * t - c
    half = track.gate_half_opening[g]
    ly = wp.dot(wp.vec3(rot[0, 1], rot[1, 1], rot[2, 1]), hit)
    lz = wp.dot(wp.vec3(rot[0, 2], rot[1, 2], rot[2, 2]), hit)
    if wp.abs(ly) < half and wp.abs(lz) < half:
        return t
    return -1.0


@wp.func
def pass_next_gate(
    tid: wp.int32,
    prev_pos: wp.array[wp.vec3],
    pos: wp.array[wp.vec3],
    track: TrackArrays,
    t: wp.int32,
    world_substeps: wp.array[wp.int32],
    drones_per_world: wp.int32,
    substep: wp.int32,
    dt: wp.float32,
    next_gate: wp.array[wp.int32],
    gates_passed: wp.array[wp.int32],
    step_passes: wp.array[wp.int32],
    pass_time: wp.array[wp.float32],
):
    """Advance flying drone ``tid``'s next gate of track ``t`` when its substep's path passes it; the crossing time
    is interpolated in the substep. Called by ``collisions.detect_collisions_and_gate_passes`` for drones not
    crashed."""
    g = next_gate[tid]
    u = segment_gate_crossing(prev_pos[tid], pos[tid], track.track_first[t] + g, track)
    if u >= 0.0:
        next_gate[tid] = (g + 1) % track.track_gates[t]
        gates_passed[tid] = gates_passed[tid] + 1
        step_passes[tid] = step_passes[tid] + 1
        pass_time[tid] = (wp.float32(world_substeps[tid / drones_per_world] + substep) + u) * dt
