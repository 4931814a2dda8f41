"""The steps of a pipeline's report: the planner's races, the report's races among learned policies, and the report.

Each races as soon as what it needs exists, so that ``spiral run --jobs N`` runs them beside the training steps that
are still going: the planner's self-matches (``eval:se-ibr``) need no trained policy, each of its head-to-head
pairings with a learned method (``eval:se-ibr-vs-<stage>``) needs that stage's best policy, and the races among
learned policies (``eval:report``) need every stage. They race on one torch thread each, cache their results under
``runs/<pipeline>/<step>/evals/`` and declare them as outputs; the ``report`` step reads what its input steps declared
(:class:`spiral.eval.runs.RunRecord`): what it writes is the same as if it had raced everything itself.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any, Protocol

from spiral.config.airframe import AirframeCfg
from spiral.config.load import load_track
from spiral.config.pipeline import PipelineSpec
from spiral.config.track import TrackSpec
from spiral.core.device import torch_threads
from spiral.core.errors import UsageError
from spiral.core.files import atomic_write_bytes, file_sha256
from spiral.eval.evaluate import SE_IBR, EvalLayout, RaceSet, evaluate_methods, race_device
from spiral.eval.report import (
    SCENARIOS,
    ReportOptions,
    build_report,
    race_learned_policies,
    race_planner_pairing,
    race_planner_racing,
)
from spiral.eval.runs import MODE_OF, RunRecord, final_stage, method_stage
from spiral.eval.unseen_tracks import race_unseen_tracks, unseen_tracks_markdown
from spiral.pipeline.manifest import MANIFEST, read_manifest
from spiral.pipeline.step import Step, StepContext
from spiral.pipeline.tracks_step import TRACKS_STEP, generated_tracks

__all__ = ["LEARNED_STEP", "PLANNER_RACING_STEP", "PLANNER_STEP", "UNSEEN_STEP", "read_run", "report_steps"]

PLANNER_STEP = "eval:se-ibr"
"""The step that races SE-IBR's self-matches (with ``report.se_ibr``)."""
PLANNER_RACING_STEP = "eval:se-ibr-racing"
"""The step that races SPIRAL's final policy against SE-IBR for the racing section (with ``report.se_ibr`` and
``report.racing``)."""
UNSEEN_STEP = "eval:unseen-tracks"
"""The step that races the final policies on tracks no training step flew (with ``report.unseen_tracks``)."""
LEARNED_STEP = "eval:report"
"""The step that races what the report races among learned policies."""
REPORT_JOBS = os.cpu_count() or 1
"""Processes in which the report races planner pairings that no step raced (a step run alone with ``--only``)."""


class PlanView(Protocol):
    """What the report's steps read of a pipeline's plan (:class:`spiral.pipeline.graph.PipelinePlan`)."""

    spec: PipelineSpec
    track: TrackSpec
    source: Path

    @property
    def run_root(self) -> Path: ...

    @property
    def airframe(self) -> AirframeCfg: ...


def report_steps(plan: PlanView, steps: list[Step]) -> list[Step]:
    """``steps`` (the stages' train, eval and publish steps) with the report's steps added: the planner's
    self-matches first (``--jobs`` runs them beside the first training step), its pairings, the report's races among
    learned policies and the report last."""
    report = plan.spec.report
    if not report.enabled:
        return steps
    out = list(steps)
    if report.se_ibr:
        out.insert(0, Step(PLANNER_STEP, _planner_fn(plan), [], _planner_section(plan)))
        if report.cross_play or report.robustness:
            out += _pairing_steps(plan)
        out += _planner_racing_steps(plan)
    out += _unseen_tracks_steps(plan)
    section = {"report": report, **plan.spec.evaluation.model_dump()}
    stage_steps = [s.name for s in steps if not s.name.startswith("publish:")]
    out.append(Step(LEARNED_STEP, _learned_fn(plan), stage_steps, section))
    out.append(Step("report", _report_fn(plan), [s.name for s in out if not s.name.startswith("publish:")], section))
    return out


def read_run(root: Path) -> RunRecord:
    """The run in folder ``root`` (``runs/<pipeline>``) as its steps' manifests declare it (``spiral report``);
    declared paths are read as written, relative to the folder the pipeline ran in."""
    manifests = {}
    for path in sorted(Path(root).glob(f"*/{MANIFEST}")):
        data = read_manifest(path.parent)
        if data is not None and "step" in data:
            manifests[data["step"]] = data
    run = RunRecord.from_manifests(root, manifests)
    if not run.stages:
        raise FileNotFoundError(f"{root}: no training step's manifest (is this runs/<pipeline>?)")
    for stage in run.stages:
        if not stage.best.is_file():
            raise FileNotFoundError(f"{root}: stage {stage.name}'s best policy {stage.best} is missing (run spiral "
                                    "report from the folder the pipeline ran in)")
    return run


