"""Several draws of one pipeline variant: the pipeline run once per seed with the same settings, each in its own run
folder, and one table of their headline figures (:mod:`spiral.eval.headline`) with the spread across seeds."""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from spiral.config import load_pipeline
from spiral.core.errors import UsageError
from spiral.pipeline.manifest import read_manifest
from spiral.pipeline.parallel import Launcher
from spiral.pipeline.runner import PipelineRunner

__all__ = ["SweepDraw", "parse_seeds", "run_sweep", "sweep_markdown"]


@dataclass(frozen=True)
class SweepDraw:
    """One seed's run of a sweep."""

    seed: int
    run_root: Path
    headline: dict[str, float | None]
    """The run's headline figures; empty when the pipeline has no report step."""


def parse_seeds(text: str) -> list[int]:
    """``0,1,2`` as seeds; a seed that is not an integer, or one given twice, is refused naming ``--seeds``."""
    try:
        seeds = [int(part) for part in text.split(",")]
    except ValueError:
        raise UsageError(f"--seeds: expected comma-separated integers, got {text!r}") from None
    if len(set(seeds)) != len(seeds):
        raise UsageError(f"--seeds: a seed given twice in {text!r}")
    return seeds


def run_sweep(path: Path, seeds: Sequence[int], overrides: Sequence[str] = (), *, jobs: int = 1,
              threads: int = 1, launcher: Launcher | None = None, log: Callable[[str], None] = print,
              **runner_options: Any) -> Path:
    """Run the pipeline at ``path`` with ``overrides`` once per seed (``seed=S`` added; complete steps are skipped,
    as by ``spiral run``), then write ``summary.json`` and ``summary.md`` into ``<runs_dir>/sweeps/<variant>``.
    Returns the markdown's path. ``jobs`` and ``threads`` are :meth:`PipelineRunner.run`'s; ``runner_options``
    (``runs_dir``, ``checkpoints_dir``, ``device``) go to each draw's :class:`PipelineRunner`.

    The draws run one after another, or, with a ``launcher`` (a cluster's), all at once, each scheduling its steps
    onto it (log lines then start with the seed)."""
    if any(o.split("=", 1)[0].strip() == "seed" for o in overrides):
        raise UsageError("--set seed=...: a sweep sets the seed of each draw; give the seeds with --seeds")
    together = launcher is not None and len(seeds) > 1
    runners = [PipelineRunner(path, log=_prefixed(log, f"[seed {seed}] ") if together else log,
                              overrides=(*overrides, f"seed={seed}"), **runner_options) for seed in seeds]
    for seed, runner in zip(seeds, runners, strict=True):
        log(f"sweep: seed {seed} in {runner.plan.run_root}")
    if together:
        with ThreadPoolExecutor(len(runners)) as pool:
            for future in [pool.submit(r.run, jobs=jobs, threads=threads, launcher=launcher) for r in runners]:
                future.result()
    else:
        for runner in runners:
            runner.run(jobs=jobs, threads=threads, launcher=launcher)
    draws = [SweepDraw(seed, r.plan.run_root, _headline(r.plan.run_root))
             for seed, r in zip(seeds, runners, strict=True)]
    name = load_pipeline(path, overrides)[0].name
    out = runners[0].plan.runs_dir / "sweeps" / name
    out.mkdir(parents=True, exist_ok=True)
    summary = {"pipeline": str(path), "overrides": list(overrides),
               "draws": [{"seed": d.seed, "run": str(d.run_root), "headline": d.headline} for d in draws]}
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    (out / "summary.md").write_text(sweep_markdown(name, draws, overrides))
    return out / "summary.md"


def _prefixed(log: Callable[[str], None], prefix: str) -> Callable[[str], None]:
    return lambda line: log(prefix + line)


def _headline(run_root: Path) -> dict[str, float | None]:
    """The headline figures the run's report step declared (none without a report step)."""
    report = run_root / "report"
    if not (report / "manifest.json").exists():
        return {}
    outputs = read_manifest(report)["outputs"]
    return json.loads(Path(outputs["headline"]["path"]).read_text()) if "headline" in outputs else {}


def sweep_markdown(name: str, draws: Sequence[SweepDraw], overrides: Sequence[str] = ()) -> str:
    """One row per headline figure: each seed's value, their mean and their spread (largest minus smallest), over
    the seeds that have it."""
    lines = [f"# Sweep `{name}`", "",
             f"Settings: {', '.join(f'`{o}`' for o in overrides) or 'the pipeline as written'}; "
             f"seeds {', '.join(str(d.seed) for d in draws)}. Run folders: "
             + ", ".join(f"`{d.run_root}`" for d in draws) + ".", "",
             "| figure | " + " | ".join(f"seed {d.seed}" for d in draws) + " | mean | spread |",
             "|---|" + "---:|" * (len(draws) + 2)]
    for figure in sorted({key for d in draws for key in d.headline}):
        values = [d.headline.get(figure) for d in draws]
        known = [v for v in values if v is not None and math.isfinite(v)]
        mean = sum(known) / len(known) if known else None
        spread = max(known) - min(known) if len(known) > 1 else None
        lines.append(f"| {figure} | " + " | ".join(_cell(v) for v in [*values, mean, spread]) + " |")
    return "\n".join(lines) + "\n"


def _cell(value: float | None) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{value:.3f}"
