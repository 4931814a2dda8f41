"""The opponents' actions in a self-play stage's rollout: ``PoolOpponents`` as spiral runs it against the
per-member masked forward it replaced (a bool mask of each member's rows, the TensorDict indexed by it, rsl-rl's
actor on the result), timed in one process on the same pool, worlds and observations, and checked to give the same
actions to the bit.

Run from the repository root with spiral's interpreter, on an otherwise idle machine:

    python benchmarks/pool_opponents.py --pool checkpoints/full/pool --worlds 358 --per-world 1 --repeats 5

The defaults are the 1v1 part of ``pipelines/full.yaml``'s SPIRAL 1v1 stage (358 of its 512 worlds, one opponent each,
60% of the worlds racing the learner's copy; the offsets and blind episodes, which both implementations apply alike,
are left out); ``--per-world 2`` with ``--worlds 154`` is its 2v2 part. Each repeat draws the opponents anew and times
both implementations in turn over ``--calls`` calls; the best per call is printed.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from pathlib import Path

import torch
from tensordict import TensorDict

from spiral.core.checkpoint import load_policy
from spiral.selfplay.matchmaking import Matchmaker
from spiral.selfplay.opponents import OpponentDraws, PoolOpponents


@torch.no_grad()
def masked_reference(opponents: PoolOpponents, obs: TensorDict) -> torch.Tensor:
    """The opponents' actions as each member's masked forward computes them (before any offset, pace or blindness,
    which both implementations apply alike)."""
    member_of_row = opponents.assignment.repeat_interleave(opponents.per_world)
    mirror_row = opponents.mirror.repeat_interleave(opponents.per_world)
    actions = torch.zeros(obs.batch_size[0], 4)
    if mirror_row.any():
        actions[mirror_row] = opponents.live(obs[mirror_row])
    for m in torch.unique(member_of_row[~mirror_row]).tolist():
        rows = (member_of_row == m) & ~mirror_row
        actions[rows] = opponents.policies[m].actor(obs[rows])
    return actions


def best_per_call(fn: Callable[[TensorDict], torch.Tensor], obs: TensorDict, calls: int) -> float:
    t0 = time.perf_counter()
    for _ in range(calls):
        fn(obs)
    return (time.perf_counter() - t0) / calls


def run(pool: Path, *, worlds: int, per_world: int, repeats: int, calls: int, members: int | None = None,
        seed: int = 0) -> dict:
    """Seconds per call of both implementations (every repeat), and whether their actions agree to the bit."""
    policies = [load_policy(p) for p in sorted(pool.glob("*.pt"))][:members]
    if not policies:
        raise SystemExit(f"--pool: no checkpoint in {pool}")
    dim = policies[0].obs_layout["obs_dim"]
    opponents = PoolOpponents(policies, Matchmaker(len(policies), latest=len(policies) - 1, p_latest=0.0,
                                                   mode="uniform"),
                              world_count=worlds, per_world=per_world, generator=torch.Generator().manual_seed(seed),
                              draws=OpponentDraws(p_self=0.6))
    opponents.live = policies[-1]
    rows = worlds * per_world
    gen = torch.Generator().manual_seed(seed + 1)
    times: dict[str, list[float]] = {"spiral": [], "masked": []}
    same = True
    for _ in range(repeats):
        opponents.reset(torch.ones(worlds, dtype=torch.bool))
        x = torch.randn(rows, dim, generator=gen)
        obs = TensorDict({"policy": x, "critic": x}, batch_size=[rows])
        same &= torch.equal(opponents(obs), masked_reference(opponents, obs))
        times["spiral"].append(best_per_call(opponents, obs, calls))
        times["masked"].append(best_per_call(lambda o: masked_reference(opponents, o), obs, calls))
    return {"pool": str(pool), "members": len(policies), "worlds": worlds, "per_world": per_world,
            "torch_threads": torch.get_num_threads(), "calls": calls, "seconds_per_call": times, "same_actions": same}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pool", type=Path, default=Path("checkpoints/full/pool"))
    ap.add_argument("--members", type=int, default=None, help="the pool's first N members only")
    ap.add_argument("--worlds", type=int, default=358)
    ap.add_argument("--per-world", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--calls", type=int, default=50)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    r = run(args.pool, worlds=args.worlds, per_world=args.per_world, repeats=args.repeats, calls=args.calls,
            members=args.members)
    spiral, masked = (min(r["seconds_per_call"][k]) for k in ("spiral", "masked"))
    print(f"{r['members']} members, {r['worlds']} worlds x {r['per_world']} opponents, {r['torch_threads']} torch "
          f"threads: spiral {1e3 * spiral:.2f} ms per call, masked forward {1e3 * masked:.2f} ms "
          f"({masked / spiral:.2f}x); same actions: {r['same_actions']}")
    if args.json:
        args.json.write_text(json.dumps(r, indent=1))


if __name__ == "__main__":
    main()
