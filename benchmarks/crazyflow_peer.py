"""spiral's simulator against crazyflow 0.4 (JAX) on the CPU, at the same drone count, physics and control rates.

One run of this script measures both, one after the other, each in a fresh process that has the machine's cores to
itself (no affinity or thread limits are set; run it on an idle machine for figures worth quoting):

- spiral: ``spiral.sim.bench.time_world`` in this interpreter (spiral's virtualenv), i.e. exactly what a row of
  ``spiral bench sim`` times for Warp: pid mode, circuit6 with gates and collisions on, crash flags cleared every
  control step, random targets re-drawn every 10 control steps; the worlds are stepped on ``--spiral-threads``
  threads (default: one per core, as XLA spreads crazyflow's step over every core).
- crazyflow: ``crazyflow.Sim`` with first-principles dynamics, Euler integration and the Mellinger state controller
  (``Control.state``: position, velocity, acceleration, attitude, body-rate setpoints), in its own virtualenv
  (``benchmarks/.venv-crazyflow``, created and filled from the package index on first use; crazyflow is never a
  dependency of spiral). The same starts and targets (same seed and draw), commanded as state setpoints.

Both take ``physics_hz / ctrl_hz`` physics steps per control step (240 / 48 = 5 by default); crazyflow's state
controller runs at ``ctrl_hz`` and its attitude, body-rate and force-torque controllers at ``physics_hz``; spiral's
position and attitude loops both run at ``physics_hz``. crazyflow's step has no collision or gate test (MuJoCo
contacts are computed only on request), so the comparison favours it.

Usage (from the repository root, spiral's interpreter)::

    python benchmarks/crazyflow_peer.py --worlds 4096 --drones 4 --json benchmarks/crazyflow_peer.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import time
import venv
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
VENV = Path(__file__).resolve().parent / ".venv-crazyflow"
CRAZYFLOW_REQUIREMENTS = ("crazyflow==0.4.0", "jax")
TRACK = ROOT / "tracks" / "circuit6.yaml"
TARGET_REDRAW_STEPS = 10  # as spiral.sim.bench
WARMUP_STEPS = 5  # as spiral.sim.bench; for crazyflow this includes the JIT compilation
TARGET_DRAWS = 8  # as spiral.sim.bench._make_world
RESULT_TAG = "RESULT "


# ----------------------------------------------------------------------------------------------------------- workers


def draw_inputs(lo: list[float], hi: list[float], drone_count: int, seed: int):
    """Starts ``(n, 3)``, yaws ``(n,)`` and target sets ``(draws, n, 4)``: the draw of ``spiral.sim.bench``."""
    import numpy as np

    rng = np.random.default_rng(seed)
    start = rng.uniform(lo, hi, (drone_count, 3)).astype(np.float32)
    yaw = rng.uniform(-math.pi, math.pi, drone_count).astype(np.float32)
    targets = np.concatenate(
        [rng.uniform(lo, hi, (TARGET_DRAWS, drone_count, 3)),
         rng.uniform(-math.pi, math.pi, (TARGET_DRAWS, drone_count, 1))], axis=2
    ).astype(np.float32)
    return start, yaw, targets


def spiral_worker(args: argparse.Namespace) -> dict[str, Any]:
    """spiral's half: Warp's ``World`` as ``spiral bench sim`` times it."""
    import warp as wp

    from spiral.sim.bench import time_world

    if (args.physics_hz, args.ctrl_hz) != (240, 48):
        raise SystemExit("spiral's benchmark world runs at 240 Hz physics and 48 Hz control")
    row = time_world(args.worlds, args.drones, device="cpu", steps=args.steps, repeats=args.repeats, seed=args.seed,
                     cpu_threads=args.spiral_threads)
    row.update(sim="spiral", version=f"warp {wp.config.version}, {args.spiral_threads} threads")
    return row


def crazyflow_worker(args: argparse.Namespace) -> dict[str, Any]:
    """crazyflow's half: ``Sim.state_control`` on each re-draw, ``Sim.step(substeps)`` every control step."""
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    import crazyflow
    import jax
    import jax.numpy as jnp
    import numpy as np
    from crazyflow import Control, Sim

    substeps = args.physics_hz // args.ctrl_hz
    w, d = args.worlds, args.drones
    n = w * d
    sim = Sim(n_worlds=w, n_drones=d, control=Control.state, freq=args.physics_hz, state_freq=args.ctrl_hz,
              attitude_freq=args.physics_hz, body_rate_freq=args.physics_hz, force_torque_freq=args.physics_hz,
              device="cpu", rng_key=args.seed)
    start, yaw, targets = draw_inputs(args.lo, args.hi, n, args.seed)
    sim.reset()
    half = yaw.reshape(w, d) / 2
    quat = np.stack([np.zeros_like(half), np.zeros_like(half), np.sin(half), np.cos(half)], axis=-1)  # x, y, z, w
    states = sim.data.states.replace(pos=jnp.asarray(start.reshape(w, d, 3)), quat=jnp.asarray(quat, jnp.float32))
    sim.data = sim.data.replace(states=states)
    cmds = []
    for t in targets:  # [x, y, z, vx, vy, vz, ax, ay, az, qx, qy, qz, qw, wx, wy, wz]; only the yaw of q is used
        c = np.zeros((n, 16), np.float32)
        c[:, :3] = t[:, :3]
        c[:, 11], c[:, 12] = np.sin(t[:, 3] / 2), np.cos(t[:, 3] / 2)
        cmds.append(jnp.asarray(c.reshape(w, d, 16)))

    def run(steps: int, first: int) -> tuple[float, float]:
        sim.data.states.pos.block_until_ready()
        begin, cpu = time.perf_counter(), time.process_time()
        for i in range(first, first + steps):
            if i % TARGET_REDRAW_STEPS == 0:
                sim.state_control(cmds[(i // TARGET_REDRAW_STEPS) % len(cmds)])
            sim.step(substeps)
        sim.data.states.pos.block_until_ready()
        return time.perf_counter() - begin, time.process_time() - cpu

    run(WARMUP_STEPS, 0)
    times = [run(args.steps, WARMUP_STEPS + r * args.steps) for r in range(args.repeats)]
    rate = n * args.steps / min(t[0] for t in times)
    vel = np.asarray(sim.data.states.vel).reshape(n, 3)
    return {
        "sim": "crazyflow",
        "version": f"crazyflow {crazyflow.__version__}, jax {jax.__version__}",
        "worlds": w,
        "drones": d,
        "steps": args.steps,
        "drone_ctrl_steps_per_s": round(rate),
        "drone_substeps_per_s": round(rate * substeps),
        "drone_ctrl_steps_per_cpu_s": round(n * args.steps / min(t[1] for t in times)),
        "mean_speed_m_s": round(float(np.linalg.norm(vel, axis=1).mean()), 3),
        "settings": {"drone": str(sim.drone), "dynamics": str(sim.dynamics), "control": str(sim.control),
                     "integrator": str(sim.integrator), "physics_hz": args.physics_hz, "ctrl_hz": args.ctrl_hz,
                     "jax_devices": [str(x) for x in jax.devices()]},
    }


# ------------------------------------------------------------------------------------------------------------ parent


def ensure_crazyflow_venv(python: Path | None) -> Path:
    """The interpreter of crazyflow's virtualenv; create it and install crazyflow from the package index if needed."""
    if python is not None:
        return python
    exe = VENV / "bin" / "python"
    probe = [str(exe), "-c", "import crazyflow, jax; print('crazyflow', crazyflow.__version__)"]  # mjx prints too
    if exe.exists() and "crazyflow 0.4.0" in subprocess.run(probe, capture_output=True, text=True).stdout.splitlines():
        return exe
    print(f"installing {' '.join(CRAZYFLOW_REQUIREMENTS)} into {VENV} ...", file=sys.stderr, flush=True)
    venv.EnvBuilder(with_pip=True, clear=True).create(VENV)
    subprocess.run([str(exe), "-m", "pip", "install", "--quiet", *CRAZYFLOW_REQUIREMENTS], check=True)
    return exe


def run_worker(python: str | Path, which: str, args: argparse.Namespace, env: dict[str, str],
               cwd: Path = ROOT) -> dict[str, Any]:
    """Run one half in a fresh interpreter and return the JSON it reports (other output only on failure)."""
    cmd = [str(python), str(Path(__file__).resolve()), "--worker", which, "--worlds", str(args.worlds),
           "--drones", str(args.drones), "--steps", str(args.steps), "--repeats", str(args.repeats),
           "--seed", str(args.seed), "--physics-hz", str(args.physics_hz), "--ctrl-hz", str(args.ctrl_hz),
           "--spiral-threads", str(args.spiral_threads), "--lo", *map(str, args.lo), "--hi", *map(str, args.hi)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=cwd)
    lines = [x for x in proc.stdout.splitlines() if x.startswith(RESULT_TAG)]
    if proc.returncode != 0 or not lines:
        sys.stderr.write(proc.stdout + proc.stderr)
        raise SystemExit(f"{which} worker failed (exit {proc.returncode})")
    return json.loads(lines[-1][len(RESULT_TAG):])


def arena(track: Path) -> tuple[list[float], list[float]]:
    """The box starts and targets are drawn from: the track's bounds shrunk by 0.5 m (as spiral.sim.bench)."""
    from spiral.config.load import load_track

    b = load_track(track).bounds
    return [v + 0.5 for v in b.min], [v - 0.5 for v in b.max]


def load() -> float:
    return round(os.getloadavg()[0], 2)


def format_table(result: dict[str, Any]) -> str:
    """Markdown table of both halves and their ratio."""
    m = result["machine"]
    lines = [f"{m['cpu']} · {m['cores']} cores · Python {m['python']} · load {m['load_start']} → {m['load_end']}",
             f"{result['worlds']} worlds × {result['drones']} drones, {result['physics_hz']} Hz physics, "
             f"{result['ctrl_hz']} Hz control, {result['steps']} timed control steps, best of {result['repeats']}",
             "",
             "| simulator | drone-ctrl-steps/s | drone-substeps/s | per CPU-s | mean speed [m/s] |",
             "|---|---:|---:|---:|---:|"]
    for r in result["results"]:
        lines.append(f"| {r['sim']} ({r['version']}) | {r['drone_ctrl_steps_per_s']:,} | "
                     f"{r['drone_substeps_per_s']:,} | {r['drone_ctrl_steps_per_cpu_s']:,} | {r['mean_speed_m_s']} |")
    lines += ["", f"spiral / crazyflow: {result['ratio_wall']:.2f}× wall clock, {result['ratio_cpu']:.2f}× per CPU-s"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--worlds", type=int, default=4096)
    parser.add_argument("--drones", type=int, default=4, help="drones per world")
    parser.add_argument("--steps", type=int, default=100, help="timed control steps per repeat")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--physics-hz", type=int, default=240)
    parser.add_argument("--ctrl-hz", type=int, default=48)
    parser.add_argument("--spiral-threads", type=int, default=os.cpu_count() or 1,
                        help="threads stepping spiral's worlds (default: one per core)")
    parser.add_argument("--json", type=Path, help="also write the result here")
    parser.add_argument("--crazyflow-python", type=Path, help="an interpreter with crazyflow 0.4 (skips the venv)")
    parser.add_argument("--only", choices=("spiral", "crazyflow"), help="run one half only")
    parser.add_argument("--worker", choices=("spiral", "crazyflow"), help=argparse.SUPPRESS)
    parser.add_argument("--lo", type=float, nargs=3, help=argparse.SUPPRESS)
    parser.add_argument("--hi", type=float, nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.physics_hz % args.ctrl_hz:
        parser.error("--ctrl-hz must divide --physics-hz")
    if args.worker:
        row = (spiral_worker if args.worker == "spiral" else crazyflow_worker)(args)
        print(RESULT_TAG + json.dumps(row), flush=True)
        return

    args.lo, args.hi = arena(TRACK)
    spiral_env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    crazyflow_env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # keep spiral out of that interpreter
    cpu = next((x.split(":", 1)[1].strip() for x in Path("/proc/cpuinfo").read_text().splitlines()
                if x.startswith("model name")), platform.processor()) if Path("/proc/cpuinfo").exists() else "?"
    machine = {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(), "load_start": load()}
    rows = []
    if args.only != "crazyflow":
        rows.append(run_worker(sys.executable, "spiral", args, spiral_env))
    if args.only != "spiral":
        python = ensure_crazyflow_venv(args.crazyflow_python)
        VENV.mkdir(exist_ok=True)  # MuJoCo may write MUJOCO_LOG.TXT into the working directory: keep it there
        rows.append(run_worker(python, "crazyflow", args, crazyflow_env, cwd=VENV))
    machine["load_end"] = load()
    result: dict[str, Any] = {"machine": machine, "worlds": args.worlds, "drones": args.drones,
                              "physics_hz": args.physics_hz, "ctrl_hz": args.ctrl_hz, "steps": args.steps,
                              "repeats": args.repeats, "seed": args.seed, "results": rows}
    if len(rows) == 2:
        result["ratio_wall"] = rows[0]["drone_ctrl_steps_per_s"] / rows[1]["drone_ctrl_steps_per_s"]
        result["ratio_cpu"] = rows[0]["drone_ctrl_steps_per_cpu_s"] / rows[1]["drone_ctrl_steps_per_cpu_s"]
        print(format_table(result))
    else:
        print(json.dumps(result, indent=1))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
