"""Contacts of each drone's sphere with the ground, the arena bounds, the gate bars and the other drones."""

from __future__ import annotations

import warp as wp

from spiral.sim.gates import pass_next_gate
from spiral.sim.options import MODULE_OPTIONS
from spiral.sim.state import (
    COLLISION_BOUNDS,
    COLLISION_DRONE,
    COLLISION_GATE,
    COLLISION_GROUND,
    QuadParams,
    TrackArrays,
)

__all__ = ["apply_contacts", "collision_bits", "detect_collisions_and_gate_passes", "sphere_box_overlap",
           "sphere_gate_overlap"]

wp.set_module_options(MODULE_OPTIONS)


@wp.func
def sphere_box_overlap(center: wp.vec3, radius: wp.float32, box_center: wp.vec3, half: wp.vec3) -> wp.bool:
    """Whether a sphere overlaps an axis-aligned box (both in the same frame)."""
    d = center - box_center
    closest = wp.min(wp.max(d, -half), half)
    return wp.length_sq(d - closest) < radius * radius


@wp.func
def sphere_gate_overlap(p: wp.vec3, radius: wp.float32, g: wp.int32, track: TrackArrays) -> wp.bool:
    """Whether a sphere touches one of the four bars of gate entry ``g`` (of all tracks' gates).

    In the gate frame (x normal, opening in y-z) each bar is a box of cross-section bar × bar: the top and bottom
    bars span the full outer width, the side bars the opening's height.
    """
    h = track.gate_half_opening[g]
    b = track.gate_bar[g]
    reach = h + b + radius
    rel = p - track.gate_center[g]
    if wp.length_sq(rel) > 2.0 * reach * reach:  # outside the frame's bounding sphere
        return False
    local = wp.transpose(track.gate_rot[g]) * rel
    if wp.abs(local[0]) > b + radius or wp.abs(local[1]) > reach or wp.abs(local[2]) > reach:
        return False
    mid = h + 0.5 * b
    flat = wp.vec3(0.5 * b, h + b, 0.5 * b)
    tall = wp.vec3(0.5 * b, 0.5 * b, h)
    return (
        sphere_box_overlap(local, radius, wp.vec3(0.0, 0.0, mid), flat)
        or sphere_box_overlap(local, radius, wp.vec3(0.0, 0.0, -mid), flat)
        or sphere_box_overlap(local, radius, wp.vec3(0.0, mid, 0.0), tall)
        or sphere_box_overlap(local, radius, wp.vec3(0.0, -mid, 0.0), tall)
    )


@wp.func
def collision_bits(
    tid: wp.int32,
    pos: wp.array[wp.vec3],
    out: wp.array[wp.int32],
    track: TrackArrays,
    t: wp.int32,
    params: QuadParams,
    drones_per_world: wp.int32,
) -> wp.int32:
    """This substep's collision bits of flying drone ``tid`` on track ``t``: ground, arena bounds, gate bars, flying
    drones."""
    p = pos[tid]
    r = params.radius
    bits = wp.int32(0)
    if p[2] < r:
        bits = bits | COLLISION_GROUND
    lo = track.bounds_min[t]
    hi = track.bounds_max[t]
    if p[0] < lo[0] or p[1] < lo[1] or p[2] < lo[2] or p[0] > hi[0] or p[1] > hi[1] or p[2] > hi[2]:
        bits = bits | COLLISION_BOUNDS
    first_gate = track.track_first[t]
    for g in range(first_gate, first_gate + track.track_gates[t]):
        if sphere_gate_overlap(p, r, g, track):
            bits = bits | COLLISION_GATE
    first = (tid / drones_per_world) * drones_per_world
    for j in range(first, first + drones_per_world):
        if j != tid and out[j] == 0 and wp.length_sq(pos[j] - p) < 4.0 * r * r:
            bits = bits | COLLISION_DRONE
    return bits


@wp.kernel
def detect_collisions_and_gate_passes(
    prev_pos: wp.array[wp.vec3],
    pos: wp.array[wp.vec3],
    out: wp.array[wp.int32],
    track: TrackArrays,
    params: QuadParams,
    world_track: wp.array[wp.int32],
    world_substeps: wp.array[wp.int32],
    drones_per_world: wp.int32,
    substep: wp.int32,
    dt: wp.float32,
    contact: wp.array[wp.int32],
    next_gate: wp.array[wp.int32],
    gates_passed: wp.array[wp.int32],
    step_passes: wp.array[wp.int32],
    pass_time: wp.array[wp.float32],
):
    """Write this substep's collision bits of each flying drone and advance its next gate when it passed it;
    drones out of the race (crashed, finished or absent) get bits 0 and no passes. Each drone meets the gates and
    bounds of its world's track (``world_track``).

    Two concerns in one launch, as one launch per substep is cheaper: both read the substep's positions and the
    crash flags and neither writes what the other reads (the gate test touches only its own drone's race counters,
    the contact test writes ``contact`` only). Crash flags change after every drone's contacts are known, in
    :func:`apply_contacts`.
    """
    tid = wp.tid()
    bits = wp.int32(0)
    if out[tid] == 0:
        t = world_track[tid / drones_per_world]
        bits = collision_bits(tid, pos, out, track, t, params, drones_per_world)
        pass_next_gate(tid, prev_pos, pos, track, t, world_substeps, drones_per_world, substep, dt, next_gate,
                       gates_passed, step_passes, pass_time)
    contact[tid] = bits


@wp.kernel
def apply_contacts(
    contact: wp.array[wp.int32],
    world_substeps: wp.array[wp.int32],
    drones_per_world: wp.int32,
    substep: wp.int32,
    dt: wp.float32,
    step_collision: wp.array[wp.int32],
    out: wp.array[wp.int32],
    crash_time: wp.array[wp.float32],
):
    """Record the substep's contacts: any collision crashes the drone (after every drone's contacts are known)."""
    tid = wp.tid()
    bits = contact[tid]
    if bits != 0:
        step_collision[tid] = step_collision[tid] | bits
        if out[tid] == 0:
            out[tid] = 1
            crash_time[tid] = wp.float32(world_substeps[tid / drones_per_world] + substep + 1) * dt
