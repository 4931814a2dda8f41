"""A pipeline's run as the report reads it: its stages, and their evaluations found among the files its steps declared
or run and cached.

The report reads only what the run's steps declared in their manifests (``runs/<pipeline>/<step>/manifest.json``):
each ``train:<stage>`` step's ``spec`` (scenario, self-play mode, airframe, simulator, track), ``best`` and ``log``;
each ``eval:<stage>`` step's ``eval``; and the race caches that the report's own steps (``eval:se-ibr``,
``eval:se-ibr-vs-<stage>``, ``eval:report``, ...) declared. Evaluations it finds nowhere are run with the same races
and seed and cached under ``<out>/evals/`` with the checksums of the checkpoints they used, so a second report reuses
them.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import copy
import dataclasses
import json
import multiprocessing
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from spiral.config.airframe import AIRFRAMES, AirframeCfg
from spiral.config.sim import SimCfg
from spiral.config.track import TrackSpec
from spiral.core.device import torch_threads
from spiral.core.files import atomic_write_bytes, file_sha256
from spiral.eval.evaluate import (
    SE_IBR,
    EvalLayout,
    FlightOverride,
    RaceSet,
    evaluate_methods,
    evaluate_mixed_teams,
    race_device,
)

__all__ = [
    "MODE_OF",
    "EvalProtocol",
    "Evaluations",
    "RowResult",
    "RunRecord",
    "StageRun",
    "crosses_in_workers",
    "final_stage",
    "load_json",
    "method_stage",
    "read_train_log",
    "run_protocol",
    "run_setup",
]

MODE_OF = {"spiral": "pool", "noselfplay": "frozen"}
"""Self-play mode of the stages of each learned method."""


@dataclass
class StageRun:
    """One training stage of a run, as its steps declared it."""

    name: str
    scenario: str
    mode: str
    """Self-play mode: ``pool`` (SPIRAL) or ``frozen`` (PPO without self-play)."""
    best: Path
    """The stage's best policy."""
    eval_path: Path | None
    """Its ``eval:<stage>`` step's evaluation (None: no such step ran)."""
    spec: dict[str, Any]
    train_log: Path | None = None


@dataclass
class RowResult:
    """One cell row of a table: a method in a scenario."""

    scenario: str
    method: str
    checkpoint: str | None = None
    """The method's checkpoint (a path, or ``se-ibr``) that produced (or can produce) the numbers."""
    metrics: dict[str, Any] | None = None
    source: str = ""
    note: str = ""


def method_stage(stages: Iterable[tuple[str, str, str]], scenario: str, method: str) -> str | None:
    """Name of the stage whose best policy races as learned ``method`` in ``scenario``, among ``stages`` given as
    ``(name, scenario, self-play mode)``: the one of the method's mode in that scenario, one named like the scenario
    (``1v1``, ``1v1-noselfplay``) winning a tie, else the first by name."""
    found = sorted((name not in (scenario, f"{scenario}-noselfplay"), name)
                   for name, stage_scenario, mode in stages if stage_scenario == scenario and mode == MODE_OF[method])
    return found[0][1] if found else None


def final_stage(stages: Iterable[tuple[str, str, bool]], mode: str) -> str | None:
    """Name of the stage whose best is the final policy of self-play ``mode``, among ``stages`` given as ``(name,
    self-play mode, published under a name)`` in curriculum order: the last published one, else the last one."""
    own = [(name, published) for name, stage_mode, published in stages if stage_mode == mode]
    chosen = [name for name, published in own if published] or [name for name, _ in own]
    return chosen[-1] if chosen else None


@dataclass(frozen=True)
class RunRecord:
    """What a report reads of a pipeline's run: its stages and the evaluation files its steps declared."""

    root: Path
    """The run folder (``runs/<pipeline>``): named in messages and in results.md."""
    stages: list[StageRun]
    """In name order."""
    evaluations: list[Path] = dataclasses.field(default_factory=list)
    """Evaluation JSONs declared by the run's evaluation steps (``eval:*``): where the report looks for what it
    races before racing it."""

    @classmethod
    def from_manifests(cls, root: Path, manifests: Mapping[str, Mapping[str, Any]]) -> RunRecord:
        """The run that ``manifests`` (step name -> manifest, as a step's context holds its inputs') declare."""
        def outputs(step: str) -> dict[str, Path]:
            return {key: Path(out["path"]) for key, out in manifests.get(step, {}).get("outputs", {}).items()}

        stages = []
        for step in sorted(name for name in manifests if name.startswith("train:")):
            declared = outputs(step)
            if "spec" not in declared or "best" not in declared:
                raise FileNotFoundError(f"{root}: step {step} declares no spec and best (run by an older spiral: "
                                        "run the pipeline again)")
            spec = json.loads(declared["spec"].read_text())
            stage = spec["stage"]
            stages.append(StageRun(stage["name"], stage["scenario"], stage["selfplay"]["mode"], declared["best"],
                                   outputs(f"eval:{stage['name']}").get("eval"), spec, declared.get("log")))
        evaluations = [path for step in sorted(manifests) if step.startswith("eval:")
                       for path in outputs(step).values() if path.suffix == ".json"]
        return cls(Path(root), stages, evaluations)

    @property
    def track(self) -> TrackSpec:
        """The track recorded in the stages' specs."""
        if not self.stages:
            raise FileNotFoundError(f"{self.root}: no stage to read the track of")
        return TrackSpec.model_validate(self.stages[0].spec["track"])


