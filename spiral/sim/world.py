"""A batch of race worlds: ``world_count`` worlds × ``drones_per_world`` drones, stepped by Warp kernels."""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from itertools import pairwise
from types import SimpleNamespace

import numpy as np
import warp as wp

from spiral.config.airframe import AirframeCfg
from spiral.config.sim import SimCfg
from spiral.config.track import TrackSpec
from spiral.sim.collisions import apply_contacts, detect_collisions_and_gate_passes
from spiral.sim.dynamics import control_and_integrate, drone_downwash
from spiral.sim.options import MODULE_OPTIONS
from spiral.sim.pid import command_heading
from spiral.sim.rotations import quat_to_rpy, yaw_quat
from spiral.sim.runtime import init_warp
from spiral.sim.state import QuadParams, QuadState, RaceCounters, make_quad_params, make_track_arrays

__all__ = ["World"]

wp.config.log_level = wp.LOG_WARNING  # no greeting or per-module load lines
wp.set_module_options(MODULE_OPTIONS)
init_warp()


@wp.kernel
def reset_drones(
    world_mask: wp.array[wp.int32],
    init_pos: wp.array[wp.vec3],
    init_vel: wp.array[wp.vec3],
    init_yaw: wp.array[wp.float32],
    init_next_gate: wp.array[wp.int32],
    params: QuadParams,
    drones_per_world: wp.int32,
    pos: wp.array[wp.vec3],
    vel: wp.array[wp.vec3],
    quat: wp.array[wp.quat],
    omega: wp.array[wp.vec3],
    rpm: wp.array[wp.vec4],
    prev_pos: wp.array[wp.vec3],
    integral: wp.array[wp.vec3],
    next_gate: wp.array[wp.int32],
    gates_passed: wp.array[wp.int32],
    out: wp.array[wp.int32],
    world_substeps: wp.array[wp.int32],
    world_nonfinite: wp.array[wp.int32],
):
    """Put every drone of a masked world at its initial state, level, at hover rpm, with a fresh race."""
    tid = wp.tid()
    w = tid / drones_per_world
    if world_mask[w] == 0:
        return
    pos[tid] = init_pos[tid]
    prev_pos[tid] = init_pos[tid]
    vel[tid] = init_vel[tid]
    quat[tid] = yaw_quat(init_yaw[tid])
    omega[tid] = wp.vec3(0.0)
    rpm[tid] = wp.vec4(params.hover_rpm)
    integral[tid] = wp.vec3(0.0)
    next_gate[tid] = init_next_gate[tid]
    gates_passed[tid] = 0
    out[tid] = 0
    if tid % drones_per_world == 0:
        world_substeps[w] = 0
        world_nonfinite[w] = 0


@wp.kernel
def advance_clocks(substeps: wp.int32, world_substeps: wp.array[wp.int32]):
    """Count the substeps of the control step just taken."""
    w = wp.tid()
    world_substeps[w] = world_substeps[w] + substeps


@wp.kernel
def euler_angles(quat: wp.array[wp.quat], rpy: wp.array[wp.vec3]):
    """Roll, pitch and yaw of every drone, for observers."""
    tid = wp.tid()
    rpy[tid] = quat_to_rpy(quat[tid])


