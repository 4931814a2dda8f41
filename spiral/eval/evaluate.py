"""Seeded evaluation races of learned policies: identical start placements for every method."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from spiral.config.airframe import AirframeCfg
from spiral.config.env import ActionCfg, EnvCfg, ObsCfg
from spiral.config.sim import SimCfg
from spiral.config.stage import SCENARIO_DRONES
from spiral.config.track import TrackSpec
from spiral.env.race_env import RaceEnv
from spiral.env.racing import RaceResults, race_winners, run_races
from spiral.eval.metrics import summarize_races
from spiral.train.checkpoint import FrozenPolicy, load_policy

TEAMS: dict[str, list[list[int]]] = {"solo": [[0]], "1v1": [[0], [1]], "2v2": [[0, 1], [2, 3]]}
"""Drone slots of each team in each scenario."""

__all__ = ["cross_play", "eval_env_for", "evaluate_methods", "evaluate_policy", "format_eval"]


def eval_env_for(policy: FrozenPolicy, track: TrackSpec, scenario: str, runs: int, seed: int, *,
                 device: str = "cpu", team_a_only: bool = False) -> RaceEnv:
    """A non-resetting env with the policy's observation/action layout, airframe and simulator settings.

    Start placements depend on ``seed`` and ``scenario`` only, so every method races from the same ones.
    """
    meta = policy.meta
    obs = {k: v for k, v in meta["obs_layout"].items() if k != "obs_dim"}
    cfg = EnvCfg(obs=ObsCfg(**obs), action=ActionCfg(**meta["env"]["action"]))
    drones = SCENARIO_DRONES[scenario]
    slots = TEAMS[scenario][0] if team_a_only else list(range(drones))
    return RaceEnv(track, AirframeCfg(**meta["airframe"]), SimCfg(**meta["sim"]), cfg, world_count=runs,
                   drones_per_world=drones, learner_slots=slots, device=device, seed=seed, auto_reset=False)


def evaluate_policy(policy: FrozenPolicy, track: TrackSpec, scenario: str, runs: int, seed: int, *,
                    device: str = "cpu", record: bool = False) -> RaceResults:
    """Self-match races: every drone of every race runs ``policy``."""
    env = eval_env_for(policy, track, scenario, runs, seed, device=device)
    return run_races(env, policy, record=record)


def cross_play(a: FrozenPolicy, b: FrozenPolicy, track: TrackSpec, scenario: str, runs: int, seed: int, *,
               device: str = "cpu") -> tuple[RaceResults, torch.Tensor]:
    """Team A (``a``) against team B (``b``): per-drone results and each race's winner (0 = A, 1 = B, −1 = none)."""
    if scenario == "solo":
        raise ValueError("cross-play needs a 1v1 or 2v2 scenario")
    for key in ("obs_layout",):
        if a.meta[key] != b.meta[key]:
            raise ValueError(f"cross-play needs policies with the same {key}")
    if a.meta["env"]["action"] != b.meta["env"]["action"]:
        raise ValueError("cross-play needs policies with the same action mapping")
    env = eval_env_for(a, track, scenario, runs, seed, device=device, team_a_only=True)
    env.set_opponent_policy(b)
    res = run_races(env, a)
    return res, race_winners(res, TEAMS[scenario])


def evaluate_methods(track: TrackSpec, methods: dict[str, str | Path], *, scenario: str, runs: int, seed: int,
                     device: str = "cpu", against: tuple[str, str | Path] | None = None) -> dict[str, Any]:
    """The evaluation JSON of ``spiral eval``: metrics of each named checkpoint in ``scenario``.

    Without ``against`` every drone of a race runs the method (self-match, as in the paper's tables). With
    ``against = (name, checkpoint)`` the method is team A and ``name`` team B; ``win_rate`` and ``draws`` are added.
    """
    out: dict[str, Any] = {"track": track.name, "scenario": scenario, "runs": runs, "seed": seed, "methods": {}}
    if against is not None:
        out["against"] = {"name": against[0], "checkpoint": str(against[1])}
    for name, path in methods.items():
        policy = load_policy(Path(path), device=device)
        if against is None:
            res = evaluate_policy(policy, track, scenario, runs, seed, device=device)
            out["methods"][name] = {"checkpoint": str(path), **summarize_races(res)}
            continue
        opponent = load_policy(Path(against[1]), device=device)
        res, winners = cross_play(policy, opponent, track, scenario, runs, seed, device=device)
        team_a, team_b = TEAMS[scenario]
        out["methods"][name] = {
            "checkpoint": str(path), **summarize_races(res, team_a),
            "win_rate": float((winners == 0).float().mean()), "loss_rate": float((winners == 1).float().mean()),
            "draws": float((winners == -1).float().mean()), "opponent": summarize_races(res, team_b),
        }
    return out


def format_eval(result: dict[str, Any]) -> str:
    """A plain-text table of an evaluation result."""
    head = f"{result['track']} {result['scenario']}, {result['runs']} races, seed {result['seed']}"
    if "against" in result:
        head += f", against {result['against']['name']}"
    lines = [head, f"{'method':<20} {'success':>8} {'95% CI':>15} {'lap [s]':>14} {'win':>6}  crashes"]
    for name, m in result["methods"].items():
        lap = f"{m['lap_time_mean']:.2f} ± {m['lap_time_std']:.2f}" if m["lap_time_mean"] is not None else "-"
        lo, hi = m["success_ci95"]
        win = f"{m['win_rate']:.2f}" if "win_rate" in m else "-"
        crashes = ", ".join(f"{k} {v}" for k, v in m["crashes"].items() if v)
        lines.append(f"{name:<20} {m['success_ratio']:>8.2f} {f'[{lo:.2f}, {hi:.2f}]':>15} {lap:>14} {win:>6}  "
                     f"{crashes or 'none'}")
    return "\n".join(lines)