def _planner_section(plan: PlanView) -> dict[str, Any]:
    """What the planner's self-matches depend on: raced on the CPU whatever the pipeline's device."""
    return {"scenarios": list(SCENARIOS), **plan.spec.evaluation.model_dump(include={"runs", "seed"}),
            "track": plan.track, "sim": plan.spec.sim, "airframe": plan.airframe,
            "device": race_device(plan.spec.device, [SE_IBR])}


def _planner_fn(plan: PlanView):
    """SE-IBR's self-matches in 1v1 and 2v2 with the protocol's races, one eval JSON per scenario (the report
    finds them), flown through the default action mapping with no separation filter: the paper's stack."""
    def run(ctx: StepContext) -> tuple[dict[str, Any], dict[str, Any]]:
        ev, outputs, info = plan.spec.evaluation, {}, {}
        for scenario in SCENARIOS:
            result = evaluate_methods(RaceSet(plan.track, scenario, ev.runs, ev.seed), {"se-ibr": "se-ibr"},
                                      device=plan.spec.device,
                                      layout=EvalLayout.default(airframe=plan.airframe, sim=plan.spec.sim))
            out = ctx.step_dir / f"eval-{scenario}.json"
            atomic_write_bytes(out, json.dumps(result, indent=2).encode())
            m = result["methods"]["se-ibr"]
            ctx.log(f"{PLANNER_STEP} {scenario}: success {m['success_ratio']:.2f}, lap {m['lap_time_mean']}")
            outputs[f"eval_{scenario}"], info[scenario] = out, m["success_ratio"]
        return outputs, info
    return run


def _pairing_steps(plan: PlanView) -> list[Step]:
    """One step per learned method and scenario that a stage of the pipeline trains: its pairing with SE-IBR."""
    stages = [(s.name, s.scenario, s.selfplay.mode) for s in plan.spec.stages]
    out = []
    for scenario in SCENARIOS:
        for method in MODE_OF:
            stage = method_stage(stages, scenario, method)
            if stage is None:
                continue
            section = {"scenario": scenario, "method": method, "against": "se-ibr",
                       **plan.spec.evaluation.model_dump(include={"runs", "seed", "sides"})}
            name = f"{PLANNER_STEP}-vs-{stage}"
            out.append(Step(name, _pairing_fn(plan, name, scenario, method), [f"train:{stage}"], section))
    return out


def _pairing_fn(plan: PlanView, name: str, scenario: str, method: str):
    def run(ctx: StepContext) -> tuple[dict[str, Any], dict[str, Any]]:
        entry = race_planner_pairing(_run(plan, ctx), plan.track, ctx.step_dir, scenario, method,
                                     _report_options(plan), log=ctx.log)
        ctx.log(f"{name}: win rate {entry['win_rate']:.2f}, success {entry['success_ratio']:.2f} against SE-IBR")
        return _caches(ctx), {"win_rate": entry["win_rate"], "success_ratio": entry["success_ratio"]}
    return run


def _planner_racing_steps(plan: PlanView) -> list[Step]:
    """SPIRAL's duels against SE-IBR for the racing section, once SPIRAL's final stage has trained (none without a
    racing section, planner races or a SPIRAL stage)."""
    racing, ev = plan.spec.report.racing, plan.spec.evaluation
    final = final_stage(((s.name, s.selfplay.mode, bool(s.publish_as)) for s in plan.spec.stages),
                        MODE_OF["spiral"])
    if racing is None or not racing.planner_runs or final is None:
        return []
    section = {"racing": racing, **ev.model_dump(include={"holdout_seed", "sides"})}

    def run(ctx: StepContext) -> tuple[dict[str, Any], dict[str, Any]]:
        duels = race_planner_racing(_run(plan, ctx), plan.track, ctx.step_dir, _report_options(plan), log=ctx.log)
        info = {f"{starts}-{s}": entry["win_rate"] for starts, by in duels.items() for s, entry in by.items()}
        ctx.log(f"{PLANNER_RACING_STEP}: SPIRAL's win rate against SE-IBR {info}")
        return _caches(ctx), info
    return [Step(PLANNER_RACING_STEP, run, [f"train:{final}"], section)]


def _final_stages(plan: PlanView) -> dict[str, str]:
    """The stage whose best is each learned method's final policy, for the methods the pipeline trains."""
    stages = [(s.name, s.selfplay.mode, bool(s.publish_as)) for s in plan.spec.stages if s.scenario != "solo"]
    finals = {method: final_stage(stages, mode) for method, mode in MODE_OF.items()}
    return {method: stage for method, stage in finals.items() if stage is not None}


