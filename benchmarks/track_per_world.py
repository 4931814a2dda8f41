"""What a track per world costs the simulator: one batch on one shared track against the same batch with each world
on a track of its own.

Run from the repository root with spiral's interpreter:

    OMP_NUM_THREADS=1 python benchmarks/track_per_world.py --worlds 1024 --drones 2 --repeats 5 --json out.json

Three worlds of the same size, stepped with the same random targets and timed as ``spiral bench sim`` times a world
(``spiral.sim.bench.draw_inputs`` and ``time_warp``: targets redrawn every 10 control steps, crash flags cleared each
step):

- ``shared``: every world races circuit6;
- ``copies``: eight copies of circuit6, world ``w`` on copy ``w % 8``: the same gates, so the difference to
  ``shared`` is what the per-world lookup costs;
- ``shipped``: the shipped tracks, world ``w`` on track ``w % 4``: a real mix (4 to 8 gates a track, each world's own
  bounds).

The three are timed in turn in every repeat, so that load from other processes hits them alike; printed and written
are the best wall time of each and the ratios to ``shared``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import warp as wp

from spiral.config import SimCfg, load_track
from spiral.config.airframe import AIRFRAMES
from spiral.sim import World
from spiral.sim.bench import draw_inputs, time_warp

TRACKS = Path(__file__).resolve().parents[1] / "tracks"


def make_world(tracks: list, worlds: int, drones: int) -> tuple[World, list[wp.array]]:
    """A world of ``worlds`` × ``drones`` with world ``w`` on ``tracks[w % len(tracks)]``, and its target sets (the
    same for every variant: drawn in the first track's arena, seed 0)."""
    world = World(tracks, AIRFRAMES["cf2x"], SimCfg(), world_count=worlds, drones_per_world=drones)
    world.set_world_tracks(np.arange(worlds) % len(tracks))
    start, yaw, targets = draw_inputs(tracks[0], worlds * drones, 8, 0)
    world.reset_all(start, yaw)
    return world, [wp.array(t, dtype=wp.vec4, device=world.device) for t in targets]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", type=int, default=1024)
    parser.add_argument("--drones", type=int, default=2)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    circuit6 = load_track(TRACKS / "circuit6.yaml")
    variants = {"shared": [circuit6], "copies": [circuit6] * 8,
                "shipped": [load_track(p) for p in sorted(TRACKS.glob("*.yaml"))]}
    built = {name: make_world(tracks, args.worlds, args.drones) for name, tracks in variants.items()}
    best = dict.fromkeys(built, float("inf"))
    for world, targets in built.values():
        time_warp(world, targets, 5, 0)  # warm-up
    for r in range(args.repeats):
        for name, (world, targets) in built.items():
            best[name] = min(best[name], time_warp(world, targets, args.steps, 5 + r * args.steps)[0])
    n = args.worlds * args.drones
    result = {"worlds": args.worlds, "drones": args.drones, "steps": args.steps, "repeats": args.repeats,
              **{f"{name}_drone_ctrl_steps_per_s": round(n * args.steps / t) for name, t in best.items()},
              **{f"{name}_time_vs_shared": round(t / best["shared"], 3) for name, t in best.items()
                 if name != "shared"}}
    print(json.dumps(result, indent=1))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
