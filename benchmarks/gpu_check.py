"""The first run of spiral on a GPU: five checks in about ten minutes, one PASS, FAIL or INFO line each, and JSON.

Run from the repository root with spiral's interpreter (torch and Warp both with CUDA):

    python benchmarks/gpu_check.py --device cuda:0 --json gpu_check.json
    python benchmarks/gpu_check.py --device cpu --quick      # the same checks at tiny sizes, about a minute

The checks, in order (``--only NAME`` runs one; repeatable):

- ``agreement``: 32 worlds × 2 drones fly 2 s (96 control steps, PID mode, 240 Hz physics) from fixed starts
  towards a fixed sequence of targets, in a part of circuit6's arena without gates, each drone of a world in its own
  lane; positions, velocities, attitudes and body rates every 8 control steps are compared with the CPU reference
  saved in ``benchmarks/gpu_check_reference.npz`` (its starts and targets included). Pass: no contact or gate event
  in either, every difference within :data:`TOLERANCE` and, on a CPU with the portable build and the reference's
  Warp version, every value the reference's to the bit.
- ``graph``: 300 control steps of 64 worlds × 4 drones (random targets; drones crash, pass gates) replayed from the
  CUDA graph against launching every kernel afresh; pass: every state, race, controller and attitude array equal to
  the bit. On a CPU the replayed launches take the graph's place.
- ``host_syncs``: the calls that make the host wait for the GPU (:class:`spiral.core.host_syncs.HostSyncCounter`)
  in each env step of a training rollout of pipelines/full.yaml's solo, 1v1 and 2v2 stages (the multi-drone stages
  from the published checkpoints and pool, as ``spiral bench ppo`` profiles them), with the five most frequent call
  sites: on the device's own path and on the path without synchronisations (``sync_free`` of the env and the pool
  opponents, the default off a CPU); pass: none on the latter, in every step.
- ``rates``: ``spiral bench ppo``'s profile of the solo stage at 1024, 4096, 16384 and 65536 worlds: env steps per
  second of the rollout and samples per second of PPO's update (a size that does not fit the device's memory is
  skipped). Reported.
- ``smoke``: ``spiral run pipelines/smoke.yaml --device DEVICE`` into a temporary runs and checkpoints folder; pass:
  it exits 0, every step leaves a manifest, every training step records the device, and both final policies and the
  report are written.

``--write-reference`` (on a CPU, portable build) flies the agreement check's drones and saves the reference.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import platform
import subprocess
import sys
import tempfile
import time
import traceback
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import warp as wp

from spiral.config import AIRFRAMES, SimCfg, load_pipeline, load_track, resolve_airframe
from spiral.core.device import check_device
from spiral.core.host_syncs import HostSyncCounter
from spiral.core.numerics import cpu_target, host_runs_x86_64_v3
from spiral.env import RaceSetting
from spiral.env.mixed import MixedRaceEnv
from spiral.selfplay.curriculum import published_opponents
from spiral.selfplay.opponents import PoolOpponents
from spiral.sim import World
from spiral.sim.bench import machine_info
from spiral.train import StageStart, StageTrainer
from spiral.train.profile import profile_iteration

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT / "benchmarks" / "gpu_check_reference.npz"
"""The agreement check's CPU reference (``--write-reference``)."""
TRACK = ROOT / "tracks" / "circuit6.yaml"
PIPELINE = ROOT / "pipelines" / "full.yaml"
"""The pipeline whose stages the host-sync and rate checks measure."""
SMOKE = ROOT / "pipelines" / "smoke.yaml"
CHECKS = ("agreement", "graph", "host_syncs", "rates", "smoke")

