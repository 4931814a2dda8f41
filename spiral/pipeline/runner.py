"""Run a pipeline's steps in order (or independent ones side by side), skipping complete ones, resuming interrupted
training, one run at a time."""

from __future__ import annotations

import json
import shlex
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from spiral.config.load import load_pipeline
from spiral.core.checkpoint import list_checkpoints
from spiral.core.device import canonical_device, check_device, torch_threads
from spiral.core.errors import UsageError
from spiral.core.files import atomic_write_bytes
from spiral.pipeline.graph import PipelinePlan, select_steps
from spiral.pipeline.lock import PipelineLock
from spiral.pipeline.manifest import (
    MANIFEST,
    Fingerprint,
    StepState,
    fingerprint,
    read_manifest,
    step_state,
    write_manifest,
)
from spiral.pipeline.parallel import Launcher, LocalLauncher, check_cores, run_parallel
from spiral.pipeline.step import PipelineError, Step, StepContext

__all__ = ["PipelineRunner", "StepStatus"]

FINGERPRINT_FILE = "fingerprint"


@dataclass
class StepStatus:
    """A step's state for ``spiral status``."""

    name: str
    status: str
    reason: str
    detail: str = ""


class PipelineRunner:
    """Loads a pipeline file and runs or reports its steps."""

    def __init__(self, path: Path, *, runs_dir: Path = Path("runs"), checkpoints_dir: Path = Path("checkpoints"),
                 log: Callable[[str], None] = print, progress: bool = True, device: str | None = None,
                 accept_code_changes: bool = False, overrides: Sequence[str] = ()) -> None:
        spec, track = load_pipeline(path, overrides)
        self.overrides = tuple(overrides)
        """``path.to.field=value`` settings over the file's (``spiral run --set``); the run is named for them."""
        if device is not None:  # its name now; whether this machine has it when steps run (spiral status needs none)
            spec = spec.model_copy(update={"device": canonical_device(device)})
        self.path, self.log, self.progress = Path(path), log, progress
        self.accept_code_changes = accept_code_changes
        """Treat steps that ran with other spiral source (same spec and inputs) as complete."""
        self.plan = PipelinePlan(spec, track, self.path, Path(runs_dir), Path(checkpoints_dir))
        self.steps = self.plan.steps()

    def _dir(self, step: Step) -> Path:
        return self.plan.run_root / step.dirname

    def _fingerprints(self) -> dict[str, Fingerprint]:
        fps: dict[str, Fingerprint] = {}
        for step in self.steps:
            fps[step.name] = fingerprint(step.name, step.spec_section, [fps[i] for i in step.inputs])
        return fps

    def status(self) -> list[StepStatus]:
        """Each step: complete, stale (why), partial (last checkpoint) or missing; stale inputs make steps stale."""
        fps, out, stale_inputs = self._fingerprints(), [], set()
        for step in self.steps:
            state = self._state(step, fps[step.name])
            if state.status == "missing" and (found := self._reusable(step, fps[step.name])) is not None:
                state = StepState("missing", f"{found} has it: spiral run reuses it")
            if state.status == "complete" and stale_inputs & set(step.inputs):
                state = StepState("stale", "an input step is not complete")
            if state.status != "complete":
                stale_inputs.add(step.name)
            detail = ""
            ckpts = list_checkpoints(self._dir(step) / "ckpt")
            if state.status == "partial" and ckpts:
                detail = f"last checkpoint: iteration {ckpts[0][0]}"
            out.append(StepStatus(step.name, state.status, state.reason, detail))
        return out

    def run(self, *, start: str | None = None, only: str | None = None, force: list[str] | None = None,
            jobs: int = 1, threads: int = 1, launcher: Launcher | None = None) -> list[str]:
        """Run the selected steps, up to ``jobs`` independent ones at a time, each with ``threads`` torch threads;
        return the names of those that ran.

        With a ``launcher`` (e.g. Ray's) every step runs in a worker it starts; without one, a step at a time runs
        in this process and several in child processes. Every executor computes a step with the same ``threads``
        (they decide its numbers to the bit): this process, a worker and a Ray task train the same policy."""
        if jobs < 1 or threads < 1:
            raise UsageError(f"jobs and threads must be at least 1, got {jobs} and {threads}")
        check_cores(launcher or LocalLauncher(), jobs, threads, self.log)
        check_device(self.plan.spec.device)
        selected = {s.name for s in select_steps(self.steps, start=start, only=only)}
        forced = set(force or [])
        unknown = forced - {s.name for s in self.steps}
        if unknown:
            raise UsageError(f"unknown step(s) {', '.join(sorted(unknown))}")
        fps, todo = self._fingerprints(), {}
        with PipelineLock(self.plan.run_root / ".lock", log=self.log):
            for step in self.steps:  # also the inputs of a step run alone (--only)
                if step.name not in forced:
                    self._reuse(step, fps[step.name])
            for step in self.steps:
                if step.name not in selected:
                    continue
                must = step.name in forced or any(i in todo for i in step.inputs)
                state = self._state(step, fps[step.name])
                if state.status == "complete" and not must and not (start and step.name == start):
                    self.log(f"step '{step.name}' unchanged, skipping")
                    continue
                if step.name not in forced:
                    self._refuse_a_device_change(step)
                self._refuse_missing_inputs(step, todo, fps)
                todo[step.name] = (step, state)  # running upstream steps leaves a step's own folder as it is
            if launcher is not None or (jobs > 1 and len(todo) > 1):
                return run_parallel(self, [step for step, _ in todo.values()], forced, jobs, threads,
                                    launcher=launcher)
            for step, state in todo.values():
                self._run_step(step, fps[step.name], state, fresh=step.name in forced, threads=threads)
        return list(todo)

    def _refuse_missing_inputs(self, step: Step, todo: dict[str, Any], fps: dict[str, Fingerprint]) -> None:
        """A step runs only once every step it reads is complete or runs before it in this run."""
        missing = [name for name in step.inputs
                   if name not in todo and self._state(self._step(name), fps[name]).status != "complete"]
        if missing:
            raise UsageError(f"step '{step.name}' reads {', '.join(missing)}, not complete: run it first "
                             f"(--only {missing[0]}), or the pipeline without --only")

    def run_step(self, name: str, *, fresh: bool = False, threads: int = 1) -> None:
        """Run one step now with ``threads`` torch threads, resuming it if it was interrupted (the caller holds the
        pipeline lock)."""
        step, fp = self._step(name), self._fingerprints()[name]
        self._run_step(step, fp, self._state(step, fp), fresh=fresh, threads=threads)

    def _state(self, step: Step, fp: Fingerprint) -> StepState:
        return step_state(self._dir(step), fp, accept_code_changes=self.accept_code_changes)

    def _run_step(self, step: Step, fp: Fingerprint, state: StepState, *, fresh: bool, threads: int) -> None:
        step_dir = self._dir(step)
        resume = step.resumable and not fresh and state.status == "partial" and self._started_as(step_dir, fp)
        if not resume and step_dir.exists():
            shutil.rmtree(step_dir)
        step_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(step_dir / FINGERPRINT_FILE, f"{fp.full}\n{fp.spec}".encode())
        inputs = {name: read_manifest(self._dir(self._step(name))) or {} for name in step.inputs}
        self.log(f"step '{step.name}' {'resuming' if resume else 'running'}")
        t0 = time.perf_counter()
        try:
            with torch_threads(threads):
                outputs, info = step.fn(StepContext(step_dir, inputs, self.log, self.progress))
        except KeyboardInterrupt:
            raise PipelineError(self._resume_hint(step, "interrupted")) from None
        except Exception as exc:
            raise PipelineError(self._resume_hint(step, f"failed: {type(exc).__name__}: {exc}")) from exc
        info = {"wall_time_s": time.perf_counter() - t0, "device": self.plan.spec.device, "torch_threads": threads,
                **({"overrides": list(self.overrides)} if self.overrides else {}), **info}
        write_manifest(step_dir, step.name, fp, outputs, info)
        self.log(f"step '{step.name}' done in {info['wall_time_s']:.1f} s")

    def _refuse_a_device_change(self, step: Step) -> None:
        """A step that finished on another device is not trained again (nor its folder removed) unless forced."""
        manifest = read_manifest(self._dir(step))
        ran_on = (manifest or {}).get("info", {}).get("device")
        if step.resumable and ran_on is not None and ran_on != self.plan.spec.device:
            raise UsageError(f"step '{step.name}' finished on {ran_on} ({self._dir(step)}); this run asks for "
                             f"{self.plan.spec.device}: keep it with --device {ran_on}, or train it again with "
                             f"--force {step.name}")

    def _reusable(self, step: Step, fp: Fingerprint) -> Path | None:
        """The folder of the same step, finished with this fingerprint and its outputs intact, in another run under
        the runs folder (another variant or seed of a pipeline shares the steps its overrides leave alone)."""
        if self._dir(step).exists():
            return None
        for other in sorted(self.plan.runs_dir.glob(f"*/{step.dirname}")):
            if other.parent != self.plan.run_root and step_state(other, fp).status == "complete":
                return other  # complete: this fingerprint (the source too) and its outputs verified
        return None

    def _reuse(self, step: Step, fp: Fingerprint) -> None:
        """Make a missing step complete with the manifest of a run that has it (:meth:`_reusable`): its outputs stay
        where that run wrote them, checked by their checksums like this run's own."""
        found = self._reusable(step, fp)
        if found is None:
            return
        manifest = read_manifest(found) or {}
        manifest["info"] = {**manifest.get("info", {}), "reused_from": str(found)}
        self._dir(step).mkdir(parents=True)
        atomic_write_bytes(self._dir(step) / MANIFEST, json.dumps(manifest, indent=2).encode())
        self.log(f"step '{step.name}' reused from {found} (the same fingerprint)")

    def _started_as(self, step_dir: Path, fp: Fingerprint) -> bool:
        """Whether the interrupted step started with this fingerprint (its spec one, with accepted code changes)."""
        try:
            started = (step_dir / FINGERPRINT_FILE).read_text().split("\n")
        except OSError:
            return False
        return started[0] == fp.full or (self.accept_code_changes and fp.spec_matches(started[-1]))

    def _step(self, name: str) -> Step:
        return next(s for s in self.steps if s.name == name)

    @property
    def command(self) -> str:
        """The ``spiral run`` command of this pipeline and its overrides (for resume hints)."""
        return " ".join(["spiral run", str(self.path), *(f"--set {shlex.quote(o)}" for o in self.overrides)])

    def _resume_hint(self, step: Step, what: str) -> str:
        return f"step '{step.name}' {what}\nresume with: {self.command} --from {step.name}"

    def describe(self) -> dict[str, Any]:
        """Machine-readable status."""
        return {"pipeline": self.plan.spec.name, "file": str(self.path), "overrides": list(self.overrides),
                "steps": [s.__dict__ for s in self.status()]}
