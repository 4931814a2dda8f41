"""Simulator throughput: Warp ``World`` against the numpy reference, on the same inputs, in the same run.

Each row runs ``pid`` mode at 240 Hz physics and 48 Hz control (5 substeps) with gates and collisions on. Drones
start at random points of the arena and chase random targets that are re-drawn every few control steps, so they
keep moving. ``freeze_crashed`` is off and the out-of-race flags are cleared before every control step: a crashed drone
skips the gate and contact tests, and a benchmark in which drones drop out would flatter the figure.
"""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import warp as wp

from spiral.config.airframe import AIRFRAMES, AirframeCfg
from spiral.config.load import load_track
from spiral.config.sim import SimCfg
from spiral.config.track import TrackSpec
from spiral.core.errors import UsageError
from spiral.core.numerics import CPU_TARGET_ENV, cpu_target
from spiral.sim.options import MODULE_OPTIONS
from spiral.sim.reference import ReferenceSim
from spiral.sim.world import World

__all__ = ["BenchExtras", "default_world_counts", "draw_inputs", "format_bench_table", "format_kernel_table",
           "kernel_profile", "machine_info", "run_build_comparison", "run_sim_bench", "run_sim_bench_two_process",
           "time_warp", "time_world", "two_process_worker"]

TARGET_REDRAW_STEPS = 10
"""Control steps between two draws of the random targets (about 0.2 s at 48 Hz)."""
WARMUP_STEPS = 5
"""Untimed control steps before timing (compiles and loads kernels, fills caches)."""
NUMPY_BUDGET_S = 2.0
"""About how long one numpy repeat of a row may take [s]; large rows time fewer numpy steps (``numpy_steps`` in the
row), never fewer than 3."""
DEFAULT_TRACK = Path(__file__).resolve().parents[2] / "tracks" / "circuit6.yaml"
"""Track of the benchmark: the paper's 6-gate circuit."""
CPU_WORLD_COUNTS = (1, 64, 1024, 4096, 16384)
"""Rows of a CPU run by default (a CPU's rate levels off from about 1024 worlds)."""
CUDA_WORLD_COUNTS = (1, 64, 1024, 4096, 16384, 65536)
"""Rows of a GPU run by default: a GPU fills up only at tens of thousands of drones."""


def default_world_counts(device: str) -> tuple[int, ...]:
    """The world counts of a benchmark run on ``device`` when none are asked for."""
    return CUDA_WORLD_COUNTS if _is_cuda(device) else CPU_WORLD_COUNTS


def _is_cuda(device: str) -> bool:
    """Whether ``device`` names a GPU (``cuda`` or ``cuda:N``), read off the name alone."""
    return str(device).startswith("cuda")


def machine_info() -> dict[str, Any]:
    """CPU model, core count, load, Python, numpy and Warp versions of this machine."""
    model = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "cpu": model,
        "cores": os.cpu_count(),
        "load_avg_1min": _load_avg(),
        "os": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "warp": wp.config.version,
        "cpu_target": cpu_target(),
        "sim_cpu_flags": MODULE_OPTIONS["cpu_compiler_flags"],
    }


def _load_avg() -> float | None:
    """The 1-minute load average, where the system has one."""
    return round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None


def _bench_cfg() -> SimCfg:
    return SimCfg(physics_hz=240, ctrl_hz=48, control_mode="pid", freeze_crashed=False)


