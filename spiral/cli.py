"""The ``spiral`` command line: parse arguments, load specs, delegate. Nothing else."""

from __future__ import annotations

import contextlib
import functools
import json
import os
import sys
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, TypeVar

import typer
from pydantic import ValidationError

from spiral import __version__
from spiral.config import KINDS, PipelineSpec, SpecError, load_pipeline, load_spec, load_track
from spiral.config.errors import format_validation_error
from spiral.config.pipeline import RacingCfg
from spiral.core.device import check_device
from spiral.core.errors import UsageError
from spiral.core.numerics import cpu_target

if TYPE_CHECKING:
    from spiral.config import SeparationCfg, StageSpec
    from spiral.eval.evaluate import FlightOverride
    from spiral.eval.report import ReportOptions
    from spiral.train.runner import StageStart

__all__ = ["app", "main"]

app = typer.Typer(no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False,
                  help="spiral: self-play training of autonomous racing drones.")
track_app = typer.Typer(no_args_is_help=True, help="Inspect race tracks.")
bench_app = typer.Typer(no_args_is_help=True, help="Throughput benchmarks.")
app.add_typer(track_app, name="track")
app.add_typer(bench_app, name="bench")

F = TypeVar("F", bound=Callable[..., Any])

Device = Annotated[str | None, typer.Option("--device", help="cpu or cuda:N (default: the pipeline's)")]
Laps = Annotated[int | None, typer.Option("--laps", min=1, help="Laps of each race (default: the track's; its time "
                                          "limit scaled to them)")]
PLANNER_RUNS = RacingCfg.model_fields["planner_runs"].default
"""The racing section's default placements of SPIRAL's duels against SE-IBR."""
DeviceOpt = Annotated[str, typer.Option("--device", help="cpu or cuda:N")]
"""A command's device; its body checks it first (``check_device``), so a missing GPU is one ``Error:`` line."""
JsonOut = Annotated[Path | None, typer.Option("--json", help="Also write the numbers as JSON to this file")]
RunsDir = Annotated[Path, typer.Option("--runs-dir", help="Folder of run outputs")]
CkptDir = Annotated[Path, typer.Option("--checkpoints-dir", help="Folder of published policies")]
Overrides = Annotated[list[str] | None, typer.Option(
    "--set", metavar="PATH=VALUE", help="Set a field of the pipeline (value as YAML; a stage by its name, e.g. "
    "stages.1v1.iterations=600; repeatable); the run gets folders of its own, named for the settings")]
Executor = Annotated[str, typer.Option("--executor", help="Where steps run: local (this machine) or ray (Ray tasks "
                                      "on a cluster sharing this working directory; pip install 'spiral[ray]')")]
Address = Annotated[str | None, typer.Option("--address", help="The Ray cluster (--executor ray): auto, host:port or "
                                             "ray://host:port; default RAY_ADDRESS or a new local Ray instance")]
Threads = Annotated[int, typer.Option("--threads", min=1, help="Torch threads of each step (on the CPU they "
                                      "decide its numbers to the bit, so every executor uses this count)")]
SimThreads = Annotated[int, typer.Option("--sim-threads", min=1, help="CPU threads stepping the simulator, each a "
                                         "share of the worlds (a Warp CPU launch uses one core); same results")]


@app.callback()
def _options(debug: Annotated[bool, typer.Option(
        "--debug", help="Show the traceback of every error, also of those printed as one Error: line")] = False,
) -> None:
    """spiral: self-play training of autonomous racing drones."""
    if debug:
        os.environ[DEBUG_ENV] = "1"


def _expected_errors() -> tuple[type[Exception], ...]:
    """Errors a user can fix: a spec, an option, a path, a checkpoint, a pipeline's state. Anything else is a bug."""
    from spiral.core.checkpoint import CheckpointError
    from spiral.pipeline import PipelineError, PipelineLockedError

    return (SpecError, ValidationError, UsageError, PipelineError, PipelineLockedError, CheckpointError,
            FileNotFoundError)


DEBUG_ENV = "SPIRAL_DEBUG"
"""Set to 1 (``spiral --debug`` sets it for the command and the processes it starts): every error keeps its
traceback."""


def _debugging() -> bool:
    return os.environ.get(DEBUG_ENV, "") not in ("", "0")


