"""Seeded evaluation races of learned policies and the SE-IBR planner: identical start placements for every method.

A method is a learned checkpoint or the planner (``se-ibr``). Start placements depend only on the seed, the
scenario and the race count, so every method (and every pairing in cross-play) races from the same ones. The env
is built with a learned policy's layout (observations, action mapping, airframe, simulator); the planner flies
through the same action interface, so when it races a learned policy it uses that policy's layout.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from spiral.baselines import opponent_policy, se_ibr_policy
from spiral.config.airframe import AIRFRAMES, AirframeCfg
from spiral.config.env import ActionCfg, EnvCfg, ObsCfg
from spiral.config.sim import SimCfg
from spiral.config.stage import SCENARIO_DRONES
from spiral.config.track import TrackSpec
from spiral.env.race_env import OpponentPolicy, RaceEnv
from spiral.env.racing import Policy, RaceResults, race_winners, run_races
from spiral.eval.metrics import summarize_races
from spiral.train.checkpoint import FrozenPolicy, load_policy

TEAMS: dict[str, list[list[int]]] = {"solo": [[0]], "1v1": [[0], [1]], "2v2": [[0, 1], [2, 3]]}
"""Drone slots of each team in each scenario."""

SE_IBR = "se-ibr"
"""Method value that selects the SE-IBR planner instead of a checkpoint."""

Agent = FrozenPolicy | str
"""A loaded method: a learned policy or :data:`SE_IBR`."""

__all__ = [
    "SE_IBR",
    "TEAMS",
    "Agent",
    "EvalLayout",
    "cross_play",
    "eval_env_for",
    "evaluate_methods",
    "evaluate_policy",
    "format_eval",
    "load_agent",
    "race_agents",
    "setup_race",
]


@dataclass(frozen=True)
class EvalLayout:
    """What an evaluation env is built from besides the track: airframe, simulator, observation/action layout."""

    airframe: AirframeCfg
    sim: SimCfg
    env: EnvCfg
    source: str = "defaults"
    """Where the layout comes from (a method name, or ``defaults``)."""

    @classmethod
    def of_policy(cls, policy: FrozenPolicy, *, source: str = "policy") -> EvalLayout:
        """The layout ``policy`` was trained with."""
        meta = policy.meta
        obs = {k: v for k, v in meta["obs_layout"].items() if k != "obs_dim"}
        env = EnvCfg(obs=ObsCfg(**obs), action=ActionCfg(**meta["env"]["action"]))
        return cls(AirframeCfg(**meta["airframe"]), SimCfg(**meta["sim"]), env, source)

    @classmethod
    def default(cls, *, airframe: AirframeCfg | None = None, sim: SimCfg | None = None) -> EvalLayout:
        """Default env settings (for planner-only races)."""
        return cls(airframe or AIRFRAMES["cf2x"], sim or SimCfg(), EnvCfg(), "defaults")


def load_agent(spec: str | Path, *, device: str = "cpu") -> Agent:
    """The planner for ``se-ibr`` (any case), else the policy of the checkpoint at ``spec``."""
    return SE_IBR if str(spec).lower() == SE_IBR else load_policy(Path(spec), device=device)


def eval_env_for(policy: FrozenPolicy, track: TrackSpec, scenario: str, runs: int, seed: int, *,
                 device: str = "cpu", team_a_only: bool = False) -> RaceEnv:
    """A non-resetting env with the policy's observation/action layout, airframe and simulator settings.

    Start placements depend on ``seed`` and ``scenario`` only, so every method races from the same ones.
    """
    return _race_env(EvalLayout.of_policy(policy), track, scenario, runs, seed, device=device,
                     team_a_only=team_a_only)


def _race_env(layout: EvalLayout, track: TrackSpec, scenario: str, runs: int, seed: int, *, device: str,
              team_a_only: bool) -> RaceEnv:
    if scenario not in TEAMS:
        raise ValueError(f"scenario: expected solo, 1v1 or 2v2, got {scenario!r}")
    drones = SCENARIO_DRONES[scenario]
    slots = TEAMS[scenario][0] if team_a_only else list(range(drones))
    return RaceEnv(track, layout.airframe, layout.sim, layout.env, world_count=runs, drones_per_world=drones,
                   learner_slots=slots, device=device, seed=seed, auto_reset=False)


def setup_race(track: TrackSpec, scenario: str, runs: int, seed: int, agent: Agent, opponent: Agent | None = None,
               *, device: str = "cpu", layout: EvalLayout | None = None) -> tuple[RaceEnv, Policy]:
    """A fresh race env and the policy of its learner slots: ``agent`` everywhere, or team A vs ``opponent``.

    The env takes ``agent``'s layout if it is learned, else ``opponent``'s, else ``layout`` (defaults when None).
    """
    if opponent is not None and scenario == "solo":
        raise ValueError("cross-play needs a 1v1 or 2v2 scenario")
    if isinstance(agent, FrozenPolicy) and isinstance(opponent, FrozenPolicy):
        _check_compatible(agent, opponent)
    learned = [a for a in (agent, opponent) if isinstance(a, FrozenPolicy)]
    chosen = EvalLayout.of_policy(learned[0]) if learned else (layout or EvalLayout.default())
    env = _race_env(chosen, track, scenario, runs, seed, device=device, team_a_only=opponent is not None)
    if opponent is not None:
        opp: OpponentPolicy = opponent_policy(env) if isinstance(opponent, str) else opponent
        env.set_opponent_policy(opp)
    policy: Policy = se_ibr_policy(env) if isinstance(agent, str) else agent
    return env, policy


def _check_compatible(a: FrozenPolicy, b: FrozenPolicy) -> None:
    if a.meta["obs_layout"] != b.meta["obs_layout"]:
        raise ValueError("cross-play needs policies with the same obs_layout")
    if a.meta["env"]["action"] != b.meta["env"]["action"]:
        raise ValueError("cross-play needs policies with the same action mapping")


def race_agents(track: TrackSpec, scenario: str, runs: int, seed: int, agent: Agent, opponent: Agent | None = None,
                *, device: str = "cpu", layout: EvalLayout | None = None,
                record: bool = False) -> tuple[RaceResults, torch.Tensor | None]:
    """Race ``agent`` (self-match) or team ``agent`` against team ``opponent``; winners only in cross-play."""
    env, policy = setup_race(track, scenario, runs, seed, agent, opponent, device=device, layout=layout)
    res = run_races(env, policy, record=record, teams=TEAMS[scenario])
    return res, race_winners(res, TEAMS[scenario]) if opponent is not None else None


def evaluate_policy(policy: FrozenPolicy, track: TrackSpec, scenario: str, runs: int, seed: int, *,
                    device: str = "cpu", record: bool = False) -> RaceResults:
    """Self-match races: every drone of every race runs ``policy``."""
    return race_agents(track, scenario, runs, seed, policy, device=device, record=record)[0]


def cross_play(a: Agent, b: Agent, track: TrackSpec, scenario: str, runs: int, seed: int, *,
               device: str = "cpu", layout: EvalLayout | None = None) -> tuple[RaceResults, torch.Tensor]:
    """Team A (``a``) against team B (``b``): per-drone results and each race's winner (0 = A, 1 = B, −1 = none)."""
    res, winners = race_agents(track, scenario, runs, seed, a, b, device=device, layout=layout)
    assert winners is not None
    return res, winners