FLIGHT = {"worlds": 32, "drones": 2, "steps": 96, "hold": 12, "every": 8, "seed": 0}
"""The agreement check's flight: worlds × drones, control steps (2 s at 48 Hz), control steps each target is held,
control steps between two saved samples, seed of the starts and targets."""
BOX = ((-0.3, 1.8), (0.8, 2.4))
"""x and z range [m] of the starts and targets: the part of circuit6's arena between its gates."""
LANES = ((-1.6, -0.7), (-0.2, 0.7))
"""y range [m] of each drone slot of a world, half a metre apart, so that the two drones never meet."""
FIELDS = ("pos", "vel", "quat", "omega")
TOLERANCE = {"pos": 1e-3, "vel": 3e-3, "quat": 5e-4, "omega": 1e-2}
"""Largest difference from the CPU reference over 2 s of flight, by state: metres, m/s, quaternion components,
rad/s. Why these: docs/benchmarks.md, "On a GPU"."""
RATE_WORLDS = (1024, 4096, 16384, 65536)
QUICK = {"graph_worlds": 16, "sync_worlds": 16, "sync_steps": 96, "rate_worlds": (16, 64)}
"""Sizes of ``--quick``."""
FULL = {"graph_worlds": 64, "sync_worlds": None, "sync_steps": 48, "rate_worlds": RATE_WORLDS}
"""Sizes of a real run (``sync_worlds`` None: each stage's own)."""


def flight_inputs(seed: int) -> dict[str, np.ndarray]:
    """The agreement flight's starts ``(n, 3)``, yaws ``(n,)`` and targets ``(draws, n, 4)``, each drone in its
    lane."""
    rng = np.random.default_rng(seed)
    n, draws = FLIGHT["worlds"] * FLIGHT["drones"], FLIGHT["steps"] // FLIGHT["hold"]
    lane = np.asarray(LANES)[np.arange(n) % FLIGHT["drones"]]
    lo = np.stack([np.full(n, BOX[0][0]), lane[:, 0], np.full(n, BOX[1][0])], axis=1)
    hi = np.stack([np.full(n, BOX[0][1]), lane[:, 1], np.full(n, BOX[1][1])], axis=1)
    start = rng.uniform(lo, hi).astype(np.float32)
    yaw = rng.uniform(-math.pi, math.pi, n).astype(np.float32)
    targets = np.concatenate([rng.uniform(lo, hi, (draws, n, 3)), rng.uniform(-math.pi, math.pi, (draws, n, 1))],
                             axis=2).astype(np.float32)
    return {"start": start, "yaw": yaw, "targets": targets}