def handles_errors(fn: F) -> F:
    """Print the errors a user can fix as ``Error: ...`` lines on stderr and exit 1, without a traceback (with
    ``--debug``: with it); any other exception is a bug and keeps its traceback."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except _expected_errors() as exc:
            if _debugging():
                raise
            if isinstance(exc, SpecError):
                lines = exc.problems
            elif isinstance(exc, ValidationError):  # a setting built from options: its model and field, one a line
                lines = format_validation_error(exc.title, exc)
            else:
                lines = str(exc).splitlines()
            for line in lines:
                typer.echo(f"Error: {line}", err=True)
            raise typer.Exit(1) from None

    return wrapper  # type: ignore[return-value]


def _write_json(path: Path | None, data: Any) -> None:
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(data, indent=2, default=str) + "\n")


@app.command()
def validate(paths: Annotated[list[Path], typer.Argument(help="Track or pipeline YAML files")]) -> None:
    """Check spec files; exit 1 with one `Error:` line per problem."""
    failed = False
    for path in paths:
        try:
            spec = load_pipeline(path)[0] if _kind_of(path) == "pipeline" else load_spec(path)
            typer.echo(f"OK {path} ({spec.kind})")  # type: ignore[attr-defined]
        except SpecError as exc:
            failed = True
            for line in exc.problems:
                typer.echo(f"Error: {line}", err=True)
    raise typer.Exit(1 if failed else 0)


def _kind_of(path: Path) -> str | None:
    import yaml

    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        return None
    return data.get("kind") if isinstance(data, dict) else None


@app.command()
@handles_errors
def schema(out: Annotated[Path, typer.Option("--out", help="Folder for <kind>.schema.json files")]) -> None:
    """Write the JSON Schema of each spec kind (for editor completion)."""
    out.mkdir(parents=True, exist_ok=True)
    for kind, model in KINDS.items():
        (out / f"{kind}.schema.json").write_text(json.dumps(model.model_json_schema(), indent=2) + "\n")
        typer.echo(f"wrote {out / f'{kind}.schema.json'}")


@track_app.command("show")
@handles_errors
def track_show(track: Path, out: Annotated[Path, typer.Option("--out", help="PNG file")] = Path("track.png")) -> None:
    """Draw a track in top and side view: gates, passing directions, centreline, start box, bounds."""
    from spiral.eval.plots import plot_track

    typer.echo(f"wrote {plot_track(load_track(track), out)}")


@track_app.command("info")
@handles_errors
def track_info(track: Path, json_out: JsonOut = None) -> None:
    """Print a track's gate count, centreline length, bounds and gates."""
    info = load_track(track).summary()
    typer.echo(f"{info['name']}: {info['gate_count']} gates, centreline {info['centreline_length_m']:.2f} m, "
               f"bounds {info['bounds']['min']} .. {info['bounds']['max']}")
    for g in info["gates"]:
        typer.echo(f"  gate {g['index']}: at {g['position']}, rpy {g['rpy_deg']} deg, passing {g['forward']}")
    _write_json(json_out, info)


@track_app.command("generate")
@handles_errors
def track_generate(
    seed: Annotated[int, typer.Option("--seed", help="Seed of the generator's random stream")],
    out: Annotated[Path, typer.Option("--out", help="Track YAML to write")],
    gates: Annotated[int, typer.Option("--gates", min=3, max=16, help="Gates in the circuit")] = 6,
    airframe: Annotated[str, typer.Option("--airframe", help="Built-in airframe of the reference lap")] = "cf2x",
    name: Annotated[str | None, typer.Option("--name", help="Track name (default: gen-s<seed>-g<gates>)")] = None,
) -> None:
    """Write a seeded circuit of N gates in the shipped tracks' ranges that the point-mass reference laps within the
    time limit (docs/tracks.md, "Generated tracks")."""
    from spiral.config import resolve_airframe
    from spiral.config.generate import TrackGenCfg, track_yaml
    from spiral.eval.bound import generate_flyable_track

    track, reference = generate_flyable_track(TrackGenCfg(gates=gates), seed, resolve_airframe(airframe), name=name)
    header = f"generated by `spiral track generate --seed {seed} --gates {gates}` (spiral {__version__})"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(track_yaml(track, header))
    info = load_track(out).summary()
    typer.echo(f"wrote {out}: {info['gate_count']} gates, centreline {info['centreline_length_m']:.2f} m, "
               f"point-mass lap {reference:.2f} s ({airframe})")