def evaluate_methods(track: TrackSpec, methods: dict[str, str | Path], *, scenario: str, runs: int, seed: int,
                     device: str = "cpu", against: tuple[str, str | Path] | None = None,
                     airframe: AirframeCfg | None = None, sim: SimCfg | None = None) -> dict[str, Any]:
    """The evaluation JSON of ``spiral eval``: metrics of each named method in ``scenario``.

    A method is a checkpoint path or ``se-ibr``. Without ``against`` every drone of a race runs the method
    (self-match, as in the paper's tables). With ``against = (name, checkpoint or se-ibr)`` the method is team A
    and ``name`` team B; ``win_rate``, ``loss_rate`` and ``draws`` are added. Planner-only races use the layout
    of the first learned method (or ``airframe``/``sim`` and default env settings when there is none); the
    entry's ``layout`` says which.
    """
    out: dict[str, Any] = {"track": track.name, "scenario": scenario, "runs": runs, "seed": seed, "methods": {}}
    if against is not None:
        out["against"] = {"name": against[0], "checkpoint": str(against[1])}
    agents = {name: load_agent(path, device=device) for name, path in methods.items()}
    opponent = load_agent(against[1], device=device) if against is not None else None
    pairs = [*agents.items(), *([(against[0], opponent)] if against is not None else [])]
    learned = [(n, a) for n, a in pairs if isinstance(a, FrozenPolicy)]
    fallback = (EvalLayout.of_policy(learned[0][1], source=learned[0][0]) if learned
                else EvalLayout.default(airframe=airframe, sim=sim))
    team_a, team_b = TEAMS[scenario][0], TEAMS[scenario][-1]
    for name, agent in agents.items():
        res, winners = race_agents(track, scenario, runs, seed, agent, opponent, device=device, layout=fallback)
        entry: dict[str, Any] = {"checkpoint": str(methods[name])}
        if winners is None:
            entry.update(summarize_races(res))
        else:
            entry.update({**summarize_races(res, team_a), "win_rate": float((winners == 0).float().mean()),
                          "loss_rate": float((winners == 1).float().mean()),
                          "draws": float((winners == -1).float().mean()), "opponent": summarize_races(res, team_b)})
        if isinstance(agent, str) and (opponent is None or isinstance(opponent, str)):
            entry["layout"] = fallback.source
        out["methods"][name] = entry
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
