"""Race trained policies again with other separation-filter settings, without retraining: the probe behind the
"Separation filter" tables in docs/training.md.

    python examples/separation_probe.py checkpoints/full/spiral.pt 2v2 --runs 512 --seed 3 \
        --filter none --filter 0.25,0.4,1.5
    python examples/separation_probe.py checkpoints/full/1v1/best.pt 1v1 \
        --against checkpoints/full/1v1-noselfplay/best.pt

Each ``--filter`` is ``none`` (no filter, the paper's stack) or ``DISTANCE,HORIZON_S,GAIN``. Prints the self-match
success and mean lap time, or with ``--against`` the win / loss / draw rates of the first policy's team and both
teams' success. Every drone of a race flies with the same filter.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from spiral.config import SeparationCfg, load_track
from spiral.core.checkpoint import FrozenPolicy, load_policy
from spiral.core.scenario import TEAMS
from spiral.eval.evaluate import RaceSet, race_policies
from spiral.eval.metrics import summarize_races


def with_filter(policy: FrozenPolicy, separation: SeparationCfg | None) -> None:
    """Make ``policy``'s evaluation layout fly with ``separation``."""
    policy.meta["env"]["action"]["separation"] = None if separation is None else separation.model_dump()


def parse_filter(text: str) -> SeparationCfg | None:
    if text == "none":
        return None
    distance, horizon, gain = (float(x) for x in text.split(","))
    return SeparationCfg(distance=distance, horizon_s=horizon, gain=gain)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("scenario", choices=["1v1", "2v2"])
    parser.add_argument("--against", type=Path, help="race team A (checkpoint) against this checkpoint")
    parser.add_argument("--track", type=Path, default=Path("tracks/circuit6.yaml"))
    parser.add_argument("--runs", type=int, default=512)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--filter", action="append", dest="filters", default=None,
                        help="none or DISTANCE,HORIZON_S,GAIN (repeatable; default: none and 0.25,0.4,1.5)")
    args = parser.parse_args()
    track = load_track(args.track)
    policy = load_policy(args.checkpoint)
    other = load_policy(args.against) if args.against else None
    for text in args.filters or ["none", "0.25,0.4,1.5"]:
        separation = parse_filter(text)
        for p in (policy, other):
            if p is not None:
                with_filter(p, separation)
        res, winners = race_policies(RaceSet(track, args.scenario, args.runs, args.seed), policy, other)
        if winners is None:
            s = summarize_races(res)
            lap = "–" if s["lap_time_mean"] is None else f"{s['lap_time_mean']:.3f} s"
            print(f"{text:>16}: success {s['success_ratio']:.3f} lap {lap}", flush=True)
        else:
            a, b = TEAMS[args.scenario]
            share = [float((winners == k).float().mean()) for k in (0, 1, -1)]
            print(f"{text:>16}: win {share[0]:.3f} loss {share[1]:.3f} draw {share[2]:.3f} | success "
                  f"{float(res.finished[:, a].float().mean()):.3f} / {float(res.finished[:, b].float().mean()):.3f}",
                  flush=True)


if __name__ == "__main__":
    main()