def _unseen_tracks_steps(plan: PlanView) -> list[Step]:
    """The final policies' races on tracks no training step flew (with ``report.unseen_tracks``): the held-out
    generated tracks and the pipeline's own track when it trained on generated ones, and the section's files."""
    cfg = plan.spec.report.unseen_tracks
    finals = _final_stages(plan)
    if cfg is None or not finals:
        return []
    generated = plan.spec.training_tracks is not None
    files = [(str(path), load_track(plan.source.parent / path)) for path in cfg.tracks]
    specialists = {name: _specialist_file(plan, name, path) for name, path in cfg.specialists.items()}
    section = {"unseen_tracks": cfg, "files": [track for _, track in files], "airframe": plan.airframe,
               "own": plan.track if generated else None, "device": race_device(plan.spec.device, [])}
    if specialists:
        section["specialist_sha256"] = {name: file_sha256(path) for name, path in specialists.items()}
    inputs = [f"train:{stage}" for stage in finals.values()] + ([TRACKS_STEP] if generated else [])

    def run(ctx: StepContext) -> tuple[dict[str, Any], dict[str, Any]]:
        tracks = []
        if generated:
            tracks += [("held out", t) for t in generated_tracks(ctx.inputs[TRACKS_STEP], "held_out")]
            tracks.append(("pipeline's track", plan.track))
        tracks += [("file", track) for _, track in files]
        methods = {method: Path(ctx.inputs[f"train:{stage}"]["outputs"]["best"]["path"])
                   for method, stage in finals.items()}
        unraced = sorted(set(specialists) - {track.name for _, track in tracks})
        if unraced:
            raise UsageError(f"{plan.source}: report.unseen_tracks.specialists: no track of the section is named "
                             f"{', '.join(unraced)}")
        with torch_threads(1):
            races = race_unseen_tracks(tracks, methods, cfg, plan.airframe, specialists=specialists,
                                       device=section["device"], log=ctx.log)
        table, text = ctx.step_dir / "unseen_tracks.json", ctx.step_dir / "unseen_tracks.md"
        atomic_write_bytes(table, json.dumps(dataclasses.asdict(races), indent=2).encode())
        atomic_write_bytes(text, unseen_tracks_markdown(races, cfg, f"spiral run {plan.source}").encode())
        return {"rows": table, "section": text}, {"tracks": len(tracks)}

    return [Step(UNSEEN_STEP, run, inputs, section)]


def _specialist_file(plan: PlanView, track: str, path: Path) -> Path:
    """A specialist's checkpoint (``report.unseen_tracks.specialists``, relative to the pipeline file); a missing
    file is an error naming the pipeline and the field."""
    found = plan.source.parent / path
    if not found.is_file():
        raise UsageError(f"{plan.source}: report.unseen_tracks.specialists.{track}: checkpoint {found} does not "
                         "exist")
    return found


def _report_options(plan: PlanView) -> ReportOptions:
    """The report's options from the pipeline's ``evaluation`` and ``report``."""
    cfg, ev = plan.spec.report, plan.spec.evaluation
    return ReportOptions(runs=ev.runs, seed=ev.seed, device=plan.spec.device, se_ibr=cfg.se_ibr,
                         cross_play=cfg.cross_play, airframe=plan.airframe, sides=ev.sides,
                         holdout=(ev.holdout_runs, ev.holdout_seed) if ev.holdout_runs else None,
                         separation=cfg.separation, robustness=cfg.robustness, racing=cfg.racing,
                         command=f"spiral run {plan.source}", jobs=REPORT_JOBS)


def _run(plan: PlanView, ctx: StepContext) -> RunRecord:
    """The run as the step's input steps declared it."""
    return RunRecord.from_manifests(plan.run_root, ctx.inputs)


def _caches(ctx: StepContext) -> dict[str, Path]:
    """The race caches a step wrote (``<step>/evals/*.json``), declared as its outputs by file name."""
    return {path.name: path for path in sorted((ctx.step_dir / "evals").glob("*.json"))}


def _learned_fn(plan: PlanView):
    def run(ctx: StepContext) -> tuple[dict[str, Any], dict[str, Any]]:
        race_learned_policies(_run(plan, ctx), plan.track, ctx.step_dir, _report_options(plan), log=ctx.log)
        return _caches(ctx), {}
    return run


def _report_fn(plan: PlanView):
    def run(ctx: StepContext) -> tuple[dict[str, Any], dict[str, Any]]:
        with torch_threads(1):  # all is raced by the steps before; anything left races as they race it
            results = build_report(_run(plan, ctx), plan.track, ctx.step_dir, _report_options(plan), log=ctx.log)
        if UNSEEN_STEP in ctx.inputs:  # the unseen-tracks section, as its step wrote it
            section = Path(ctx.inputs[UNSEEN_STEP]["outputs"]["section"]["path"]).read_text()
            atomic_write_bytes(results, (results.read_text().rstrip("\n") + "\n\n" + section).encode())
        ctx.log(f"report: {results}")
        return {"results": results, "csv": results.with_name("results.csv"),
                "headline": results.with_name("headline.json")}, {}
    return run
