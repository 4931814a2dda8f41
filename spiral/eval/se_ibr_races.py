"""Command line of the seeded SE-IBR races (:mod:`spiral.baselines.races`): self-matches and duels, summarised.

Run ``python -m spiral.eval.se_ibr_races --help``; ``docs/se_ibr.md`` reports what it prints.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any

import torch

from spiral.baselines.races import duel_statistics, head_to_head, self_match
from spiral.baselines.se_ibr import planning_cost
from spiral.config import load_track
from spiral.core.scenario import SCENARIO_DRONES
from spiral.eval.metrics import summarize_races

__all__ = ["main"]


def main(argv: list[str] | None = None) -> None:
    """Command line: ``python -m spiral.eval.se_ibr_races {solo,1v1,2v2,duel} --track tracks/circuit6.yaml``."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("scenario", choices=["solo", "1v1", "2v2", "duel"])
    ap.add_argument("--track", type=Path, default=Path("tracks/circuit6.yaml"))
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cfg", type=json.loads, default={}, help="SEIBRCfg overrides as JSON (learner/self-match)")
    ap.add_argument("--opponent-cfg", type=json.loads, default={"alpha": 0.0}, help="duel: slot 1's overrides")
    ap.add_argument("--json", type=Path, default=None, help="also write the result here")
    ap.add_argument("--save", type=Path, default=None, help="also torch.save the RaceResults (with trajectories)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    track = load_track(args.track)
    t0, cpu0, load0 = time.perf_counter(), time.process_time(), os.getloadavg()[0]
    out: dict[str, Any] = {"track": track.name, "scenario": args.scenario, "runs": args.runs, "seed": args.seed,
                           "cfg": args.cfg}
    if args.scenario == "duel":
        res, pol, opp = head_to_head(track, learner=args.cfg, opponent=args.opponent_cfg, runs=args.runs,
                                     seed=args.seed)
        out.update(opponent_cfg=args.opponent_cfg, slot0=summarize_races(res, [0]), slot1=summarize_races(res, [1]),
                   duel=duel_statistics(track, res), timing=pol.planner.timing(), opponent_timing=opp.planner.timing(),
                   planning=planning_cost(pol, opp))
    else:
        drones = SCENARIO_DRONES[args.scenario]
        res, pol = self_match(track, drones, runs=args.runs, seed=args.seed, **args.cfg)
        out.update(summary=summarize_races(res), timing=pol.planner.timing(), planning=planning_cost(pol))
        if drones == 2:
            out["duel"] = duel_statistics(track, res)
    out["wall_s"] = time.perf_counter() - t0
    out["cpu_s"] = time.process_time() - cpu0
    out["load_avg_1min"] = {"start": load0, "end": os.getloadavg()[0]}
    if args.save is not None:
        torch.save(res, args.save)
    text = json.dumps(out, indent=1)
    print(text)
    if args.json is not None:
        args.json.write_text(text + "\n")


if __name__ == "__main__":
    main()
