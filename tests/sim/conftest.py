"""Simulator fixtures: Warp modules loaded once per session, a hand-made gate track, world factories over the devices
present (``cpu``, and ``cuda:0`` where Warp finds a GPU), test kernels."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import warp as wp

from spiral.config import AIRFRAMES, AirframeCfg, AirframeSel, SimCfg, TrackSpec, resolve_airframe
from spiral.sim import QuadParams, TrackArrays, World
from spiral.sim.collisions import sphere_gate_overlap
from spiral.sim.dynamics import all_finite, body_wrench
from spiral.sim.gates import segment_gate_crossing
from spiral.sim.pid import mix
from tests.sim.helpers import DEVICES

wp.config.quiet = True


@wp.kernel
def segment_crossing_kernel(
    p0: wp.array[wp.vec3], p1: wp.array[wp.vec3], gate: wp.array[wp.int32], track: TrackArrays,
    out: wp.array[wp.float32],
):
    """Evaluate ``segment_gate_crossing`` for each segment."""
    i = wp.tid()
    out[i] = segment_gate_crossing(p0[i], p1[i], gate[i], track)


@wp.kernel
def gate_overlap_kernel(
    pos: wp.array[wp.vec3], gate: wp.array[wp.int32], radius: wp.float32, track: TrackArrays,
    out: wp.array[wp.int32],
):
    """Evaluate ``sphere_gate_overlap`` for each sphere centre."""
    i = wp.tid()
    out[i] = wp.where(sphere_gate_overlap(pos[i], radius, gate[i], track), 1, 0)


@wp.kernel
def mix_wrench_kernel(wrench: wp.array[wp.vec4], params: QuadParams, rpm: wp.array[wp.vec4],
                      out: wp.array[wp.vec4]):
    """Mix each (thrust, torque) into motor speeds, then map the speeds back to a wrench."""
    i = wp.tid()
    w = wrench[i]
    motor = mix(w[0], wp.vec3(w[1], w[2], w[3]), params)
    rpm[i] = motor
    out[i] = body_wrench(motor, params)


@wp.kernel
def finite_kernel(v: wp.array[wp.vec3], out: wp.array[wp.int32]):
    """Evaluate ``all_finite`` for each vector."""
    i = wp.tid()
    out[i] = wp.where(all_finite(v[i]), 1, 0)


class Kernels:
    """Numpy-in, numpy-out wrappers of the ``@wp.func`` helpers under test."""

    @staticmethod
    def segment_crossing(world: World, p0: np.ndarray, p1: np.ndarray, gate: np.ndarray) -> np.ndarray:
        """Crossing fraction of each segment through its gate, or −1 (on ``world``'s device)."""
        n, dev = len(p0), world.device
        out = wp.zeros(n, dtype=wp.float32, device=dev)
        wp.launch(segment_crossing_kernel, n,
                  inputs=[wp.array(np.asarray(p0, np.float32), dtype=wp.vec3, device=dev),
                          wp.array(np.asarray(p1, np.float32), dtype=wp.vec3, device=dev),
                          wp.array(np.asarray(gate, np.int32), dtype=wp.int32, device=dev), world.track],
                  outputs=[out], device=dev)
        return out.numpy()

    @staticmethod
    def gate_overlap(world: World, pos: np.ndarray, gate: np.ndarray, radius: float) -> np.ndarray:
        """1 where a sphere at ``pos`` touches a bar of its gate (on ``world``'s device)."""
        n, dev = len(pos), world.device
        out = wp.zeros(n, dtype=wp.int32, device=dev)
        wp.launch(gate_overlap_kernel, n,
                  inputs=[wp.array(np.asarray(pos, np.float32), dtype=wp.vec3, device=dev),
                          wp.array(np.asarray(gate, np.int32), dtype=wp.int32, device=dev), radius, world.track],
                  outputs=[out], device=dev)
        return out.numpy()

    @staticmethod
    def mix_roundtrip(world: World, wrench: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Motor speeds of each (thrust, τx, τy, τz) and the wrench those speeds produce (on ``world``'s device)."""
        n, dev = len(wrench), world.device
        rpm, out = wp.zeros(n, dtype=wp.vec4, device=dev), wp.zeros(n, dtype=wp.vec4, device=dev)
        wp.launch(mix_wrench_kernel, n, inputs=[wp.array(np.asarray(wrench, np.float32), dtype=wp.vec4, device=dev),
                                                world.params], outputs=[rpm, out], device=dev)
        return rpm.numpy(), out.numpy()

    @staticmethod
    def all_finite(v: np.ndarray) -> np.ndarray:
        """1 where every component of a 3-vector is finite (the dynamics kernel's health check), on the CPU."""
        out = wp.zeros(len(v), dtype=wp.int32, device="cpu")
        wp.launch(finite_kernel, len(v), inputs=[wp.array(np.asarray(v, np.float32), dtype=wp.vec3, device="cpu")],
                  outputs=[out], device="cpu")
        return out.numpy()


@pytest.fixture(scope="session")
def gate_track() -> TrackSpec:
    """Gate 0 at (0, 0, 1.5) passed along +x; gate 1 at (0, 3, 1.5) passed along −x; roomy arena."""
    return TrackSpec.model_validate({
        "kind": "track",
        "name": "gates2",
        "gates": [
            {"position": [0.0, 0.0, 1.5], "rpy_deg": [0, 0, 0], "direction": 1},
            {"position": [0.0, 3.0, 1.5], "rpy_deg": [0, 0, 0], "direction": -1},
        ],
        "start": {"center": [-2.0, 1.5, 1.5], "size": [0.4, 0.4, 0.2]},
        "bounds": {"min": [-4.0, -4.0, 0.0], "max": [4.0, 6.0, 4.0]},
    })


@pytest.fixture(scope="session")
def cf2x() -> AirframeCfg:
    """The default Crazyflie airframe."""
    return AIRFRAMES["cf2x"]


@pytest.fixture(scope="session")
def cf2x_no_drag() -> AirframeCfg:
    """The Crazyflie with linear drag switched off."""
    return resolve_airframe(AirframeSel(overrides={"drag": (0.0, 0.0, 0.0)}))


@pytest.fixture(scope="session")
def kernels(gate_track: TrackSpec, cf2x: AirframeCfg) -> type[Kernels]:
    """Test kernels, with every simulator module loaded once for the session (Warp compiles each on first use)."""
    world = World(gate_track, cf2x, SimCfg(), world_count=1, drones_per_world=2, device="cpu")
    world.reset_all(np.array([[-2.0, 1.4, 1.5], [-2.0, 1.6, 1.5]]))
    world.step()
    Kernels.mix_roundtrip(world, np.zeros((1, 4)))
    return Kernels


@pytest.fixture(params=DEVICES)
def sim_device(request: pytest.FixtureRequest) -> str:
    """The device of the test's worlds: each of :data:`DEVICES` (a test pins one with
    ``@pytest.mark.parametrize("sim_device", [...])``)."""
    return request.param


@pytest.fixture
def make_world(kernels: type[Kernels], gate_track: TrackSpec, cf2x: AirframeCfg,
               sim_device: str) -> Callable[..., World]:
    """Factory: ``make_world(track=gate_track, airframe=cf2x, world_count=1, drones=1, cpu_threads=1,
    **SimCfg fields)``, the worlds on ``sim_device``."""

    def make(track: TrackSpec | None = None, airframe: AirframeCfg | None = None, *, world_count: int = 1,
             drones: int = 1, cpu_threads: int = 1, **sim: Any) -> World:
        return World(track or gate_track, airframe or cf2x, SimCfg(**sim), world_count=world_count,
                     drones_per_world=drones, device=sim_device, cpu_threads=cpu_threads)

    return make


def run_commands(world: World, commands: np.ndarray) -> dict[str, np.ndarray]:
    """Step ``world`` once per command set ``(steps, n, 4)``; return stacked pos, vel, quat, omega, rpm, rpy."""
    keys = ("pos", "vel", "quat", "omega", "rpm")
    out: dict[str, list[np.ndarray]] = {k: [] for k in (*keys, "rpy")}
    for cmd in commands:
        world.cmd.assign(np.asarray(cmd, np.float32))
        world.step()
        for k in keys:
            out[k].append(getattr(world.state, k).numpy().copy())  # on CPU .numpy() is a view
        out["rpy"].append(world.rpy.numpy().copy())
    return {k: np.stack(v) for k, v in out.items()}


@pytest.fixture(scope="session")
def run() -> Callable[[World, np.ndarray], dict[str, np.ndarray]]:
    """The :func:`run_commands` helper."""
    return run_commands


def random_targets(rng: np.random.Generator, steps: int, drone_count: int, *, hold: int = 10,
                   lo: tuple[float, float, float] = (-2.0, -2.0, 0.8),
                   hi: tuple[float, float, float] = (2.0, 2.0, 2.5)) -> np.ndarray:
    """PID commands ``(steps, n, 4)``: random targets and yaws, each held for ``hold`` control steps."""
    draws = -(-steps // hold)
    pos = rng.uniform(lo, hi, (draws, drone_count, 3))
    yaw = rng.uniform(-np.pi, np.pi, (draws, drone_count, 1))
    return np.repeat(np.concatenate([pos, yaw], axis=2), hold, axis=0)[:steps].astype(np.float32)


@pytest.fixture(scope="session")
def targets() -> Callable[..., np.ndarray]:
    """The :func:`random_targets` helper."""
    return random_targets