def read_train_log(path: Path) -> list[dict[str, Any]]:
    """Rows of a ``train_log.jsonl`` (a half-written last line is skipped)."""
    if not path.is_file():
        return []
    rows = []
    for line in path.read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return rows


@dataclass(frozen=True)
class EvalProtocol:
    """How a report's evaluations race: ``runs`` races of each scenario on ``track`` from the start placements of
    ``seed``, head to head from ``sides`` (see :func:`spiral.eval.evaluate.cross_play`)."""

    track: TrackSpec
    runs: int
    seed: int
    layout: EvalLayout
    """The layout of planner-only races (:func:`spiral.eval.evaluate.evaluate_methods`)."""
    sides: str = "both"
    starts: Literal["box", "track"] = "box"
    """Where every race starts (as :class:`FlightOverride`'s ``starts``)."""

    def races(self, scenario: str) -> RaceSet:
        """The seeded races of ``scenario``."""
        return RaceSet(self.track, scenario, self.runs, self.seed)


class Evaluations:
    """Finds evaluation results in the run folder, or runs them as ``protocol`` says and caches them under
    ``<out>/evals``."""

    def __init__(self, run: RunRecord, out_dir: Path, protocol: EvalProtocol, *, device: str, se_ibr: bool,
                 log: Callable[[str], None]) -> None:
        self.run, self.cache, self.stages, self.protocol = run, out_dir / "evals", run.stages, protocol
        self.device, self.se_ibr, self.log = device, se_ibr, log
        self.prefix = ""
        """Start of the cached files' names (the held-out and racing variants have their own)."""

    def held_out(self, runs: int, seed: int) -> Evaluations:
        """The same evaluations from other placements (``runs`` races of ``seed``), cached under ``holdout-`` names;
        learned policies only."""
        other = copy.copy(self)
        other.protocol = dataclasses.replace(self.protocol, runs=runs, seed=seed)
        other.prefix, other.se_ibr = "holdout-", False
        return other

    def racing(self, runs: int, seed: int, laps: int, starts: Literal["box", "track"]) -> Evaluations:
        """Races of ``laps`` laps from ``runs`` placements of ``seed``, every one starting where ``starts`` says,
        cached under ``racing-<laps>laps-<starts>-`` names."""
        other = copy.copy(self)
        other.protocol = dataclasses.replace(self.protocol, runs=runs, seed=seed,
                                             track=self.protocol.track.with_laps(laps), starts=starts)
        other.prefix = f"racing-{laps}laps-{starts}-"
        return other

    def stage_for(self, scenario: str, method: str) -> StageRun | None:
        """The stage of learned ``method`` in ``scenario``; one named like the scenario wins a tie."""
        name = method_stage(((s.name, s.scenario, s.mode) for s in self.stages), scenario, method)
        return next((s for s in self.stages if s.name == name), None)

    def checkpoint(self, scenario: str, method: str) -> str | None:
        """The checkpoint (a path, or ``se-ibr``) of ``method`` in ``scenario``, if it exists."""
        if method == "se-ibr":
            return SE_IBR
        stage = self.stage_for(scenario, method)
        return str(stage.best) if stage is not None and stage.best.is_file() else None

    def self_match(self, scenario: str, method: str) -> RowResult:
        """Self-match metrics of ``method`` in ``scenario``: found, run, or missing with a reason."""
        res = RowResult(scenario, method, checkpoint=self.checkpoint(scenario, method))
        if method == "se-ibr":
            found = self._find_se_ibr(scenario)
            if found is not None:
                res.metrics, res.source = found
                return res
            if not self.se_ibr:
                res.note = "not evaluated: pass --se-ibr to run the planner (slow, minutes per scenario)"
                return res
        else:
            stage = self.stage_for(scenario, method)
            if stage is None:
                res.note = f"no {MODE_OF[method]}-mode {scenario} stage in {self.run.root}"
                return res
            data = None if stage.eval_path is None else load_json(stage.eval_path)
            if data is not None and (data["runs"], data["seed"]) == self._placements() and data["methods"]:
                res.metrics, res.source = next(iter(data["methods"].values())), str(stage.eval_path)
                return res
            if res.checkpoint is None:
                res.note = f"stage '{stage.name}' has no best.pt"
                return res
        assert res.checkpoint is not None
        data, path = self._run(f"self-{scenario}-{method}", scenario, {method: res.checkpoint}, None)
        res.metrics, res.source = data["methods"][method], str(path)
        return res

    def flown(self, scenario: str, method: str, checkpoint: str, flight: FlightOverride, variant: str) -> RowResult:
        """Self-match of ``method`` racing ``checkpoint`` with another flight stack; ``variant`` names it in the
        cache."""
        data, path = self._run(f"self-{scenario}-{method}-{variant}", scenario, {method: checkpoint}, None,
                               flight=flight)
        return RowResult(scenario, method, checkpoint=checkpoint, metrics=data["methods"][method], source=str(path))

    def cross(self, scenario: str, a: tuple[str, str], b: tuple[str, str], *, flight: FlightOverride | None = None,
              variant: str = "") -> dict[str, Any]:
        """Team ``a`` (method, checkpoint) against team ``b``: the method entry of the evaluation JSON (with the
        opponent team's metrics under ``opponent``)."""
        data, _ = self._run(_cross_tag(scenario, a, b, variant), scenario, {a[0]: a[1]}, b, flight=flight)
        return data["methods"][a[0]]

    def has_cross(self, scenario: str, a: tuple[str, str], b: tuple[str, str]) -> bool:
        """Whether :meth:`cross` would find the pairing raced (in this cache or another step's of the run folder)."""
        return self._cached(_cross_tag(scenario, a, b, ""), self._inputs(scenario, {a[0]: a[1]}, b)) is not None

    def mixed(self, a: tuple[str, str], b: tuple[str, str]) -> dict[str, Any]:
        """2v2 races in mixed teams (one drone of ``a`` and one of ``b`` per team): each method's entry."""
        data, _ = self._run(f"mixed-2v2-{a[0]}-{b[0]}", "2v2", {a[0]: a[1], b[0]: b[1]}, None, mixed=True)
        return data["methods"]

    def _find_se_ibr(self, scenario: str) -> tuple[dict[str, Any], str] | None:
        paths = [self.cache / f"self-{scenario}-se-ibr.json", *self.run.evaluations]
        for path in paths:
            data = load_json(path)
            if data is None or data.get("scenario") != scenario or "against" in data:
                continue
            if (data.get("runs"), data.get("seed")) != self._placements():
                continue
            for entry in data.get("methods", {}).values():
                if str(entry.get("checkpoint", "")).lower() == SE_IBR:
                    return entry, str(path)
        return None

    def _inputs(self, scenario: str, methods: dict[str, str], against: tuple[str, str] | None, *,
                flight: FlightOverride | None = None, mixed: bool = False) -> dict[str, Any]:
        """What an evaluation's numbers depend on, as its JSON records them under ``inputs``."""
        flight = self._flight(flight)
        checkpoints = [*methods.values(), *([against[1]] if against else [])]
        p = self.protocol
        inputs = {"track": p.track.model_dump(mode="json"), "scenario": scenario, "runs": p.runs,
                  "seed": p.seed, "device": race_device(self.device, checkpoints),
                  "checkpoints": [c if c == SE_IBR else _checksum(Path(c)) for c in checkpoints],
                  **({"sides": p.sides} if against else {}), **({"mixed": True} if mixed else {}),
                  **({"flight": flight.to_json()} if flight is not None and flight.to_json() else {})}
        return json.loads(json.dumps(inputs))  # compare as read back: tuples become lists

    def _cached(self, tag: str, inputs: dict[str, Any]) -> tuple[dict[str, Any], Path] | None:
        """The evaluation ``tag`` raced with ``inputs``: from this cache, else from the caches the run's steps
        declared (where a pipeline races the report's evaluations ahead of it)."""
        name = f"{self.prefix}{tag}.json"
        for path in [self.cache / name, *(p for p in self.run.evaluations if p.name == name)]:
            cached = load_json(path)
            if cached is not None and cached.get("inputs") == inputs:
                return cached, path
        return None

    def _run(self, tag: str, scenario: str, methods: dict[str, str], against: tuple[str, str] | None, *,
             flight: FlightOverride | None = None, mixed: bool = False) -> tuple[dict[str, Any], Path]:
        """Run ``spiral eval`` for ``methods`` (optionally against a team, or in mixed teams) unless a matching
        cache exists."""
        inputs = self._inputs(scenario, methods, against, flight=flight, mixed=mixed)
        found = self._cached(tag, inputs)
        if found is not None:
            return found
        flight, p = self._flight(flight), self.protocol
        self.log(f"report: running {self.prefix}{tag} ({p.runs} races, seed {p.seed})")
        if mixed:
            data = evaluate_mixed_teams(p.track, methods, runs=p.runs, seed=p.seed, device=self.device, flight=flight)
        else:
            data = evaluate_methods(p.races(scenario), methods, device=self.device, against=against,
                                    layout=p.layout, sides=p.sides, flight=flight)
        data["inputs"] = inputs
        path = self.cache / f"{self.prefix}{tag}.json"
        atomic_write_bytes(path, (json.dumps(data, indent=2) + "\n").encode())  # other steps may be reading the run
        return data, path

    def _flight(self, flight: FlightOverride | None) -> FlightOverride | None:
        """``flight`` with these evaluations' starts."""
        if self.protocol.starts == "box":
            return flight
        return dataclasses.replace(flight or FlightOverride(), starts=self.protocol.starts)

    def _placements(self) -> tuple[int, int]:
        """Races and seed of these evaluations, as an evaluation JSON records them."""
        return self.protocol.runs, self.protocol.seed