@app.command()
@handles_errors
def run(
    pipeline: Path,
    from_step: Annotated[str | None, typer.Option("--from", help="Start at this step")] = None,
    only: Annotated[str | None, typer.Option("--only", help="Run only this step")] = None,
    force: Annotated[list[str] | None, typer.Option("--force", help="Rerun this step from scratch")] = None,
    device: Device = None,
    runs_dir: RunsDir = Path("runs"),
    checkpoints_dir: CkptDir = Path("checkpoints"),
    jobs: Annotated[int, typer.Option("--jobs", "-j", min=1, help="Independent steps run side by side, each in its "
                                      "own process")] = 1,
    threads: Threads = 1,
    accept_code_changes: Annotated[bool, typer.Option(
        "--accept-code-changes", help="Keep steps that ran with other spiral source code (same spec and inputs) "
        "instead of rerunning them")] = False,
    overrides: Overrides = None,
    executor: Executor = "local",
    address: Address = None,
) -> None:
    """Run a pipeline's steps in order; complete steps are skipped, interrupted training resumes."""
    from spiral.pipeline import PipelineRunner

    runner = PipelineRunner(pipeline, runs_dir=runs_dir, checkpoints_dir=checkpoints_dir, device=device,
                            accept_code_changes=accept_code_changes, overrides=overrides or ())
    with _launcher(executor, address, runner.plan.spec.device) as launcher:
        ran = runner.run(start=from_step, only=only, force=force, jobs=jobs, threads=threads, launcher=launcher)
    typer.echo(f"pipeline '{runner.plan.spec.name}': {len(ran)} step(s) ran, {len(runner.steps) - len(ran)} skipped")


@app.command()
@handles_errors
def sweep(
    pipeline: Path,
    seeds: Annotated[str, typer.Option("--seeds", help="Comma-separated pipeline seeds, one run each (e.g. 0,1)")],
    device: Device = None,
    runs_dir: RunsDir = Path("runs"),
    checkpoints_dir: CkptDir = Path("checkpoints"),
    jobs: Annotated[int, typer.Option("--jobs", "-j", min=1, help="Steps of a run side by side (as spiral run)")] = 1,
    threads: Threads = 1,
    overrides: Overrides = None,
    executor: Executor = "local",
    address: Address = None,
) -> None:
    """Run a pipeline once per seed with the same --set settings, each in its own run folder, and table their
    headline figures with the spread across seeds (runs/sweeps/<variant>/summary.md). Under --executor ray the
    draws run at the same time."""
    from spiral.core.device import canonical_device
    from spiral.pipeline.sweep import parse_seeds, run_sweep

    seed_list = parse_seeds(seeds)
    run_device = "cpu"  # only Ray's launcher asks for GPUs
    if executor == "ray":
        run_device = canonical_device(device) if device else load_pipeline(pipeline, overrides or ())[0].device
    with _launcher(executor, address, run_device) as launcher:
        summary = run_sweep(pipeline, seed_list, overrides or (), runs_dir=runs_dir, checkpoints_dir=checkpoints_dir,
                            device=device, jobs=jobs, threads=threads, launcher=launcher)
    typer.echo(f"wrote {summary}")


@contextlib.contextmanager
def _launcher(executor: str, address: str | None, device: str) -> Iterator[Any]:
    """The workers' launcher of ``--executor`` (None: the local default), closed after the run."""
    if executor not in ("local", "ray"):
        raise UsageError(f"--executor {executor!r}: expected local or ray")
    if executor == "local":
        if address is not None:
            raise UsageError("--address names a Ray cluster: give it with --executor ray")
        yield None
        return
    from spiral.pipeline.ray_executor import RayLauncher

    with RayLauncher(address, device=device) as launcher:
        yield launcher


@app.command()
@handles_errors
def status(pipeline: Path, json_out: JsonOut = None, runs_dir: RunsDir = Path("runs"),
           checkpoints_dir: CkptDir = Path("checkpoints"),
           accept_code_changes: Annotated[bool, typer.Option(
               "--accept-code-changes", help="Count steps that ran with other spiral source code as complete")] = False,
           overrides: Overrides = None, device: Device = None) -> None:
    """Show each step as complete, stale (why), partial (last checkpoint) or missing (as for a run on --device)."""
    from spiral.pipeline import PipelineRunner

    runner = PipelineRunner(pipeline, runs_dir=runs_dir, checkpoints_dir=checkpoints_dir, device=device,
                            accept_code_changes=accept_code_changes, overrides=overrides or ())
    steps = runner.status()
    width = max((len(s.name) for s in steps), default=0)
    for s in steps:
        extra = "; ".join(x for x in (s.reason, s.detail) if x)
        typer.echo(f"{s.name:<{width}}  {s.status}{f' ({extra})' if extra else ''}")
    _write_json(json_out, runner.describe())