def fly(device: str, inputs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Fly the agreement flight on ``device``: each state every ``every`` control steps ``(samples, n, k)`` and the
    race's event counters at the end."""
    world = World(load_track(TRACK), AIRFRAMES["cf2x"], SimCfg(), world_count=FLIGHT["worlds"],
                  drones_per_world=FLIGHT["drones"], device=device)
    world.reset_all(inputs["start"], inputs["yaw"])
    samples: dict[str, list[np.ndarray]] = {k: [] for k in FIELDS}
    for i in range(FLIGHT["steps"]):
        if i % FLIGHT["hold"] == 0:
            world.cmd.assign(inputs["targets"][i // FLIGHT["hold"]])
        world.step()
        if (i + 1) % FLIGHT["every"] == 0:
            for k in FIELDS:
                samples[k].append(getattr(world.state, k).numpy().copy())
    return {**{k: np.stack(v) for k, v in samples.items()}, "out": world.race.out.numpy().copy(),
            "gates_passed": world.race.gates_passed.numpy().copy()}


def write_reference(path: Path = REFERENCE) -> dict[str, Any]:
    """Fly the agreement flight on this CPU with the portable build and save it, its inputs and how it was made."""
    if cpu_target() != "portable" or not host_runs_x86_64_v3():
        raise SystemExit("--write-reference: only with the portable build (SPIRAL_CPU_TARGET unset) on an x86-64-v3 "
                         "host, whose bits every such host reproduces")
    inputs = flight_inputs(FLIGHT["seed"])
    got = fly("cpu", inputs)
    if got["out"].any() or got["gates_passed"].any():
        raise SystemExit("--write-reference: a drone crashed or passed a gate; the flight must be smooth")
    made = {"warp": wp.config.version, "cpu": machine_info()["cpu"], "cpu_target": cpu_target(),
            "written": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    np.savez_compressed(path, **inputs, **got, **{f"meta_{k}": np.array(v) for k, v in made.items()})
    return {"path": str(path), "bytes": path.stat().st_size, **made}


def agreement(device: str, *, reference: Path = REFERENCE) -> dict[str, Any]:
    """Fly the reference's flight on ``device`` and compare it with the reference: largest difference by state
    (and by sample time, for positions), equal events, and the bits where the host should reproduce them."""
    ref = dict(np.load(reference))
    got = fly(device, {k: ref[k] for k in ("start", "yaw", "targets")})
    errors = {k: float(np.abs(got[k].astype(np.float64) - ref[k]).max()) for k in FIELDS}
    events = all(np.array_equal(got[k], ref[k]) for k in ("out", "gates_passed"))
    bitwise = all(np.array_equal(got[k], ref[k]) for k in FIELDS) and events
    bits_expected = (device == "cpu" and cpu_target() == "portable" and host_runs_x86_64_v3()
                     and str(ref["meta_warp"]) == wp.config.version)
    within = all(errors[k] <= TOLERANCE[k] for k in FIELDS)
    ok = events and within and (bitwise or not bits_expected)
    diffs = ", ".join(f"{k} {errors[k]:.1e} (≤ {TOLERANCE[k]:g})" for k in FIELDS)
    summary = (f"largest differences after up to 2 s: {diffs}; events {'equal' if events else 'DIFFER'}; "
               f"bit for bit: {'yes' if bitwise else 'no'}{' (expected on this host)' if bits_expected else ''}")
    pos_by_time = np.abs(got["pos"].astype(np.float64) - ref["pos"]).max(axis=(1, 2))
    return {"status": "pass" if ok else "fail", "summary": summary, "max_abs_diff": errors, "tolerance": TOLERANCE,
            "events_equal": events, "bitwise": bitwise, "bitwise_expected": bits_expected,
            "pos_diff_by_sample": pos_by_time.tolist(), "reference": {k[5:]: str(v) for k, v in ref.items()
                                                                      if k.startswith("meta_")}}


def _arrays(world: World) -> dict[str, np.ndarray]:
    """Copies of every state, race, controller, heading and attitude array of ``world``."""
    named = {**{f"state.{k}": v for k, v in vars(world.state).items()},
             **{f"race.{k}": v for k, v in vars(world.race).items()},
             "integral": world.integral, "heading": world.heading, "rpy": world.rpy, "ext_force": world.ext_force}
    return {k: v.numpy().copy() for k, v in named.items() if isinstance(v, wp.array)}


def _graph_run(device: str, worlds: int, fast: bool, *, steps: int, seed: int) -> tuple[dict[str, np.ndarray], bool]:
    """``steps`` control steps of ``worlds`` × 4 drones on circuit6 towards random targets (re-drawn every 10
    steps), on the device's fast path (a CUDA graph, or on a CPU replayed launches) or with plain launches; every
    array at the end, and whether the fast path ran."""
    track = load_track(TRACK)
    world = World(track, AIRFRAMES["cf2x"], SimCfg(), world_count=worlds, drones_per_world=4, device=device)
    world.use_graph, world.replay_launches = fast and world.use_graph, fast and not world.use_graph
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(track.bounds.min) + 0.5, np.asarray(track.bounds.max) - 0.5
    n = world.drone_count
    world.reset_all(rng.uniform(lo, hi, (n, 3)), rng.uniform(-math.pi, math.pi, n))
    for i in range(steps):
        if i % 10 == 0:
            world.cmd.assign(np.c_[rng.uniform(lo, hi, (n, 3)), rng.uniform(-math.pi, math.pi, n)].astype(np.float32))
        world.step()
    return _arrays(world), world._graph is not None or world._launches is not None


def graph(device: str, *, worlds: int = 64, steps: int = 300, seed: int = 1) -> dict[str, Any]:
    """The device's fast path (CUDA graph; on a CPU replayed launches) against plain launches, bit for bit."""
    plain, _ = _graph_run(device, worlds, False, steps=steps, seed=seed)
    fast, fast_ran = _graph_run(device, worlds, True, steps=steps, seed=seed)
    differ = sorted(k for k in plain if not np.array_equal(plain[k], fast[k]))
    path = "CUDA graph" if wp.get_device(device).is_cuda else "replayed launches"
    crashed, passes = int((plain["race.out"] != 0).sum()), int(plain["race.gates_passed"].sum())
    ok = not differ and fast_ran
    verdict = "equal to the bit" if not differ else f"DIFFER in {', '.join(differ)}"
    summary = (f"{path} against plain launches, {steps} control steps of {worlds} worlds × 4 drones ({crashed} "
               f"drones out, {passes} gate pass{'' if passes == 1 else 'es'}): {verdict}")
    return {"status": "pass" if ok else "fail", "summary": summary, "path": path, "differing_arrays": differ,
            "drones_out": crashed, "gate_passes": passes, "worlds": worlds, "steps": steps}


def _stage_trainer(name: str, device: str, worlds: int | None, scratch: Path) -> StageTrainer:
    """A trainer of pipelines/full.yaml's stage ``name`` (``worlds`` worlds, or its own), a multi-drone stage from
    the published best of the stage it starts from, racing a copy of the published pool (or frozen opponent)."""
    spec, track = load_pipeline(PIPELINE)
    index = [s.name for s in spec.stages].index(name)
    stage = spec.stages[index] if worlds is None else spec.stages[index].model_copy(update={"worlds": worlds})
    published = ROOT / "checkpoints" / spec.name
    start = None
    if stage.scenario != "solo":
        init = published / str(spec.init_stage(index)) / "best.pt"
        frozen = published / stage.selfplay.opponent_from / "best.pt" if stage.selfplay.opponent_from else None
        opponents = published_opponents(stage, init, scratch, pool_dir=published / "pool", opponent_checkpoint=frozen,
                                        device=device, seed=spec.seed)
        start = StageStart(init, opponents.worlds)
    setting = RaceSetting(track, resolve_airframe(spec.airframe, source=str(PIPELINE)), spec.sim)
    return StageTrainer(setting, stage, scratch / "run", start=start, device=device, seed=spec.seed, progress=False,
                        log=lambda _: None)


def set_sync_free(trainer: StageTrainer, on: bool = True) -> None:
    """Put ``trainer``'s training env and its pool opponents on the path without host synchronisations (their
    ``sync_free``, the default off a CPU), or (``on`` false) on the CPU's path."""
    env = trainer.env
    for part in env.parts.values() if isinstance(env, MixedRaceEnv) else [env]:
        part.sync_free = on
        if isinstance(part.opponent_policy, PoolOpponents):
            part.opponent_policy.sync_free = on


def count_syncs(trainer: StageTrainer, steps: int) -> dict[str, Any]:
    """Host synchronisations in each of ``steps`` env steps of a training rollout (the policy acting and PPO
    storing the step left out), with the most frequent call sites and the learner episodes that ended (so resets)."""
    alg, env = trainer.runner.alg, trainer.vec_env
    alg.train_mode()
    obs, per_step, sites, ended = env.get_observations().to(trainer.device), [], Counter(), 0
    with torch.inference_mode():
        for _ in range(steps):
            actions = alg.act(obs)
            with HostSyncCounter() as syncs:
                obs, rewards, dones, extras = env.step(actions.to(env.device))
            per_step.append(syncs.total)
            sites.update(syncs.sites)
            ended += int(dones.sum())
            alg.process_env_step(obs, rewards, dones, extras)
            if alg.storage.step == alg.storage.num_transitions_per_env:  # a full rollout: stored, never learnt from
                alg.storage.clear()
    top = [{"call": call, "site": site, "per_step": count / steps} for (call, site), count in sites.most_common(5)]
    return {"per_step_mean": sum(per_step) / steps, "per_step_max": max(per_step), "steps": steps,
            "worlds": trainer.stage.worlds, "ended_episodes": ended, "top_sites": top}


def host_syncs(device: str, *, worlds: int | None = None, steps: int = 24) -> dict[str, Any]:
    """Host synchronisations per training env step of the solo, 1v1 and 2v2 stages, on the device's own path and on
    the path without them (the same on a GPU); pass: none on the latter."""
    stages, free = {}, {}
    for name in ("solo", "1v1", "2v2"):
        with tempfile.TemporaryDirectory() as scratch:
            stages[name] = count_syncs(_stage_trainer(name, device, worlds, Path(scratch)), steps)
        with tempfile.TemporaryDirectory() as scratch:
            trainer = _stage_trainer(name, device, worlds, Path(scratch))
            set_sync_free(trainer)
            free[name] = count_syncs(trainer, steps)
    ok = all(s["per_step_max"] == 0 for s in free.values())
    summary = "per env step, sync-free path: " + ", ".join(f"{n} {s['per_step_mean']:.1f}" for n, s in free.items())
    if device.startswith("cpu"):
        summary += "; the CPU's own path: " + ", ".join(f"{n} {s['per_step_mean']:.1f}" for n, s in stages.items())
    return {"status": "pass" if ok else "fail", "summary": summary, "stages": stages, "sync_free": free}


def out_of_memory(exc: BaseException) -> bool:
    """Whether ``exc`` says the device ran out of memory: torch's ``OutOfMemoryError``, or a Warp allocation that
    failed."""
    text = str(exc)
    return isinstance(exc, torch.OutOfMemoryError) or (
        isinstance(exc, RuntimeError) and ("out of memory" in text.lower() or text.startswith("Failed to allocate")))


def _free(device: str) -> None:
    """Give back what a failed size left allocated."""
    gc.collect()
    if wp.get_device(device).is_cuda:
        torch.cuda.empty_cache()


def _rate_row(device: str, worlds: int, iterations: int) -> dict[str, Any]:
    """``spiral bench ppo``'s profile of the solo stage at ``worlds`` worlds, as a row of the rates check."""
    spec, track = load_pipeline(PIPELINE)
    stage = next(s for s in spec.stages if s.name == "solo").model_copy(update={"worlds": worlds})
    setting = RaceSetting(track, resolve_airframe(spec.airframe, source=str(PIPELINE)), spec.sim)
    r = profile_iteration(setting, stage, iterations=iterations, device=device, seed=spec.seed)
    return {"worlds": worlds, "samples_per_iteration": r["samples_per_iteration"],
            "env_steps_per_s": r["samples_per_iteration"] / r["rollout_s"], "rollout_s": r["rollout_s"],
            "rollout_parts_s": r["rollout_parts_s"], "update_s": r["update_s"],
            "update_samples_per_s": r["update_samples_per_s"],
            "update_over_matmul_limit": r["update_over_matmul_limit"]}


def rates(device: str, *, sizes: tuple[int, ...] = RATE_WORLDS, iterations: int = 2) -> dict[str, Any]:
    """Env-step and PPO-update rates of the solo stage at each of ``sizes`` worlds (reported); a size that does not
    fit the device's memory is skipped."""
    rows = []
    for worlds in sizes:
        try:
            rows.append(_rate_row(device, worlds, iterations))
        except RuntimeError as exc:  # torch's OutOfMemoryError is one
            if not out_of_memory(exc):
                raise
            _free(device)
            rows.append({"worlds": worlds, "skipped": f"out of memory: {str(exc).splitlines()[0]}"})
    summary = ", ".join(f"{r['worlds']} worlds: skipped (out of memory)" if "skipped" in r else
                        f"{r['worlds']} worlds: {r['env_steps_per_s']:,.0f} env-steps/s, update "
                        f"{r['update_samples_per_s']:,.0f} samples/s" for r in rows)
    return {"status": "info", "summary": summary, "rows": rows}


def smoke(device: str, pipeline: Path = SMOKE) -> dict[str, Any]:
    """``spiral run pipelines/smoke.yaml`` (or ``pipeline``) on ``device`` into temporary folders, and what it left
    there: every step ran on ``device``, both final policies were published and the report was written."""
    with tempfile.TemporaryDirectory() as tmp:
        runs, ckpt = Path(tmp) / "runs", Path(tmp) / "checkpoints"
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "spiral.cli", "run", str(pipeline), "--device", device,
                               "--runs-dir", str(runs), "--checkpoints-dir", str(ckpt)],
                              capture_output=True, text=True, cwd=ROOT)
        wall = time.perf_counter() - t0
        manifests = {p.parent.name: json.loads(p.read_text()) for p in runs.glob("*/*/manifest.json")}
        devices = {name: m.get("info", {}).get("device") for name, m in manifests.items() if name.startswith("train-")}
        published = [name for name in ("spiral.pt", "ppo-noselfplay.pt") if any(ckpt.glob(f"*/{name}"))]
        report = any(runs.glob("*/report/results.csv"))
    last = (proc.stdout.strip().splitlines() or [""])[-1]
    if proc.returncode:
        sys.stderr.write(proc.stderr[-4000:])
    ok = (proc.returncode == 0 and f"{len(manifests)} step(s) ran, 0 skipped" in last and bool(devices)
          and set(devices.values()) == {device} and len(published) == 2 and report)
    summary = (f"exit {proc.returncode} in {wall:.0f} s: {last or '(no output)'}; training steps on "
               f"{sorted(set(map(str, devices.values())))}; published {published}; "
               f"report {'written' if report else 'MISSING'}")
    return {"status": "pass" if ok else "fail", "summary": summary, "wall_s": wall, "returncode": proc.returncode,
            "steps": len(manifests), "training_devices": devices, "stderr_tail": proc.stderr[-2000:]}


def run_check(name: str, fn: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    """Run one check and print its line; an exception fails the check (its traceback on stderr), not the run."""
    t0 = time.perf_counter()
    try:
        result = fn()
    except Exception as exc:  # a check that cannot run is a failed check; the others still run
        traceback.print_exc()
        result = {"status": "fail", "summary": f"{type(exc).__name__}: {exc}".splitlines()[0]}
    result = {"check": name, **result, "seconds": time.perf_counter() - t0}
    label = {"pass": "PASS", "fail": "FAIL", "info": "INFO"}[result["status"]]
    print(f"{label} {name} ({result['seconds']:.0f} s): {result['summary']}", flush=True)
    return result


def checks(device: str, quick: bool) -> dict[str, Callable[[], dict[str, Any]]]:
    """Each check's call on ``device`` at its sizes (``quick``: tiny)."""
    size = QUICK if quick else FULL
    return {
        "agreement": lambda: agreement(device),
        "graph": lambda: graph(device, worlds=size["graph_worlds"]),
        "host_syncs": lambda: host_syncs(device, worlds=size["sync_worlds"], steps=size["sync_steps"]),
        "rates": lambda: rates(device, sizes=size["rate_worlds"], iterations=1 if quick else 2),
        "smoke": lambda: smoke(device),
    }


def environment(device: str) -> dict[str, Any]:
    """The machine, the libraries and, on a GPU, the GPU."""
    info = {**machine_info(), "torch": torch.__version__, "torch_cuda": torch.version.cuda,
            "platform": platform.platform(), "device": device}
    if wp.get_device(device).is_cuda:
        info.update(gpu=torch.cuda.get_device_name(torch.device(device)), warp_device=wp.get_device(device).name,
                    gpu_memory_gb=torch.cuda.get_device_properties(torch.device(device)).total_memory / 2**30)
    return info


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda:0", help="cpu or cuda:N (default cuda:0)")
    parser.add_argument("--json", type=Path, help="also write the results as JSON to this file")
    parser.add_argument("--quick", action="store_true", help="tiny sizes (a minute on a CPU)")
    parser.add_argument("--only", action="append", choices=CHECKS, help="run only this check (repeatable)")
    parser.add_argument("--write-reference", action="store_true", help="write the agreement check's CPU reference")
    args = parser.parse_args(argv)
    if args.write_reference:
        print(json.dumps(write_reference(), indent=2))
        return 0
    try:
        device = check_device(args.device)
    except ValueError as exc:
        print(f"Error: {exc}", file=sys.stderr)
        return 1
    todo = checks(device, args.quick)
    results = [run_check(name, todo[name]) for name in (args.only or CHECKS)]
    failed = [r["check"] for r in results if r["status"] == "fail"]
    print(f"{len(results) - len(failed)} of {len(results)} checks passed or reported; failed: "
          f"{', '.join(failed) or 'none'}")
    if args.json:
        args.json.write_text(json.dumps({"environment": environment(device), "quick": args.quick,
                                         "checks": results}, indent=2, default=str) + "\n")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
