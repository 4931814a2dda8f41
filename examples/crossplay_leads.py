"""Who leads and who wins when two policies race each other: the analysis behind "Pool opponents instead of mirror
races in the 1v1 stage" in docs/training.md.

    python examples/crossplay_leads.py checkpoints/full/1v1/best.pt checkpoints/full/1v1-noselfplay/best.pt 1v1 \
        --runs 512 --seed 3 --passage 3

Prints the win / loss / draw rates of team A (the first checkpoint), then for each team: how many races it led at
gate passage ``--passage`` (counted from 0; its first drone through first), how many of those it lost and by which
crashes of its own drones (collision kind and the gate passages completed before it), and all its crashes.
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import torch

from spiral.config import load_track
from spiral.core.scenario import TEAMS
from spiral.env import RaceResults
from spiral.eval.evaluate import RaceSet, race_policies
from spiral.sim import COLLISION_KINDS
from spiral.train import load_policy

KIND_NAMES = {bit: name for name, bit in COLLISION_KINDS.items()}


def first_through(res: RaceResults, slots: list[int], passage: int) -> torch.Tensor:
    """Race time at which the team's first drone completed gate passage ``passage`` (inf if none did), shape (W,)."""
    t = res.split_time[:, slots, passage]
    return torch.where(t > 0, t, torch.inf).amin(dim=1)


def crash_counts(res: RaceResults, slots: list[int], worlds: torch.Tensor) -> Counter:
    """(collision kind, gate passages completed) of the crashed drones of ``slots`` in the bool mask ``worlds``."""
    crashed = res.crashed[:, slots] & worlds[:, None]
    kinds = res.crash_kind[:, slots][crashed].tolist()
    gates = res.gates_passed[:, slots][crashed].tolist()
    return Counter((KIND_NAMES.get(int(k), str(k)), int(g)) for k, g in zip(kinds, gates, strict=True))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("a", type=Path, help="team A's checkpoint")
    parser.add_argument("b", type=Path, help="team B's checkpoint")
    parser.add_argument("scenario", choices=["1v1", "2v2"])
    parser.add_argument("--track", default="tracks/circuit6.yaml")
    parser.add_argument("--runs", type=int, default=512)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--passage", type=int, default=3, help="gate passage at which the leader is read")
    args = parser.parse_args()

    res, winner = race_policies(RaceSet(load_track(args.track), args.scenario, args.runs, args.seed),
                                load_policy(args.a), load_policy(args.b))
    if not 0 <= args.passage < res.split_time.shape[-1]:
        parser.error(f"--passage: the lap has gate passages 0..{res.split_time.shape[-1] - 1}")
    print("A: win {:.3f} loss {:.3f} draw {:.3f}".format(*((winner == k).float().mean().item() for k in (0, 1, -1))))
    teams = dict(zip("AB", TEAMS[args.scenario], strict=True))
    times = {name: first_through(res, slots, args.passage) for name, slots in teams.items()}
    for index, (name, slots) in enumerate(teams.items()):
        other = times["B" if name == "A" else "A"]
        leads = torch.isfinite(times[name]) & (times[name] < other)
        lost = leads & (winner != index)
        lost_by_crash = lost & res.crashed[:, slots].any(dim=1)
        print(f"{name}: leads at passage {args.passage} in {int(leads.sum())}, loses {int(lost.sum())} of them, "
              f"{int(lost_by_crash.sum())} with a crash of its own: {dict(crash_counts(res, slots, lost_by_crash))}")
        everything = crash_counts(res, slots, torch.ones_like(leads))
        print(f"{name}: {sum(everything.values())} crashes of {res.present[:, slots].sum().item()} drones: "
              f"{dict(everything.most_common())}")


if __name__ == "__main__":
    main()