@app.command()
@handles_errors
def train(
    pipeline: Path,
    stage: Annotated[str, typer.Option("--stage", help="Stage name in the pipeline")],
    device: Device = None,
    runs_dir: RunsDir = Path("runs"),
    checkpoints_dir: CkptDir = Path("checkpoints"),
    distributed: Annotated[bool, typer.Option("--distributed", help="One process per GPU under torchrun "
                                              "(docs/scaling.md)")] = False,
    threads: Threads = 1,
    sim_threads: SimThreads = 1,
    overrides: Overrides = None,
) -> None:
    """Train one stage of a pipeline (its inputs must be complete); resumes from its newest checkpoint."""
    from spiral.pipeline import PipelineRunner

    if distributed:
        from spiral.pipeline.distributed import train_stage_distributed

        if sim_threads > 1:
            raise UsageError("--sim-threads: a distributed stage steps each process's worlds on one thread")

        train_stage_distributed(pipeline, stage, runs_dir=runs_dir, checkpoints_dir=checkpoints_dir, device=device,
                                overrides=overrides or ())
        return
    runner = PipelineRunner(pipeline, runs_dir=runs_dir, checkpoints_dir=checkpoints_dir, device=device,
                            overrides=overrides or ())
    runner.plan.sim_threads = sim_threads
    runner.run(only=f"train:{stage}", threads=threads)


def _parse_method(text: str) -> tuple[str, str]:
    """``NAME=CHECKPOINT`` as a method's (name, checkpoint); a bare checkpoint (or ``se-ibr``) names itself."""
    name, sep, checkpoint = text.partition("=")
    if not sep:
        return text, text
    return name, checkpoint


@app.command("eval")
@handles_errors
def evaluate(
    track: Annotated[Path, typer.Option("--track", help="Track YAML")],
    method: Annotated[list[str], typer.Option("--method", help="NAME=CHECKPOINT or se-ibr (repeatable)")],
    scenario: Annotated[str, typer.Option("--scenario", help="solo, 1v1 or 2v2")] = "solo",
    against: Annotated[str | None, typer.Option("--against", help="NAME=CHECKPOINT or se-ibr: opponent team")] = None,
    runs: Annotated[int, typer.Option("--runs", min=1, help="Races (start placements with --against)")] = 50,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the start placements")] = 0,
    sides: Annotated[str, typer.Option(
        "--sides", help="With --against: 'both' races every placement twice, sides swapped; 'a': method on team A "
        "only")] = "both",
    separation: Annotated[str, typer.Option(
        "--separation", help="Flight stack of every drone: 'keep' (as trained), 'none' (no separation filter) or "
        "DISTANCE,HORIZON_S,GAIN (a filter)")] = "keep",
    separation_team: Annotated[str, typer.Option(
        "--separation-team", help="Drones the filter acts on: 'all', 'a' (the --method's drones only, team A; with "
        "--against they keep it when the sides are swapped) or 'b' (team B's only)")] = "all",
    downwash: Annotated[bool | None, typer.Option(
        "--downwash/--no-downwash", help="Switch the simulator's downwash on or off (default: as trained)")] = None,
    starts: Annotated[str, typer.Option(
        "--starts", help="Where the races start: 'box' (the start box, the protocol), 'track' (every drone at its "
        "own random point along the track) or 'file' (each world's drones in single file on one stretch)")] = "box",
    laps: Laps = None,
    device: DeviceOpt = "cpu",
    json_out: JsonOut = None,
) -> None:
    """Race methods from seeded start placements (identical for every method) and report their metrics."""
    device = check_device(device)
    from spiral.core.scenario import SCENARIO_DRONES
    from spiral.eval.evaluate import RaceSet, evaluate_methods, format_eval

    _check_choice("--scenario", scenario, tuple(SCENARIO_DRONES))
    flight = _flight_override(separation, separation_team, downwash, starts)
    spec = load_track(track)
    result = evaluate_methods(RaceSet(spec.with_laps(laps or spec.laps), scenario, runs, seed),
                              dict(_parse_method(m) for m in method), device=device,
                              against=_parse_method(against) if against else None, sides=sides, flight=flight)
    typer.echo(format_eval(result))
    _write_json(json_out, result)


def _check_choice(option: str, value: str, choices: tuple[str, ...]) -> None:
    """Raise a ``UsageError`` naming ``option`` unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise UsageError(f"{option}: expected {', '.join(choices[:-1])} or {choices[-1]}, got {value!r}")


def _flight_override(separation: str, separation_team: str, downwash: bool | None, starts: str) -> FlightOverride:
    """``spiral eval``'s changes to the flight stack and the starts, from its options."""
    from spiral.eval.evaluate import FlightOverride, parse_separation

    _check_choice("--separation-team", separation_team, ("all", "a", "b"))
    _check_choice("--starts", starts, ("box", "track", "file"))
    return FlightOverride(separation=parse_separation(separation), downwash=downwash,
                          separation_team=separation_team, starts=starts)  # type: ignore[arg-type]


