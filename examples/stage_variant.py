"""Train a variant of one pipeline stage from a given policy, then evaluate it: the tool behind the ablations in
docs/training.md.

    python examples/stage_variant.py pipelines/full.yaml 1v1 runs/full/train-solo/best.pt runs/ablate/my-1v1 \
        --set selfplay.p_self=0.8 --set env.reward.proximity=0.1 --set iterations=600

Each ``--set dotted.key=value`` (value parsed as YAML) overrides the stage's spec, which is validated again. A
multi-drone stage copies the pool next to the init checkpoint (if any) into ``OUT/pool``; a frozen (no-self-play)
stage races ``--opponent CKPT`` (in the pipeline the best of its ``selfplay.opponent_from`` stage), else its init.
``--pool-from DIR`` (repeatable) adds every member of another stage's pool folder, e.g. the 1v1 pool of a run with
another seed, as frozen opponents the learner's pool draws from beside its own (its own latest best stays the latest
best; promotion still races the stage's own best). ``--first-opponent CKPT`` makes CKPT the pool's first member, the
one ``selfplay.p_first`` draws, e.g. an exploiter: a no-self-play stage trained against the init policy
(``--opponent``). The 50-race self-match evaluation (seed 0, as in the pipeline's eval step) is printed and written to
``OUT/summary.json``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import yaml

from spiral.config import StageSpec, load_pipeline, resolve_airframe
from spiral.env import RaceSetting
from spiral.eval import RaceSet, evaluate_methods
from spiral.selfplay import StageSources, run_stage
from spiral.selfplay.pool import Pool


def override(spec: dict, dotted: str, value: object) -> None:
    """Set ``spec[a][b]... = value`` for ``dotted = "a.b..."``, creating intermediate tables."""
    *path, last = dotted.split(".")
    for key in path:
        spec = spec.setdefault(key, {})
    spec[last] = value


def add_foreign_members(pool: Pool, sources: list[Path], init: Path) -> None:
    """Copy every member of each ``sources`` pool into ``pool``, the k-th source's tagged ``-fromk`` in their stage
    (a source already copied, on a rerun into the same folder, is skipped). A new pool gets them first and then the
    init policy; either way the pool's own latest best stays its latest best."""
    own = pool.latest_best
    for k, source in enumerate(sources, start=1):
        tag = f"-from{k}"
        if any(m.stage.endswith(tag) for m in pool.members):
            continue
        for m in Pool(source).members:
            pool.add(source / m.file, stage=m.stage + tag, iteration=m.iteration, evaluation=m.evaluation,
                     rating=m.rating)
    keep_latest(pool, own, init)


def put_first(pool: Pool, checkpoint: Path, init: Path) -> None:
    """Make ``checkpoint`` the pool's first member (stage ``first``; a rerun into the same folder finds it there and
    adds nothing). A new pool then gets the init policy; either way the pool's own latest best stays its latest best."""
    if any(m.stage == "first" for m in pool.members):
        return
    own = pool.latest_best
    pool.add(checkpoint, stage="first", iteration=0, evaluation={})
    pool.members.insert(0, pool.members.pop())
    keep_latest(pool, own, init)


def keep_latest(pool: Pool, own: str | None, init: Path) -> None:
    """Restore the pool's latest best ``own`` after other members joined it; a pool that had none gets ``init``."""
    if own is None:
        pool.add(init, stage="init", iteration=0, evaluation={})
    else:
        pool.latest_best = own
        pool.save()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("pipeline", type=Path)
    parser.add_argument("stage")
    parser.add_argument("init", help="checkpoint the stage starts from (its opponents' first best); 'none' for a "
                        "solo stage from scratch")
    parser.add_argument("out", type=Path)
    parser.add_argument("--opponent", type=Path, help="frozen stages: the checkpoint every opponent runs (the "
                        "pipeline's selfplay.opponent_from stage's best); the init checkpoint when absent")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets")
    parser.add_argument("--pool-from", action="append", default=[], type=Path, metavar="DIR",
                        help="another pool folder whose members join the learner's opponents (multi-drone stages)")
    parser.add_argument("--first-opponent", type=Path, metavar="CKPT",
                        help="a checkpoint that becomes the pool's first member, the one selfplay.p_first draws")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()

    spec, track = load_pipeline(args.pipeline)
    stage = next((s for s in spec.stages if s.name == args.stage), None)
    if stage is None:
        parser.error(f"{args.pipeline} has no stage {args.stage!r}")
    raw = stage.model_dump(exclude_unset=True)  # what the pipeline file set: a solo stage sets no selfplay
    for item in args.sets:
        key, sep, value = item.partition("=")
        if not sep:
            parser.error(f"--set {item!r}: expected KEY=VALUE")
        override(raw, key, yaml.safe_load(value))
    stage = StageSpec.model_validate(raw)

    args.out.mkdir(parents=True, exist_ok=True)
    pool = args.out / "pool"
    init = None if args.init == "none" else Path(args.init)
    if init is not None and not pool.exists() and (init.parent / "pool").is_dir():
        shutil.copytree(init.parent / "pool", pool)
    if (args.pool_from or args.first_opponent) and (init is None or stage.scenario == "solo"
                                                    or stage.selfplay.mode != "pool"):
        parser.error("--pool-from and --first-opponent need a self-play stage (selfplay.mode: pool) and an init "
                     "checkpoint")
    if args.pool_from:
        add_foreign_members(Pool(pool), args.pool_from, init)
    if args.first_opponent:
        put_first(Pool(pool), args.first_opponent, init)
    start = time.perf_counter()
    result = run_stage(RaceSetting(track, resolve_airframe(spec.airframe), spec.sim), stage, args.out,
                       sources=StageSources(pool_dir=pool, init_checkpoint=init, opponent_checkpoint=args.opponent),
                       device=args.device, seed=stage.seed if stage.seed is not None else spec.seed, progress=False)
    wall = time.perf_counter() - start
    evaluation = evaluate_methods(RaceSet(track, stage.scenario, 50, 0), {"variant": result.best_path},
                                  device=args.device)
    m = evaluation["methods"]["variant"]
    summary = {"stage": stage.name, "overrides": args.sets, "train_wall_s": round(wall, 1),
               "success_ratio": m["success_ratio"], "lap_time_mean": m["lap_time_mean"], "crashes": m["crashes"]}
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
