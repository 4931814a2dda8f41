"""Tables of docs/se_ibr.md from the files benchmarks/se_ibr_races.sh writes.

Usage: ``python benchmarks/se_ibr_table.py [OUT_DIR]`` (default /tmp/se_ibr). Adds the point-mass lap-time reference
of each track (``spiral.eval.bound.lap_time_bound``, the report's reference) and prints Markdown.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import torch

from spiral.baselines.races import duel_statistics, paired_duel
from spiral.config import AIRFRAMES, load_track
from spiral.eval.bound import lap_time_bound

TRACKS = ("circuit6", "oval4", "figure8", "splits3d")


def _load(out: Path, name: str) -> dict[str, Any]:
    return json.loads((out / f"{name}.json").read_text())


def _ci(s: dict[str, Any]) -> str:
    lo, hi = s["success_ci95"]
    return f"{s['success_ratio']:.3f} [{lo:.2f}, {hi:.2f}]"


def _fails(s: dict[str, Any]) -> str:
    return ", ".join(f"{k} {v}" for k, v in s["crashes"].items() if v) or "none"


def _cost(d: dict[str, Any]) -> str:
    p = d["planning"]
    return (f"{p['plan_cpu_ms_median']:.1f} / {p['plan_cpu_ms_p95']:.1f} | "
            f"{p['plan_ms_median']:.1f} / {p['plan_ms_p95']:.1f} | "
            f"{p['world_ms_median']:.1f} / {p['world_ms_p95']:.1f} | {100 * p['soft_fraction']:.1f} % | "
            f"{d['wall_s']:.0f} / {d['cpu_s']:.0f} | {d['load_avg_1min']['start']:.1f}–{d['load_avg_1min']['end']:.1f}")


def solo_table(out: Path) -> list[str]:
    lines = ["| track | races (seed) | success [95 % CI] | lap [s] | reference [s] | lap / reference | failures | "
             "CPU ms/plan/drone median / p95 | wall ms/plan/drone median / p95 | wall ms/world-step median / p95 | "
             "fallback share | wall / CPU [s] | load avg |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    bounds = {t: lap_time_bound(load_track(f"tracks/{t}.yaml"), AIRFRAMES["cf2x"]).lap_time for t in TRACKS}
    names = [("circuit6", "solo_circuit6"), ("circuit6", "solo_circuit6_holdout")]
    names += [(t, f"solo_{t}") for t in TRACKS[1:]]
    for track, name in names:
        d = _load(out, name)
        s = d["summary"]
        lap = s["lap_time_mean"]
        lines.append(f"| {track} | {d['runs']} ({d['seed']}) | {_ci(s)} | {lap:.2f} ± {s['lap_time_std']:.2f} | "
                     f"{bounds[track]:.2f} | {lap / bounds[track]:.2f} | {_fails(s)} | {_cost(d)} |")
    return lines


def self_table(out: Path) -> list[str]:
    lines = ["| scenario | α | drones | success [95 % CI] | lap [s] | failures | CPU ms/plan/drone median / p95 | "
             "wall ms/plan/drone median / p95 | wall ms/world-step median / p95 | fallback share | wall / CPU [s] | "
             "load avg |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name in ("self_1v1_a1", "self_1v1_a0", "self_2v2_a1", "self_2v2_a0"):
        d = _load(out, name)
        s = d["summary"]
        alpha = d["cfg"].get("alpha", 1.0)
        drones = d["runs"] * (2 if d["scenario"] == "1v1" else 4)
        lines.append(f"| {d['scenario']} | {alpha:g} | {drones} | {_ci(s)} | {s['lap_time_mean']:.2f} ± "
                     f"{s['lap_time_std']:.2f} | {_fails(s)} | {_cost(d)} |")
    return lines


def duel_table(out: Path) -> list[str]:
    track = load_track("tracks/circuit6.yaml")
    lines = ["| slot 0 | slot 1 | slot 0 wins | slot 1 wins | lap slot 0 / 1 [s] | success 0 / 1 | "
             "min separation median [m] | close (< 0.35 m) share |", "|---|---|---|---|---|---|---|---|"]
    label = {0.0: "IBR (α = 0)", 1.0: "SE-IBR (α = 1)"}
    res = {}
    for name in ("duel_a0_vs_a0", "duel_a1_vs_a0", "duel_a0_vs_a1"):
        d = _load(out, name)
        res[name] = torch.load(out / f"{name}.pt", weights_only=False)
        st = duel_statistics(track, res[name], close_m=0.35)
        a, b = label[d["cfg"].get("alpha", 1.0)], label[d["opponent_cfg"].get("alpha", 1.0)]
        lines.append(f"| {a} | {b} | {st['a_wins']} | {st['b_wins']} | {st['a_lap_mean']:.2f} / "
                     f"{st['b_lap_mean']:.2f} | {st['a_success']:.2f} / {st['b_success']:.2f} | "
                     f"{st['min_separation_median']:.3f} | {st['close_share']:.2f} |")
    lines += ["", "| SE-IBR in | SE-IBR wins | IBR wins in that slot (control) | winner changed | gained / lost | "
              "SE-IBR lap change [s] | opponent lap change [s] |", "|---|---|---|---|---|---|---|"]
    for slot, name in ((0, "duel_a1_vs_a0"), (1, "duel_a0_vs_a1")):
        p = paired_duel(res[name], res["duel_a0_vs_a0"], slot=slot)
        lines.append(f"| slot {slot} | {p['wins']} | {p['control_wins']} | {p['winner_changed']} | {p['gained']} / "
                     f"{p['lost']} | {p['lap_change']:+.3f} | {p['other_lap_change']:+.3f} |")
    return lines


def main() -> None:
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/se_ibr")
    torch.set_num_threads(1)
    for title, table in (("Solo", solo_table), ("Self-matches (circuit6, 50 races, seed 0)", self_table),
                         ("Duels (circuit6, 1v1, 50 races, seed 0)", duel_table)):
        print(f"\n**{title}**\n")
        print("\n".join(table(out)))


if __name__ == "__main__":
    main()