@bench_app.command("sim")
@handles_errors
def bench_sim(
    worlds: Annotated[str | None, typer.Option("--worlds", help="Comma-separated world counts (default: "
                                               "1,64,1024,4096,16384; on a GPU up to 65536)")] = None,
    device: DeviceOpt = "cpu",
    steps: Annotated[int, typer.Option("--steps", min=1, help="Timed control steps per row")] = 100,
    two_process: Annotated[bool | None, typer.Option("--two-process/--no-two-process", help="CPU: also run 4096x4 "
                                                     "in two processes (default: on a CPU)")] = None,
    builds: Annotated[bool | None, typer.Option("--builds/--no-builds", help="CPU: also time 4096x4 with each CPU "
                                                "build (SPIRAL_CPU_TARGET portable and native), each in fresh "
                                                "processes (default: on a CPU)")] = None,
    threads: Annotated[int | None, typer.Option("--threads", min=1, help="CPU: also run 4096x4 in one process with "
                                                "the worlds stepped on this many threads (1: not; default: 2 on a "
                                                "CPU)")] = None,
    json_out: JsonOut = None,
) -> None:
    """Simulator throughput (pid mode, gates and collisions on) against the numpy reference."""
    device = check_device(device)
    from spiral.sim.bench import BenchExtras, default_world_counts, format_bench_table, run_sim_bench

    extras = BenchExtras.for_device(device, two_process=two_process, builds=builds, threads=threads)
    counts = [int(w) for w in worlds.split(",") if w.strip()] if worlds else list(default_world_counts(device))
    result = run_sim_bench(counts, device=device, steps=steps, extras=extras)
    typer.echo(format_bench_table(result))
    _write_json(json_out, result)


@bench_app.command("kernels")
@handles_errors
def bench_kernels(
    worlds: Annotated[int, typer.Option("--worlds", min=1, help="Worlds")] = 4096,
    drones: Annotated[int, typer.Option("--drones", min=1, help="Drones per world")] = 4,
    device: DeviceOpt = "cpu",
    launches: Annotated[int, typer.Option("--launches", min=1, help="Launches per timed repeat")] = 30,
    repeats: Annotated[int, typer.Option("--repeats", min=1, help="Timed repeats (the best is kept)")] = 9,
    json_out: JsonOut = None,
) -> None:
    """Where a simulator control step's time goes: each kernel timed alone, beside the whole step."""
    device = check_device(device)
    from spiral.sim.bench import format_kernel_table, kernel_profile

    result = kernel_profile(worlds, drones, device=device, launches=launches, repeats=repeats)
    typer.echo(format_kernel_table(result))
    _write_json(json_out, result)


@bench_app.command("repro")
@handles_errors
def bench_repro(
    training: Annotated[bool, typer.Option("--training/--no-training", help="Also train a few PPO iterations")] = True,
    json_out: JsonOut = None,
) -> None:
    """Digests of a fixed simulator rollout and a few PPO iterations: equal digests on two machines, equal bits."""
    from spiral.train.reproducibility import run_digests

    result = run_digests(training=training)
    n, m = result["numerics"], result["machine"]
    typer.echo(f"{m['cpu']} · SPIRAL_CPU_TARGET={n['cpu_target']} (portable simulator: {n['portable_sim']}) · torch "
               f"{n['torch']} {n['torch_cpu_capability']}")
    for key in ("sim", "training"):
        if key in result:
            typer.echo(f"{key:<8} {result[key]}")
    _write_json(json_out, result)


@app.command("export")
@handles_errors
def export(
    checkpoint: Annotated[Path, typer.Argument(help="Checkpoint (.pt) to export")],
    fmt: Annotated[str, typer.Option("--format", help="onnx or torchscript")],
    out: Annotated[Path, typer.Option("--out", help="Output file")],
) -> None:
    """Export a policy (observation normaliser included) for deployment: obs (B, obs_dim) -> actions (B, 4)."""
    from spiral.train.export import export_policy

    typer.echo(f"wrote {export_policy(checkpoint, out, fmt=fmt)}")  # type: ignore[arg-type]