class World:
    """Batched race worlds on one Warp device.

    Drone ``i`` belongs to world ``i // drones_per_world``. Write commands into :attr:`cmd` (target position and
    yaw in ``pid`` mode, four motor speeds in ``rpm`` mode), then call :meth:`step` for one control step of
    ``sim.substeps`` physics steps. Per-step events are in :attr:`race` (``step_passes``, ``step_collision``).

    ``track`` is the track of every world, or a sequence of tracks: world ``w`` races ``tracks[world_track[w]]``
    (:meth:`set_world_tracks`; all race the first until told), so that one batch flies many layouts.

    ``cpu_threads`` CPU threads step the replayed launches, each on a contiguous share of the worlds (worlds never
    interact, so the result is the same for any count). A Warp CPU launch runs on one core; with 2 threads a process
    steps on two, which pays when the simulator has the cores to itself (docs/physics.md). CUDA ignores it.
    """

    def __init__(
        self,
        track: TrackSpec | Sequence[TrackSpec],
        airframe: AirframeCfg,
        sim: SimCfg,
        *,
        world_count: int,
        drones_per_world: int,
        device: str = "cpu",
        cpu_threads: int = 1,
    ) -> None:
        if world_count < 1 or drones_per_world < 1:
            raise ValueError("world_count and drones_per_world must be positive")
        if cpu_threads < 1:
            raise ValueError(f"cpu_threads must be positive, got {cpu_threads}")
        self.tracks = [track] if isinstance(track, TrackSpec) else list(track)
        if not self.tracks:
            raise ValueError("track: give a track or a non-empty sequence of tracks")
        self.airframe, self.sim = airframe, sim
        self.world_count, self.drones_per_world = world_count, drones_per_world
        self.drone_count = world_count * drones_per_world
        self.device = str(wp.get_device(device))
        self.params = make_quad_params(airframe, sim)
        self.track = make_track_arrays(self.tracks, self.device)
        self.state = QuadState(self.drone_count, self.device)
        self.race = RaceCounters(world_count, self.drone_count, self.device)
        self._alloc_buffers()
        self._graph = None
        self.use_graph = wp.get_device(self.device).is_cuda
        self._plan_threads(cpu_threads)

    def _alloc_buffers(self) -> None:
        n = self.drone_count
        self.cmd = wp.zeros(n, dtype=wp.vec4, device=self.device)
        """Command of the next control step (pid: x, y, z [m], yaw [rad]; rpm: four motor speeds)."""
        self.integral = wp.zeros(n, dtype=wp.vec3, device=self.device)
        self.ext_force = wp.zeros(n, dtype=wp.vec3, device=self.device)
        self.heading = wp.zeros(n, dtype=wp.vec2, device=self.device)
        """(cos, sin) of the commanded yaw of the current control step (pid mode)."""
        self.rpy = wp.zeros(n, dtype=wp.vec3, device=self.device)
        """Roll, pitch, yaw [rad] after the last step."""
        self._reset_mask = wp.zeros(self.world_count, dtype=wp.int32, device=self.device)

    def _plan_threads(self, cpu_threads: int) -> None:
        """Split the worlds into one shard per CPU thread (one shard on a GPU, where a graph replays the step)."""
        threads = 1 if self.use_graph else min(cpu_threads, self.world_count)
        self._shards = _world_ranges(self.world_count, threads)
        self._pool = ThreadPoolExecutor(threads - 1, thread_name_prefix="spiral-sim") if threads > 1 else None
        self._launches: list[list] | None = None
        """Per shard of worlds, the control step's kernel launches with their arguments packed once (CPU: replayed
        each step)."""

    @property
    def time_step(self) -> float:
        """Duration of one control step [s]."""
        return self.sim.substeps * self.sim.dt

    def step(self) -> None:
        """Advance every world one control step."""
        if self.use_graph:
            if self._graph is None:
                with wp.ScopedCapture(device=self.device) as capture:
                    self._simulate()
                self._graph = capture.graph
            wp.capture_launch(self._graph)
        elif self.replay_launches and self._launches is not None:
            self.race.step_passes.zero_()
            self.race.step_collision.zero_()
            self._replay()
        elif self.replay_launches:
            self._launches = [self._simulate(self._shard(lo, hi), record=True) for lo, hi in self._shards]
        else:
            self._simulate()

    replay_launches = True
    """On the CPU, pack the kernels' arguments once and replay the launches (Python's share of a launch is most of
    its cost at small world counts); False launches each kernel afresh, the plain path tests compare it with."""

    def _replay(self) -> None:
        if self._pool is None:
            _run(self._launches[0])
            return
        pending = [self._pool.submit(_run, cmds) for cmds in self._launches[1:]]
        _run(self._launches[0])
        for done in pending:
            done.result()

    def _shard(self, lo: int, hi: int) -> World | SimpleNamespace:
        """What :meth:`_simulate` reads, for worlds ``lo:hi`` only: per-world arrays sliced to these worlds,
        per-drone arrays to their drones (views, no copies)."""
        if (lo, hi) == (0, self.world_count):
            return self
        d = self.drones_per_world

        def cut(fields: dict) -> dict:
            return {key: (arr[lo:hi] if arr.shape[0] == self.world_count else arr[lo * d:hi * d])
                    if isinstance(arr, wp.array) else arr for key, arr in fields.items()}

        own = cut(dict(cmd=self.cmd, heading=self.heading, integral=self.integral, ext_force=self.ext_force,
                       rpy=self.rpy))
        return SimpleNamespace(**own, state=SimpleNamespace(**cut(vars(self.state))),
                               race=SimpleNamespace(**cut(vars(self.race))), world_count=hi - lo,
                               drone_count=(hi - lo) * d)

    def _simulate(self, v: World | SimpleNamespace | None = None, *, record: bool = False) -> list:
        """Launch one control step's kernels in order on ``v`` (the world, the default, or a shard of it); with
        ``record``, return the launches (arguments packed) as well, after running them."""
        v = self if v is None else v
        s, r, n, d = v.state, v.race, v.drone_count, self.drones_per_world
        dt = float(self.sim.dt)
        r.step_passes.zero_()
        r.step_collision.zero_()
        mode = 0 if self.sim.control_mode == "pid" else 1
        launches = []

        def launch(kernel, dim: int, inputs: list, outputs: list) -> None:
            cmd = wp.launch(kernel, dim, inputs=inputs, outputs=outputs, device=self.device, record_cmd=record)
            if record:
                cmd.launch()
                launches.append(cmd)

        if mode == 0:
            launch(command_heading, n, [v.cmd], [v.heading])
        for k in range(self.sim.substeps):
            if self.sim.downwash:
                launch(drone_downwash, n, [s.pos, r.out, self.params, d], [v.ext_force])
            launch(control_and_integrate, n,
                   [s.pos, s.vel, s.quat, s.omega, s.rpm, v.cmd, v.heading, v.integral, r.out,
                    v.ext_force, self.params, mode, d, dt],
                   [s.prev_pos, r.world_nonfinite])
            launch(detect_collisions_and_gate_passes, n,
                   [s.prev_pos, s.pos, r.out, self.track, self.params, r.world_track, r.world_substeps, d, k, dt],
                   [r.contact, r.next_gate, r.gates_passed, r.step_passes, r.pass_time])
            launch(apply_contacts, n, [r.contact, r.world_substeps, d, k, dt],
                   [r.step_collision, r.out, r.crash_time])
        launch(advance_clocks, v.world_count, [self.sim.substeps], [r.world_substeps])
        launch(euler_angles, n, [s.quat], [v.rpy])
        return launches

    def reset(
        self,
        world_mask: wp.array,
        init_pos: wp.array,
        init_yaw: wp.array,
        *,
        init_vel: wp.array | None = None,
        init_next_gate: wp.array | None = None,
    ) -> None:
        """Reset the worlds whose ``world_mask`` entry is non-zero; per-drone initial values for all drones."""
        s, r = self.state, self.race
        zeros_v = init_vel if init_vel is not None else wp.zeros(self.drone_count, dtype=wp.vec3, device=self.device)
        gates = init_next_gate if init_next_gate is not None else wp.zeros(self.drone_count, dtype=wp.int32,
                                                                           device=self.device)
        wp.launch(reset_drones, self.drone_count,
                  inputs=[world_mask, init_pos, zeros_v, init_yaw, gates, self.params, self.drones_per_world],
                  outputs=[s.pos, s.vel, s.quat, s.omega, s.rpm, s.prev_pos, self.integral, r.next_gate,
                           r.gates_passed, r.out, r.world_substeps, r.world_nonfinite],
                  device=self.device)
        wp.launch(euler_angles, self.drone_count, inputs=[s.quat], outputs=[self.rpy], device=self.device)

    def set_world_tracks(self, world_track: np.ndarray) -> None:
        """Race world ``w`` on ``tracks[world_track[w]]`` from now on (give each changed world a reset with starts
        and next gates of its new track)."""
        world_track = np.asarray(world_track)
        in_range = np.all((world_track >= 0) & (world_track < len(self.tracks)))
        if world_track.shape != (self.world_count,) or not in_range:
            raise ValueError(f"world_track: expected {self.world_count} indices in [0, {len(self.tracks)}), got "
                             f"{world_track!r}")
        self.race.world_track.assign(world_track.astype(np.int32))

    def reset_all(self, init_pos: np.ndarray, init_yaw: np.ndarray | None = None) -> None:
        """Reset every world from numpy arrays (convenience for tests and tools): positions ``(N, 3)``."""
        n = self.drone_count
        yaw = np.zeros(n, np.float32) if init_yaw is None else np.asarray(init_yaw, np.float32)
        self._reset_mask.fill_(1)
        self.reset(self._reset_mask, wp.array(np.asarray(init_pos, np.float32), dtype=wp.vec3, device=self.device),
                   wp.array(yaw, dtype=wp.float32, device=self.device))

    def world_time(self) -> np.ndarray:
        """Simulated time since each world's reset [s] (numpy copy)."""
        return self.race.world_substeps.numpy() * self.sim.dt


def _world_ranges(world_count: int, parts: int) -> list[tuple[int, int]]:
    """``parts`` contiguous ranges of worlds, as equal as integers allow."""
    edges = [world_count * k // parts for k in range(parts + 1)]
    return list(pairwise(edges))


def _run(launches: list) -> None:
    for cmd in launches:
        cmd.launch()
