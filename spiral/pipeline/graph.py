"""Expand a pipeline spec into ordered steps: train, eval and publish per stage."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from spiral.config.airframe import AirframeCfg, resolve_airframe
from spiral.config.pipeline import PipelineSpec
from spiral.config.stage import StageSpec
from spiral.config.track import TrackSpec
from spiral.core.errors import UsageError
from spiral.core.files import atomic_write_bytes, file_sha256
from spiral.env.setting import RaceSetting
from spiral.eval.evaluate import RaceSet, evaluate_methods
from spiral.pipeline.report_steps import PLANNER_STEP, report_steps
from spiral.pipeline.step import Step, StepContext
from spiral.pipeline.tracks_step import TRACKS_STEP, generated_tracks, tracks_step
from spiral.selfplay.curriculum import StageSources, run_stage
from spiral.train.progress import TRAIN_LOG

__all__ = ["PLANNER_STEP", "PipelinePlan", "select_steps"]

@dataclass
class PipelinePlan:
    """A pipeline's steps and where they write: ``runs/<name>/<step>/`` and ``checkpoints/<name>/<stage>/``."""

    spec: PipelineSpec
    track: TrackSpec
    source: Path
    runs_dir: Path
    checkpoints_dir: Path
    sim_threads: int = 1
    """CPU threads that step each training step's simulator (``spiral train --sim-threads``; the same results for
    any count)."""

    @property
    def run_root(self) -> Path:
        """Folder of this pipeline's step outputs."""
        return self.runs_dir / self.spec.name

    @property
    def publish_root(self) -> Path:
        """Folder of this pipeline's published policies."""
        return self.checkpoints_dir / self.spec.name

    @property
    def airframe(self) -> AirframeCfg:
        """The pipeline's airframe with its overrides applied (an error names the pipeline file)."""
        return resolve_airframe(self.spec.airframe, source=str(self.source))

    def steps(self) -> list[Step]:
        """Every step in dependency order."""
        steps: list[Step] = []
        if self.spec.training_tracks is not None:
            steps.append(tracks_step(self))
        for index, stage in enumerate(self.spec.stages):
            init = self.spec.init_stage(index)
            previous = f"train:{init}" if init else None
            source = stage.selfplay.opponent_from if stage.scenario != "solo" else None
            opponent = f"train:{source}" if source else None
            tracks = TRACKS_STEP if self.spec.training_tracks is not None else None
            inputs = list(dict.fromkeys(name for name in (tracks, previous, opponent) if name))
            train = Step(f"train:{stage.name}", self._train_fn(stage, previous, opponent), inputs,
                         self._train_section(stage), resumable=True)
            evaluate = Step(f"eval:{stage.name}", self._eval_fn(stage), [train.name],
                            {"scenario": stage.scenario, **self.spec.evaluation.model_dump(include={"runs", "seed"})})
            publish = Step(f"publish:{stage.name}", self._publish_fn(stage), [train.name, evaluate.name],
                           {"stage": stage.name, "dest": str(self.publish_root / stage.name),
                            "publish_as": stage.publish_as})
            steps += [train, evaluate, publish]
        return report_steps(self, steps)

    def _last_pool_stage(self) -> str | None:
        """The last self-play stage: its pool is the one published to ``checkpoints/<name>/pool``."""
        names = [s.name for s in self.spec.stages if s.scenario != "solo" and s.selfplay.mode == "pool"]
        return names[-1] if names else None

    def _train_section(self, stage: StageSpec) -> dict[str, Any]:
        """The training step's spec: models, which its fingerprint hashes by the fields that differ from defaults,
        and the content of a checkpoint file it starts from."""
        section = {"stage": stage, "track": self.track,
                   "airframe": self.airframe,
                   "sim": self.spec.sim, "device": self.spec.device,
                   "seed": stage.seed if stage.seed is not None else self.spec.seed}
        init = self.init_file(stage)
        if init is not None:
            section["init_sha256"] = file_sha256(init)
        return section

    def init_file(self, stage: StageSpec) -> Path | None:
        """The checkpoint file ``stage`` starts from (its ``init_from``, relative to the pipeline file), if it names
        one; a missing file is an error naming the pipeline and the field."""
        if stage.init_file is None:
            return None
        path = self.source.parent / stage.init_file
        if not path.is_file():
            index = [s.name for s in self.spec.stages].index(stage.name)
            raise UsageError(f"{self.source}: stages.{index}.init_from: checkpoint {path} does not exist")
        return path

    def _train_fn(self, stage: StageSpec, previous: str | None, opponent: str | None):
        def run(ctx: StepContext) -> tuple[dict[str, Path], dict[str, Any]]:
            section = self._train_section(stage)
            resolved = {key: v.model_dump() if isinstance(v, BaseModel) else v for key, v in section.items()}
            spec_path = ctx.step_dir / "spec.json"
            atomic_write_bytes(spec_path, json.dumps(resolved, indent=2).encode())
            init, frozen = (Path(ctx.inputs[s]["outputs"]["best"]["path"]) if s else None for s in (previous, opponent))
            init = init or self.init_file(stage)
            pool_dir = ctx.step_dir / "pool"
            inherited = ctx.inputs[previous]["outputs"].get("pool") if previous else None
            if inherited is not None and not pool_dir.exists():  # the pool carries over from stage to stage
                shutil.copytree(Path(inherited["path"]).parent, pool_dir)
            sources = StageSources(pool_dir=pool_dir, init_checkpoint=init, opponent_checkpoint=frozen)
            setting = RaceSetting(self.track, self.airframe, self.spec.sim, self.sim_threads)
            if TRACKS_STEP in ctx.inputs:  # generated tracks instead of the pipeline's, a track per world
                first, *more = generated_tracks(ctx.inputs[TRACKS_STEP], "train")
                setting = RaceSetting(first, self.airframe, self.spec.sim, self.sim_threads, more_tracks=tuple(more))
            result = run_stage(setting, stage, ctx.step_dir,
                               sources=sources, device=self.spec.device, seed=section["seed"], log=ctx.log,
                               progress=ctx.progress)
            info = {"iterations": result.iterations, "wall_time_s": result.wall_time_s, "env_steps": result.env_steps,
                    "best": {"success": result.best.success, "lap_time": result.best.lap_time,
                             "iteration": result.best.iteration}}
            outputs = {"best": result.best_path, "last": result.last_path, "spec": spec_path}
            if (ctx.step_dir / TRAIN_LOG).is_file():
                outputs["log"] = ctx.step_dir / TRAIN_LOG
            if (pool_dir / "pool.json").is_file():  # a self-play stage's pool, declared for the steps that read it
                outputs["pool"] = pool_dir / "pool.json"
            return outputs, info
        return run

    def _eval_fn(self, stage: StageSpec):
        def run(ctx: StepContext) -> tuple[dict[str, Path], dict[str, Any]]:
            best = Path(ctx.inputs[f"train:{stage.name}"]["outputs"]["best"]["path"])
            ev = self.spec.evaluation
            result = evaluate_methods(RaceSet(self.track, stage.scenario, ev.runs, ev.seed), {"spiral": best},
                                      device=self.spec.device)
            out = ctx.step_dir / "eval.json"
            atomic_write_bytes(out, json.dumps(result, indent=2).encode())
            m = result["methods"]["spiral"]
            ctx.log(f"eval:{stage.name}: success {m['success_ratio']:.2f}, lap {m['lap_time_mean']}")
            return {"eval": out}, {"success_ratio": m["success_ratio"], "lap_time_mean": m["lap_time_mean"]}
        return run

    def _publish_fn(self, stage: StageSpec):
        def run(ctx: StepContext) -> tuple[dict[str, Path], dict[str, Any]]:
            dest = self.publish_root / stage.name
            dest.mkdir(parents=True, exist_ok=True)
            best = Path(ctx.inputs[f"train:{stage.name}"]["outputs"]["best"]["path"])
            evaluation = Path(ctx.inputs[f"eval:{stage.name}"]["outputs"]["eval"]["path"])
            outputs = {}
            copies = [("best", best, dest / "best.pt"), ("best_meta", best.with_suffix(".json"), dest / "best.json"),
                      ("eval", evaluation, dest / "eval.json")]
            if stage.publish_as:
                final = self.publish_root / stage.publish_as
                copies += [("final", best, final),
                           ("final_meta", best.with_suffix(".json"), final.with_suffix(".json"))]
            for key, src, target in copies:
                atomic_write_bytes(target, src.read_bytes())
                outputs[key] = target
            pool = ctx.inputs[f"train:{stage.name}"]["outputs"].get("pool")
            if pool is not None and stage.name == self._last_pool_stage():
                shutil.rmtree(self.publish_root / "pool", ignore_errors=True)
                shutil.copytree(Path(pool["path"]).parent, self.publish_root / "pool")
                outputs["pool"] = self.publish_root / "pool" / "pool.json"
            ctx.log(f"publish:{stage.name}: published {dest / 'best.pt'}")
            return outputs, {"dest": str(dest)}
        return run


def select_steps(steps: list[Step], *, start: str | None = None, only: str | None = None) -> list[Step]:
    """Steps to consider: all, from ``start`` on, or ``only`` one (unknown names raise ValueError)."""
    names = [s.name for s in steps]
    for name in (start, only):
        if name is not None and name not in names:
            raise UsageError(f"unknown step {name!r}; steps: {', '.join(names)}")
    if only is not None:
        return [s for s in steps if s.name == only]
    if start is not None:
        return steps[names.index(start):]
    return steps


def wipe(path: Path) -> None:
    """Remove a step folder."""
    shutil.rmtree(path, ignore_errors=True)