@track_app.command("bound")
@handles_errors
def track_bound(
    track: Path,
    airframe: Annotated[str, typer.Option("--airframe", help="Built-in airframe name")] = "cf2x",
    model: Annotated[str, typer.Option("--model", help="thrust (thrust ball and tilt cone) or ball")] = "thrust",
    steps: Annotated[int, typer.Option("--steps", min=2, help="Mean time steps per gate-to-gate segment")] = 24,
    json_out: JsonOut = None,
) -> None:
    """Minimum-time lap of a point mass with the airframe's acceleration limits: the lap-time reference."""
    from spiral.config import resolve_airframe
    from spiral.eval.bound import format_bound, lap_time_bound

    _check_choice("--model", model, ("thrust", "ball"))
    result = lap_time_bound(load_track(track), resolve_airframe(airframe), model=model, steps_per_segment=steps)
    typer.echo(format_bound(result))
    _write_json(json_out, result.to_json(trajectory=True))


@app.command()
@handles_errors
def report(
    run_dir: Annotated[Path, typer.Argument(help="A pipeline's run folder, runs/<pipeline>")],
    out: Annotated[Path | None, typer.Option("--out", help="Report folder [default: RUN_DIR/report]")] = None,
    track: Annotated[Path | None, typer.Option("--track", help="Track YAML [default: the run's]")] = None,
    se_ibr: Annotated[bool, typer.Option("--se-ibr", help="Run SE-IBR where no evaluation exists (slow)")] = False,
    runs: Annotated[int | None, typer.Option("--runs", min=1, help="Races [default: the pipeline's]")] = None,
    holdout_runs: Annotated[int, typer.Option(
        "--holdout-runs", min=0, help="Race the learned policies again from this many other placements (0: no)")] = 0,
    holdout_seed: Annotated[int, typer.Option("--holdout-seed", min=0, help="Seed of those placements")] = 1,
    sides: Annotated[str, typer.Option(
        "--sides", help="Head to head: 'both' races every placement twice, sides swapped; 'a': row method on team A "
        "only")] = "both",
    separation: Annotated[str, typer.Option(
        "--separation", help="Also race the learned methods with this separation filter, DISTANCE,HORIZON_S,GAIN, as "
        "extra table rows ('none': no such rows)")] = "none",
    robustness: Annotated[bool, typer.Option(
        "--robustness/--no-robustness", help="Final policies in every scenario, racing strangers, downwash")] = True,
    racing_laps: Annotated[int, typer.Option(
        "--racing-laps", min=0, help="Add a racing section of races of this many laps from the held-out placements, "
        "from the start box and track starts (needs --holdout-runs; 0: none)")] = 0,
    planner_runs: Annotated[int, typer.Option(
        "--planner-runs", min=0,
        help="Placements of the racing section's 1v1 duels against SE-IBR (with --se-ibr)")] = PLANNER_RUNS,
    jobs: Annotated[int, typer.Option("--jobs", "-j", min=1, help="Processes racing SE-IBR's head-to-head "
                                      "pairings side by side (with --se-ibr)")] = 1,
    device: DeviceOpt = "cpu",
) -> None:
    """Write results.md (the paper's tables, cross-play, lap-time reference), results.csv and figures."""
    device, filter_row = check_device(device), _filter_row(separation)
    from spiral.eval.report import ReportOptions, build_report
    from spiral.pipeline.report_steps import read_run

    racing = RacingCfg(laps=racing_laps, planner_runs=planner_runs) if racing_laps else None
    options = ReportOptions(runs=runs, device=device, se_ibr=se_ibr, sides=sides,
                            holdout=(holdout_runs, holdout_seed) if holdout_runs else None,
                            separation=filter_row, robustness=robustness, racing=racing, jobs=jobs)
    options = replace(options, command=_report_command(run_dir, options, separation))
    run = read_run(run_dir)  # what the run's steps declared in their manifests
    spec = load_track(track) if track is not None else run.track
    typer.echo(f"wrote {build_report(run, spec, out or run_dir / 'report', options)}")


def _filter_row(separation: str) -> SeparationCfg | None:
    """``spiral report --separation``: the filter of the extra table rows, or None (``none``)."""
    from spiral.eval.evaluate import KEEP, parse_separation

    filter_row = parse_separation(separation)
    if filter_row == KEEP:
        raise UsageError("--separation: expected none or DISTANCE,HORIZON_S,GAIN")
    return filter_row  # type: ignore[return-value]


def _report_command(run_dir: Path, o: ReportOptions, separation: str) -> str:
    """The ``spiral report`` command line that asks for ``o`` (``separation`` as given), quoted in results.md."""
    command = f"spiral report {run_dir}" + (" --se-ibr" if o.se_ibr else "") + (f" --runs {o.runs}" if o.runs else "")
    if o.holdout is not None:
        command += f" --holdout-runs {o.holdout[0]} --holdout-seed {o.holdout[1]}"
    if o.sides != "both":
        command += f" --sides {o.sides}"
    if o.separation is not None:
        command += f" --separation {separation}"
    if not o.robustness:
        command += " --no-robustness"
    if o.racing is not None:
        planner_runs = o.racing.planner_runs
        command += f" --racing-laps {o.racing.laps}" + (
            f" --planner-runs {planner_runs}" if planner_runs != PLANNER_RUNS else "")
    return command