def draw_inputs(track: TrackSpec, drone_count: int, draws: int,
                 seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Start positions ``(n, 3)``, start yaws ``(n,)`` and ``draws`` target sets ``(draws, n, 4)``, in the arena."""
    rng = np.random.default_rng(seed)
    lo = np.asarray(track.bounds.min) + 0.5
    hi = np.asarray(track.bounds.max) - 0.5
    start = rng.uniform(lo, hi, (drone_count, 3)).astype(np.float32)
    yaw = rng.uniform(-math.pi, math.pi, drone_count).astype(np.float32)
    targets = np.concatenate(
        [rng.uniform(lo, hi, (draws, drone_count, 3)), rng.uniform(-math.pi, math.pi, (draws, drone_count, 1))], axis=2
    ).astype(np.float32)
    return start, yaw, targets


def time_warp(world: World, targets: list[wp.array], steps: int, first: int) -> tuple[float, float]:
    """Wall and process CPU seconds for ``steps`` control steps, from step ``first`` of the target schedule."""
    device = world.device
    wp.synchronize_device(device)
    start, cpu = time.perf_counter(), time.process_time()
    for i in range(first, first + steps):
        if i % TARGET_REDRAW_STEPS == 0:
            wp.copy(world.cmd, targets[(i // TARGET_REDRAW_STEPS) % len(targets)])
        world.race.out.zero_()
        world.step()
    wp.synchronize_device(device)
    return time.perf_counter() - start, time.process_time() - cpu


def _time_numpy(ref: ReferenceSim, targets: np.ndarray, steps: int, first: int) -> tuple[float, float]:
    """Wall and CPU seconds for ``steps`` control steps of the numpy reference, on :func:`time_warp`'s schedule."""
    start, cpu = time.perf_counter(), time.process_time()
    cmd = targets[(first // TARGET_REDRAW_STEPS) % len(targets)]
    for i in range(first, first + steps):
        if i % TARGET_REDRAW_STEPS == 0:
            cmd = targets[(i // TARGET_REDRAW_STEPS) % len(targets)]
        ref.out[:] = 0
        ref.step(cmd)
    return time.perf_counter() - start, time.process_time() - cpu


def _make_world(track: TrackSpec, airframe: AirframeCfg, world_count: int, drones: int, device: str,
                seed: int, cpu_threads: int = 1) -> tuple[World, list[wp.array], np.ndarray, np.ndarray, np.ndarray]:
    n = world_count * drones
    draws = 8
    start, yaw, targets = draw_inputs(track, n, draws, seed)
    world = World(track, airframe, _bench_cfg(), world_count=world_count, drones_per_world=drones, device=device,
                  cpu_threads=cpu_threads)
    world.reset_all(start, yaw)
    targets_wp = [wp.array(t, dtype=wp.vec4, device=world.device) for t in targets]
    return world, targets_wp, start, yaw, targets


def _bench_row(track: TrackSpec, airframe: AirframeCfg, world_count: int, drones: int, *, device: str, steps: int,
               seed: int, repeats: int) -> dict[str, Any]:
    """One row: Warp and numpy on the same inputs, repeats interleaved so that load from others hits both alike."""
    n = world_count * drones
    world, targets_wp, start, yaw, targets = _make_world(track, airframe, world_count, drones, device, seed)
    ref = ReferenceSim(airframe, _bench_cfg(), n, track=track, drones_per_world=drones, dtype=np.float32)
    ref.reset(start, yaw)
    time_warp(world, targets_wp, WARMUP_STEPS, 0)
    one = _time_numpy(ref, targets, 1, 0)[0]  # untimed warm-up, also sizes the numpy run
    np_steps = int(min(steps, max(3, NUMPY_BUDGET_S / max(one, 1e-9))))
    warp_t, np_t = [], []
    for r in range(repeats):
        warp_t.append(time_warp(world, targets_wp, steps, WARMUP_STEPS + r * steps))
        np_t.append(_time_numpy(ref, targets, np_steps, 1 + r * np_steps))
    speed = np.linalg.norm(world.state.vel.numpy(), axis=1)
    warp_rate, np_rate = n * steps / min(t[0] for t in warp_t), n * np_steps / min(t[0] for t in np_t)
    return {
        "worlds": world_count,
        "drones": drones,
        "drone_ctrl_steps_per_s": round(warp_rate),
        "drone_substeps_per_s": round(warp_rate * world.sim.substeps),
        "numpy_drone_ctrl_steps_per_s": round(np_rate),
        "speedup_vs_numpy": round(warp_rate / np_rate, 2),
        "steps": steps,
        "numpy_steps": np_steps,
        "drone_ctrl_steps_per_cpu_s": round(n * steps / min(t[1] for t in warp_t)),
        "numpy_drone_ctrl_steps_per_cpu_s": round(n * np_steps / min(t[1] for t in np_t)),
        "mean_speed_m_s": round(float(speed.mean()), 3),
    }


def _bench_settings(track: TrackSpec, airframe: AirframeCfg, cfg: SimCfg, *, repeats: int, seed: int
                    ) -> dict[str, Any]:
    """What a benchmark run measured and how, for its JSON."""
    return {
        "track": track.name,
        "airframe": airframe.name,
        "control_mode": cfg.control_mode,
        "physics_hz": cfg.physics_hz,
        "ctrl_hz": cfg.ctrl_hz,
        "substeps": cfg.substeps,
        "gates": True,
        "collisions": True,
        "freeze_crashed": False,
        "crash_flags_cleared_each_step": True,
        "target_redraw_steps": TARGET_REDRAW_STEPS,
        "warmup_steps": WARMUP_STEPS,
        "repeats": repeats,
        "seed": seed,
        "numpy_dtype": "float32",
        "timing": "wall clock, best of the repeats, Warp and numpy repeats interleaved; *_per_cpu_s use the "
                  "process CPU time instead (a proxy when other processes share the cores)",
    }


@dataclass(frozen=True)
class BenchExtras:
    """Entries of a :func:`run_sim_bench` result beside its rows, each timing Warp at 4096 worlds × 4 drones."""

    two_process: bool = False
    """Run it in two processes side by side (``two_process`` entry)."""
    builds: bool = False
    """On the CPU, time it with each CPU build (``builds`` entry, :func:`run_build_comparison`)."""
    threads: int = 1
    """Above 1, time Warp alone with the worlds stepped on this many threads of one process (``threaded`` entry;
    the rows use one)."""

    @classmethod
    def for_device(cls, device: str, *, two_process: bool | None = None, builds: bool | None = None,
                   threads: int | None = None) -> BenchExtras:
        """The extras of a run on ``device``, each left ``None`` at its default: on a CPU all of them (two
        processes, both builds, two threads); on a GPU none, since each measures how the CPU's cores are shared.

        Raises:
            UsageError: an extra asked for on a GPU, naming its option.
        """
        if not _is_cuda(device):
            return cls(two_process=two_process is not False, builds=builds is not False,
                       threads=2 if threads is None else threads)
        asked = [option for option, on in (("--two-process", two_process), ("--builds", builds),
                                           (f"--threads {threads}", (threads or 1) > 1)) if on]
        if asked:
            raise UsageError(f"{', '.join(asked)}: the simulator runs on the GPU on {device}, and these rows compare "
                             "CPU processes, threads and builds; leave them out or use --device cpu")
        return cls()


def run_sim_bench(worlds: Sequence[int], *, device: str = "cpu", drones: Sequence[int] = (1, 4), steps: int = 100,
                  seed: int = 0, repeats: int = 3, extras: BenchExtras = BenchExtras(),
                  track: TrackSpec | None = None) -> dict[str, Any]:
    """Measure drone-control-steps per second of Warp and of the numpy reference for each world count and layout.

    Args:
        worlds: World counts, one row per count and layout.
        device: Warp device, ``cpu`` or ``cuda:N``; numpy always runs on the CPU.
        drones: Drones per world; 4 is the racing layout.
        steps: Timed control steps of Warp per repeat.
        seed: Seed of start positions and targets.
        repeats: Timed repeats; each row keeps the fastest (other processes may share the cores).
        extras: Entries to add beside the rows (CPU only: :meth:`BenchExtras.for_device`).
        track: Track of the run; the paper's circuit by default.

    Returns:
        ``{"device", "machine", "settings", "results": [row, ...]}`` and the entries of ``extras``.
    """
    wp.init()
    BenchExtras.for_device(device, two_process=extras.two_process, builds=extras.builds, threads=extras.threads)
    track, airframe = track if track is not None else load_track(DEFAULT_TRACK), AIRFRAMES["cf2x"]
    machine = machine_info()
    rows = [_bench_row(track, airframe, w, d, device=device, steps=steps, seed=seed, repeats=repeats)
            for w in worlds for d in drones]
    result: dict[str, Any] = {
        "device": str(wp.get_device(device)),
        "machine": machine,
        "settings": _bench_settings(track, airframe, _bench_cfg(), repeats=repeats, seed=seed),
        "results": rows,
    }
    _add_extras(result, extras, track, steps=steps, seed=seed, repeats=repeats)
    return result


def _add_extras(result: dict[str, Any], extras: BenchExtras, track: TrackSpec, *, steps: int, seed: int,
                repeats: int) -> None:
    """Time the entries of ``extras`` at 4096 worlds × 4 drones into ``result``, the machine's load read after the
    in-process ones (the others run in processes of their own)."""
    if extras.threads > 1:
        result["threaded"] = time_world(4096, 4, device=result["device"], steps=steps, repeats=repeats, seed=seed,
                                        cpu_threads=extras.threads, track=track)
    result["machine"]["load_avg_1min_end"] = _load_avg()
    if extras.builds and result["device"] == "cpu":
        result["builds"] = run_build_comparison(4096, 4, steps=steps, seed=seed, repeats=repeats)
    if extras.two_process:
        result["two_process"] = run_sim_bench_two_process(4096, 4, device=result["device"], steps=steps, seed=seed,
                                                          repeats=repeats)


def time_world(world_count: int, drones: int, *, device: str = "cpu", steps: int = 100, repeats: int = 3,
               seed: int = 0, cpu_threads: int = 1, track: TrackSpec | None = None) -> dict[str, Any]:
    """Warp alone, timed as a row of :func:`run_sim_bench` times it (same track, settings, starts and targets; no
    numpy reference): the best of ``repeats`` runs of ``steps`` control steps, wall clock and process CPU time,
    with the worlds stepped on ``cpu_threads`` threads. For peer comparisons (``benchmarks/crazyflow_peer.py``)."""
    wp.init()
    track, airframe = track if track is not None else load_track(DEFAULT_TRACK), AIRFRAMES["cf2x"]
    world, targets_wp, *_ = _make_world(track, airframe, world_count, drones, device, seed, cpu_threads)
    time_warp(world, targets_wp, WARMUP_STEPS, 0)
    times = [time_warp(world, targets_wp, steps, WARMUP_STEPS + r * steps) for r in range(repeats)]
    n = world_count * drones
    rate = n * steps / min(t[0] for t in times)
    return {
        "worlds": world_count,
        "drones": drones,
        "cpu_threads": cpu_threads,
        "steps": steps,
        "drone_ctrl_steps_per_s": round(rate),
        "drone_substeps_per_s": round(rate * world.sim.substeps),
        "drone_ctrl_steps_per_cpu_s": round(n * steps / min(t[1] for t in times)),
        "mean_speed_m_s": round(float(np.linalg.norm(world.state.vel.numpy(), axis=1).mean()), 3),
        "settings": _bench_settings(track, airframe, _bench_cfg(), repeats=repeats, seed=seed),
    }


def _restorer(world: World) -> Callable[[], None]:
    """A function that puts ``world``'s state, race counters and per-drone buffers back as they are now, with the
    crash flags cleared."""
    mutable = [a for a in (*vars(world.state).values(), *vars(world.race).values(), world.integral, world.heading,
                           world.rpy, world.ext_force) if isinstance(a, wp.array)]
    snapshot = [wp.clone(a) for a in mutable]

    def restore() -> None:
        for a, saved in zip(mutable, snapshot, strict=True):
            wp.copy(a, saved)
        world.race.out.zero_()

    return restore


def _best_per_call(world: World, restore: Callable[[], None], run: Callable[[], Any], count: int, *,
                   repeats: int, graphed: bool = False) -> tuple[float, float]:
    """Wall and process CPU seconds per call of ``run``, ``count`` calls in a row from the restored state, best of
    ``repeats``; the clock read after the device has finished (``wp.synchronize_device``). With ``graphed``, on a GPU
    the ``count`` calls are captured once as a CUDA graph and its launch is timed: the GPU's time for the calls
    without Python's time to launch each of them."""
    calls = _captured(world.device, run, count) if graphed and _is_cuda(world.device) else None
    times = []
    for _ in range(repeats):
        restore()
        wp.synchronize_device(world.device)
        start, cpu = time.perf_counter(), time.process_time()
        if calls is not None:
            wp.capture_launch(calls)
        else:
            for _ in range(count):
                run()
        wp.synchronize_device(world.device)
        times.append((time.perf_counter() - start, time.process_time() - cpu))
    return min(t[0] for t in times) / count, min(t[1] for t in times) / count


def _captured(device: str, run: Callable[[], Any], count: int) -> Any:
    """A CUDA graph of ``count`` calls of ``run`` on ``device`` (recorded, not run)."""
    with wp.ScopedCapture(device=device) as capture:
        for _ in range(count):
            run()
    return capture.graph


def kernel_profile(world_count: int, drones: int, *, device: str = "cpu", launches: int = 30, repeats: int = 9,
                   seed: int = 0, track: TrackSpec | None = None) -> dict[str, Any]:
    """Where a control step's time goes: each kernel of :meth:`World.step` timed alone, on the state of a world
    that :func:`time_world` would time (same track, settings, starts and targets, after the warm-up steps).

    Each kernel's recorded launch runs ``launches`` times in a row from the same state (restored before every
    repeat, crash flags cleared), best of ``repeats``; then ``launches`` whole control steps are timed the same way
    (crash flags cleared before each, as :func:`time_world` does), so that the rows can be compared with their sum.
    Wall clock (read after synchronising the device) and process CPU time. On a GPU a kernel's ``launches`` launches
    are timed as one CUDA graph (the GPU's time, not Python's to launch them), and a whole step is
    :meth:`World.step`'s own graph launch.
    """
    wp.init()
    track, airframe = track if track is not None else load_track(DEFAULT_TRACK), AIRFRAMES["cf2x"]
    world, targets_wp, *_ = _make_world(track, airframe, world_count, drones, device, seed)
    time_warp(world, targets_wp, WARMUP_STEPS, 0)
    restore = _restorer(world)
    best_of = partial(_best_per_call, world, restore, repeats=repeats)  # each repeat starts from the snapshot
    rows = _kernel_rows(world, best_of, launches)
    wall, cpu = best_of(lambda: (world.race.out.zero_(), world.step()), launches)
    return {
        "worlds": world_count,
        "drones": drones,
        "device": world.device,
        "launches": launches,
        "repeats": repeats,
        "kernels": rows,
        "step_wall_ms": 1e3 * wall,
        "step_cpu_ms": 1e3 * cpu,
        "kernels_cpu_ms": sum(r["cpu_ms_per_step"] for r in rows),
        "kernels_wall_ms": sum(r["wall_ms_per_step"] for r in rows),
        "machine": machine_info(),
        "settings": _bench_settings(track, airframe, _bench_cfg(), repeats=repeats, seed=seed),
    }


def _kernel_rows(world: World, best_of: Callable[..., tuple[float, float]], launches: int) -> list[dict[str, Any]]:
    """One row per kernel of a control step, in launch order: its recorded launch timed ``launches`` times in a row
    by ``best_of`` (wall and CPU seconds per call; on a GPU from a graph of the launches), per launch, per drone and
    per control step."""
    order: dict[str, list] = {}
    for cmd in world._simulate(record=True):  # one control step's launches, arguments packed
        order.setdefault(cmd.kernel.key, []).append(cmd)
    n = world.drone_count
    rows = []
    for key, cmds in order.items():
        wall, cpu = best_of(cmds[0].launch, launches, graphed=True)
        rows.append({"kernel": key, "launches_per_step": len(cmds), "cpu_ms_per_launch": 1e3 * cpu,
                     "cpu_ns_per_drone": 1e9 * cpu / n, "cpu_ms_per_step": 1e3 * cpu * len(cmds),
                     "wall_ms_per_launch": 1e3 * wall, "wall_ns_per_drone": 1e9 * wall / n,
                     "wall_ms_per_step": 1e3 * wall * len(cmds)})
    return rows


def format_kernel_table(result: dict[str, Any]) -> str:
    """Markdown table of a :func:`kernel_profile` result, with the whole control step under it: process CPU time on
    the CPU (robust to other processes' load), wall clock on a GPU (where the host's CPU time is not the kernels')."""
    m, n = result["machine"], result["worlds"] * result["drones"]
    clock, name = ("wall", "wall clock") if str(result["device"]).startswith("cuda") else ("cpu", "CPU")
    lines = [
        f"device {result['device']} · {m['cpu']} · {m['cores']} cores · Warp {m['warp']} · load {m['load_avg_1min']}"
        f" · {result['worlds']} worlds × {result['drones']} drones",
        "",
        f"| kernel | launches per control step | {name} per launch | per drone | per control step |",
        "|---|---:|---:|---:|---:|",
    ]
    for r in result["kernels"]:
        lines.append(f"| `{r['kernel']}` | {r['launches_per_step']} | {r[f'{clock}_ms_per_launch']:.3f} ms | "
                     f"{r[f'{clock}_ns_per_drone']:.1f} ns | {r[f'{clock}_ms_per_step']:.2f} ms |")
    step = result[f"step_{clock}_ms"]
    lines += ["", f"The kernels alone: {result[f'kernels_{clock}_ms']:.2f} ms per control step; whole control steps "
                  f"(launches and the step's flag clearing included): {step:.2f} ms ({name}), "
                  f"{n / step / 1e3:.3f} M drone-ctrl-steps per {'s' if clock == 'wall' else 'CPU-s'}."]
    return "\n".join(lines)


def two_process_worker(world_count: int, drones: int, device: str, steps: int, seed: int, repeats: int) -> None:
    """Child side of :func:`run_sim_bench_two_process`: time each repeat when told to on stdin, report on stdout.

    Prints ``ready`` after the warm-up and before each repeat, waits for a line on stdin, then prints the repeat's
    ``span start end`` (``time.perf_counter``, a system-wide monotonic clock on Linux). Other output (Warp's
    banner) may come in between and is skipped by the parent.
    """
    wp.init()  # quiet: spiral.sim.world sets Warp's log level on import
    world, targets_wp, *_ = _make_world(load_track(DEFAULT_TRACK), AIRFRAMES["cf2x"], world_count, drones, device,
                                        seed)
    time_warp(world, targets_wp, WARMUP_STEPS, 0)
    for r in range(repeats):
        print("ready", flush=True)
        sys.stdin.readline()
        begin = time.perf_counter()
        time_warp(world, targets_wp, steps, WARMUP_STEPS + r * steps)
        print(f"span {begin!r} {time.perf_counter()!r}", flush=True)


def _read_tagged(proc: subprocess.Popen, tag: str) -> str:
    """Next line of ``proc``'s stdout that starts with ``tag``."""
    for line in proc.stdout:
        if line.startswith(tag):
            return line
    raise RuntimeError(f"two-process benchmark worker exited with {proc.wait()} before reporting {tag!r}")


def run_sim_bench_two_process(
    world_count: int = 4096, drones: int = 4, *, device: str = "cpu", steps: int = 100, seed: int = 0,
    repeats: int = 3
) -> dict[str, Any]:
    """Run one Warp row in two processes at once (a CPU launch uses one thread) and report their sum.

    The children are fresh interpreters (``subprocess``), released together for each repeat. The aggregate of a
    repeat is both processes' drone-control-steps over the wall time from the first start to the last end; the best
    repeat is kept.
    """
    procs = [_start_worker(world_count, drones, device, steps, seed + i, repeats) for i in range(2)]
    spans = _released_spans(procs, repeats)
    n = world_count * drones
    aggregates = [2 * n * steps / (max(s[r][1] for s in spans) - min(s[r][0] for s in spans)) for r in range(repeats)]
    best = int(np.argmax(aggregates))
    return {
        "worlds": world_count,
        "drones": drones,
        "processes": 2,
        "steps": steps,
        "per_process_drone_ctrl_steps_per_s": [round(n * steps / (s[best][1] - s[best][0])) for s in spans],
        "aggregate_drone_ctrl_steps_per_s": round(aggregates[best]),
    }


def _start_worker(world_count: int, drones: int, device: str, steps: int, seed: int,
                  repeats: int) -> subprocess.Popen:
    """A fresh interpreter running :func:`two_process_worker`, talking through pipes."""
    code = (f"from spiral.sim.bench import two_process_worker; "
            f"two_process_worker({world_count}, {drones}, {device!r}, {steps}, {seed}, {repeats})")
    return subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)


def _released_spans(procs: list[subprocess.Popen], repeats: int) -> list[list[tuple[float, float]]]:
    """Release the workers ``procs`` together for each of ``repeats`` repeats, each once every one is ready; each
    worker's ``(start, end)`` per repeat. The workers are closed and waited for afterwards."""
    spans: list[list[tuple[float, float]]] = [[] for _ in procs]
    try:
        for _ in range(repeats):
            for p in procs:
                _read_tagged(p, "ready")
            for p in procs:
                p.stdin.write("go\n")
                p.stdin.flush()
            for i, p in enumerate(procs):
                begin, end = (float(v) for v in _read_tagged(p, "span").split()[1:])
                spans[i].append((begin, end))
    finally:
        for p in procs:
            p.stdin.close()
            p.wait()
    return spans


def run_build_comparison(world_count: int = 4096, drones: int = 4, *, steps: int = 100, seed: int = 0,
                         repeats: int = 3) -> dict[str, Any]:
    """Time one Warp row with each simulator build (``SPIRAL_CPU_TARGET`` portable, native; ``avx2`` builds the
    portable one), each repeat in a fresh process with its build, the builds taking turns, and keep each build's best
    repeat."""
    rates: dict[str, list[int]] = {target: [] for target in ("portable", "native")}
    code = (f"import json; from spiral.sim.bench import time_world; "
            f"print('row', json.dumps(time_world({world_count}, {drones}, steps={steps}, repeats=1, seed={seed})))")
    for _ in range(repeats):
        for target in rates:
            env = {**os.environ, CPU_TARGET_ENV: target}
            out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
            row = next(line for line in out.stdout.splitlines() if line.startswith("row "))
            rates[target].append(json.loads(row[4:])["drone_ctrl_steps_per_s"])
    best = {target: max(r) for target, r in rates.items()}
    return {"worlds": world_count, "drones": drones, "steps": steps, "repeats": repeats,
            "drone_ctrl_steps_per_s": best, "portable_over_native": round(best["portable"] / best["native"], 3)}


def format_bench_table(result: dict[str, Any]) -> str:
    """Markdown table of a :func:`run_sim_bench` result, with the machine and the two-process row if present."""
    m = result["machine"]
    lines = [
        f"device {result['device']} · {m['cpu']} · {m['cores']} cores · Python {m['python']} · "
        f"Warp {m['warp']} · numpy {m['numpy']} · load {m['load_avg_1min']} → {m.get('load_avg_1min_end')}",
        "",
        "| worlds | drones/world | drone-ctrl-steps/s | drone-substeps/s | numpy drone-ctrl-steps/s "
        "(numpy steps) | speed-up | Warp per CPU-s |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in result["results"]:
        lines.append(
            f"| {r['worlds']} | {r['drones']} | {r['drone_ctrl_steps_per_s']:,} | {r['drone_substeps_per_s']:,} | "
            f"{r['numpy_drone_ctrl_steps_per_s']:,} ({r['numpy_steps']}) | {r['speedup_vs_numpy']:.1f}× | "
            f"{r['drone_ctrl_steps_per_cpu_s']:,} |"
        )
    two = result.get("two_process")
    if two:
        each = " + ".join(f"{v:,}" for v in two["per_process_drone_ctrl_steps_per_s"])
        lines += ["", f"Two processes side by side, {two['worlds']} worlds × {two['drones']} drones each: "
                      f"{two['aggregate_drone_ctrl_steps_per_s']:,} drone-ctrl-steps/s in aggregate ({each})."]
    builds = result.get("builds")
    if builds:
        rate = builds["drone_ctrl_steps_per_s"]
        lines += ["", f"CPU builds, {builds['worlds']} worlds × {builds['drones']} drones, each repeat in a fresh "
                      f"process: portable {rate['portable']:,}, native {rate['native']:,} drone-ctrl-steps/s "
                      f"(portable {builds['portable_over_native']:.2f}× native)."]
    one = result.get("threaded")
    if one:
        lines += ["", f"One process, worlds stepped on {one['cpu_threads']} threads, {one['worlds']} worlds × "
                      f"{one['drones']} drones: {one['drone_ctrl_steps_per_s']:,} drone-ctrl-steps/s "
                      f"({one['drone_ctrl_steps_per_cpu_s']:,} per CPU-s)."]
    return "\n".join(lines)