def _cross_tag(scenario: str, a: tuple[str, str], b: tuple[str, str], variant: str) -> str:
    return f"cross-{scenario}-{a[0]}-vs-{b[0]}" + (f"-{variant}" if variant else "")


@contextlib.contextmanager
def crosses_in_workers(ev: Evaluations, pairings: list[tuple[str, tuple[str, str], tuple[str, str]]], *,
                       jobs: int) -> Iterator[None]:
    """Race the head-to-head ``pairings`` (scenario, team a, team b) that ``ev`` does not find raced in up to ``jobs``
    processes (one torch thread each) while the body of the ``with`` runs (on one torch thread), and wait for them
    at its end, so that the report's own calls find them cached. Used for the planner's pairings, which take minutes
    each: the body races what needs no planner meanwhile. With ``jobs`` ≤ 1 or nothing to race nothing runs in a
    worker."""
    missing = [p for p in pairings if not ev.has_cross(*p)]
    if jobs <= 1 or not missing:
        yield
        return
    quiet = copy.copy(ev)
    quiet.log = print
    context = multiprocessing.get_context("spawn")
    pool = concurrent.futures.ProcessPoolExecutor(max_workers=jobs, mp_context=context)
    try:
        with torch_threads(1):  # the workers take the cores: this process's races must not oversubscribe them
            futures = []
            for scenario, a, b in missing:
                ev.log(f"report: running {ev.prefix}{_cross_tag(scenario, a, b, '')} in a worker process")
                futures.append(pool.submit(_cross_in_worker, (quiet, (scenario, a, b))))
            yield
            for future in futures:
                future.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _cross_in_worker(job: tuple[Evaluations, tuple[str, tuple[str, str], tuple[str, str]]]) -> None:
    ev, (scenario, a, b) = job
    with torch_threads(1):
        ev.cross(scenario, a, b)


def load_json(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _checksum(path: Path) -> str:
    side = load_json(path.with_suffix(".json"))
    return side["sha256"] if side and "sha256" in side else file_sha256(path)


def run_protocol(stages: list[StageRun], runs: int | None, seed: int | None) -> tuple[int, int]:
    """Races and seed: as given, else those of the pipeline's stage evaluations, else 50 and 0."""
    for stage in stages:
        data = None if stage.eval_path is None else load_json(stage.eval_path)
        if data is not None:
            return runs or data["runs"], data["seed"] if seed is None else seed
    return runs or 50, 0 if seed is None else seed


def run_setup(stages: list[StageRun]) -> tuple[AirframeCfg, SimCfg]:
    for stage in stages:
        if "airframe" in stage.spec and "sim" in stage.spec:
            return AirframeCfg.model_validate(stage.spec["airframe"]), SimCfg.model_validate(stage.spec["sim"])
    return AIRFRAMES["cf2x"], SimCfg()