@app.command()
@handles_errors
def race(
    track: Annotated[Path, typer.Option("--track", help="Track YAML")],
    method: Annotated[str, typer.Option("--method", help="NAME=CHECKPOINT or se-ibr: every drone, or team A")],
    against: Annotated[str | None, typer.Option("--against", help="NAME=CHECKPOINT or se-ibr: team B")] = None,
    scenario: Annotated[str, typer.Option("--scenario", help="solo, 1v1 or 2v2")] = "solo",
    seed: Annotated[int, typer.Option("--seed", help="Seed of the start placement")] = 0,
    out: Annotated[Path, typer.Option("--out", help="race.gif or race.mp4")] = Path("race.gif"),
    fps: Annotated[float, typer.Option("--fps", min=1, help="Frames per second of race time")] = 15.0,
    laps: Laps = None,
    device: DeviceOpt = "cpu",
) -> None:
    """Render one race: top and side views, gates, trails by team, time and lap counters, crash marks."""
    device = check_device(device)
    from spiral.eval.replay import record_race, render_race

    opponent = _parse_method(against) if against else None
    spec = load_track(track)
    rec = record_race(spec.with_laps(laps or spec.laps), scenario, _parse_method(method), opponent, seed=seed,
                      device=device)
    frames = render_race(rec, out, fps=fps)
    typer.echo(f"wrote {out}: {frames} frames, {rec.duration:.2f} s of racing")
    for line in rec.outcomes():
        typer.echo(line)


@bench_app.command("train")
@handles_errors
def bench_train(
    track: Annotated[Path, typer.Option("--track", help="Track YAML")] = Path("tracks/circuit6.yaml"),
    worlds: Annotated[int, typer.Option("--worlds", min=1, help="Parallel worlds")] = 1024,
    iterations: Annotated[int, typer.Option("--iterations", min=1, help="Timed PPO iterations")] = 10,
    device: DeviceOpt = "cpu",
    sim_threads: SimThreads = 1,
    json_out: JsonOut = None,
) -> None:
    """End-to-end PPO throughput for the compact and the paper's observation layout."""
    device = check_device(device)
    from spiral.config import AIRFRAMES, SimCfg
    from spiral.env.setting import RaceSetting
    from spiral.train.bench import run_train_bench

    setting = RaceSetting(load_track(track), AIRFRAMES["cf2x"], SimCfg(), sim_threads=sim_threads)
    result = run_train_bench(setting, worlds=worlds, iterations=iterations,
                             device=device)
    for r in result["results"]:
        typer.echo(f"{r['layout']:<8} {r['obs_dim']:>4} inputs: {r['env_steps_per_s']:>8.0f} env-steps/s, "
                   f"update {100 * r['update_share']:.0f}% of the iteration")
    _write_json(json_out, result)


@bench_app.command("ppo")
@handles_errors
def bench_ppo(
    pipeline: Annotated[Path, typer.Argument(help="Pipeline YAML")] = Path("pipelines/full.yaml"),
    stage: Annotated[str, typer.Option("--stage", help="Stage name in the pipeline")] = "solo",
    worlds: Annotated[int | None, typer.Option("--worlds", min=1, help="Worlds (default: the stage's)")] = None,
    iterations: Annotated[int, typer.Option("--iterations", min=1, help="Profiled PPO iterations")] = 3,
    device: DeviceOpt = "cpu",
    sim_threads: SimThreads = 1,
    checkpoints_dir: CkptDir = Path("checkpoints"),
    init: Annotated[Path | None, typer.Option("--init", help="Multi-drone stage: the checkpoint it starts from "
                                              "(default: the published best of the stage it starts from)")] = None,
    pool: Annotated[Path | None, typer.Option("--pool", help="Self-play stage: the pool it races, copied (default: "
                                              "the published pool, if any)")] = None,
    json_out: JsonOut = None,
) -> None:
    """Profile PPO iterations of one stage: the rollout by env hook, the update by part, against the matmul limit.

    A multi-drone stage races what it races in the pipeline, from the published checkpoints: its init stage's best,
    the pool (self-play) or the frozen opponent's best (no self-play)."""
    device = check_device(device)
    from spiral.config.load import load_pipeline
    from spiral.env.setting import RaceSetting
    from spiral.pipeline.graph import PipelinePlan
    from spiral.train.profile import profile_iteration

    spec, track = load_pipeline(pipeline)
    plan = PipelinePlan(spec, track, pipeline, Path("runs"), checkpoints_dir)
    index = _stage_index(spec, pipeline, stage)
    spec_stage = spec.stages[index] if worlds is None else spec.stages[index].model_copy(update={"worlds": worlds})
    init = init or plan.init_file(spec.stages[index])
    inputs = None if spec_stage.scenario == "solo" else _published_inputs(spec, index, plan.publish_root, init, pool)
    with tempfile.TemporaryDirectory() as scratch:
        start = None if inputs is None else _stage_start(spec_stage, *inputs, Path(scratch), device=device,
                                                         seed=spec.seed)
        setting = RaceSetting(track, plan.airframe, spec.sim, sim_threads)
        r = profile_iteration(setting, spec_stage, iterations=iterations, device=device, seed=spec.seed, start=start)
    typer.echo(_profile_text(r))
    _write_json(json_out, r)


def _stage_index(spec: PipelineSpec, pipeline: Path, name: str) -> int:
    """Where stage ``name`` is in ``pipeline``'s stages."""
    names = [s.name for s in spec.stages]
    if name not in names:
        raise UsageError(f"--stage: {pipeline} has no stage named {name!r} (stages: {', '.join(names)})")
    return names.index(name)


def _stage_start(stage: StageSpec, init: Path, pool: Path | None, frozen: Path | None, scratch: Path, *,
                 device: str, seed: int) -> StageStart:
    """What multi-drone ``stage`` starts from and races, from :func:`_published_inputs`'s checkpoints and pool (the
    pool copied into ``scratch``)."""
    from spiral.selfplay.curriculum import published_opponents
    from spiral.train.runner import StageStart

    opponents = published_opponents(stage, init, scratch, pool_dir=pool, opponent_checkpoint=frozen, device=device,
                                    seed=seed)
    return StageStart(init, opponents.worlds)


def _profile_text(r: dict[str, Any]) -> str:
    """``spiral bench ppo``'s summary of a :func:`~spiral.train.profile.profile_iteration` result."""
    rollout = ", ".join(f"{k} {1e3 * v:.0f}" for k, v in r["rollout_parts_s"].items())
    parts = ", ".join(f"{k} {100 * v:.0f}%" for k, v in r["update_parts_share"].items())
    return (f"{r['samples_per_iteration']} samples per iteration ({r['worlds']} worlds, {r['learner_drones']} "
            f"learner drones, {r['obs_dim']} inputs, {r['torch_threads']} torch threads)\n"
            f"rollout {r['rollout_s']:.3f} s: {rollout} [ms]\n"
            f"update {r['update_s']:.3f} s ({r['update_cpu_s']:.3f} CPU-s): {parts}\n"
            f"update {r['update_samples_per_s']:.0f} samples/s; matmul limit {r['matmul_limit_samples_per_s']:.0f}"
            f" samples/s at {r['matmul_gflops']:.1f} GFLOP/s ({r['matmul_dtype'].removeprefix('torch.')});"
            f" update / limit {r['update_over_matmul_limit']:.2f}"
            f" (CPU time {r['update_over_matmul_limit_cpu']:.2f})")


def _published_inputs(spec: PipelineSpec, index: int, published: Path, init: Path | None,
                      pool: Path | None) -> tuple[Path, Path | None, Path | None]:
    """What multi-drone stage ``index`` starts from and races, from the policies published under ``published``:
    ``init`` (default: the best of the stage it starts from), in pool mode ``pool`` (default: the published pool, if
    any), in frozen mode the best of the stage its opponent comes from."""
    stage, frozen = spec.stages[index], None
    init = init or published / str(spec.init_stage(index)) / "best.pt"
    if stage.selfplay.mode == "pool":
        pool = pool or (published / "pool" if (published / "pool").is_dir() else None)
    elif stage.selfplay.opponent_from:
        frozen = published / stage.selfplay.opponent_from / "best.pt"
    for option, path in (("--init", init), ("--pool", pool), ("the frozen opponent", frozen)):
        if path is not None and not path.exists():
            raise UsageError(f"{option}: {path} does not exist (train the pipeline, or pass another)")
    return init, pool, frozen


def main() -> None:
    """Console-script entry point."""
    try:
        cpu_target()  # SPIRAL_CPU_TARGET, checked before anything is built with it
    except ValueError as exc:
        typer.echo(f"Error: {exc}", err=True)
        raise SystemExit(1) from None
    app()


if __name__ == "__main__":
    sys.exit(main())
