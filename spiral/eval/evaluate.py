"""Seeded evaluation races of learned policies and the SE-IBR planner: identical start placements for every method.

A method is a learned checkpoint or the planner (checkpoint ``se-ibr``), under a name. Start placements depend only
on the seed, the scenario and the race count, so every method (and every pairing in cross-play) races from the same
ones. The env is built with a learned policy's layout (observations, action mapping, airframe, simulator); the
planner flies through the same action interface, so when it races a learned policy it uses that policy's layout.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

import torch
from tensordict import TensorDict

from spiral.baselines import PlannerPolicy, opponent_policy, planning_cost, se_ibr_policy
from spiral.config.airframe import AIRFRAMES, AirframeCfg
from spiral.config.env import EVAL_REWARD, ActionCfg, EnvCfg, ObsCfg, SeparationCfg
from spiral.config.sim import SimCfg
from spiral.config.track import TrackSpec
from spiral.core.checkpoint import FrozenPolicy, load_policy
from spiral.core.errors import UsageError
from spiral.core.outcome import race_winner
from spiral.core.policy import OpponentPolicy, Policy
from spiral.core.scenario import SCENARIO_DRONES, TEAMS
from spiral.env.race_env import RaceEnv
from spiral.env.racing import RaceResults, concat_results, run_races
from spiral.env.setting import RaceSetting
from spiral.eval.metrics import first_gate_order, summarize_races

SIDES = ("a", "both")
"""Head-to-head protocols: method on team A's slots only, or every placement raced from both sides."""


def check_sides(sides: str) -> None:
    """Raise ``ValueError`` unless ``sides`` is one of :data:`SIDES`."""
    if sides not in SIDES:
        raise UsageError(f"sides: expected {' or '.join(SIDES)}, got {sides!r}")


SE_IBR = "se-ibr"
"""A method's checkpoint that selects the SE-IBR planner instead of a checkpoint file."""

MethodPolicy = FrozenPolicy | str
"""What a method races, loaded: a learned policy, or :data:`SE_IBR` for the planner (built for each race env)."""


@dataclass(frozen=True)
class RaceSet:
    """Seeded evaluation races: ``runs`` races of ``scenario`` on ``track`` from the start placements of ``seed``,
    the same for every method raced on them."""

    track: TrackSpec
    scenario: str
    runs: int
    seed: int

__all__ = [
    "MIXED_SLOTS",
    "SE_IBR",
    "SIDES",
    "EvalLayout",
    "FlightOverride",
    "MethodPolicy",
    "RaceSet",
    "SlotPolicy",
    "check_sides",
    "cross_play",
    "eval_env_for",
    "evaluate_methods",
    "evaluate_mixed_teams",
    "evaluate_policy",
    "format_eval",
    "load_method",
    "parse_separation",
    "race_device",
    "race_policies",
    "setup_race",
]


def policy_obs(policy: FrozenPolicy) -> ObsCfg:
    """The observation layout ``policy`` was trained with (its checkpoint's ``obs_layout``)."""
    return ObsCfg(**{k: v for k, v in policy.meta["obs_layout"].items() if k != "obs_dim"})


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
        env = EnvCfg(obs=policy_obs(policy), action=ActionCfg(**meta["env"]["action"]), reward=EVAL_REWARD)
        return cls(AirframeCfg(**meta["airframe"]), SimCfg(**meta["sim"]), env, source)

    @classmethod
    def default(cls, *, airframe: AirframeCfg | None = None, sim: SimCfg | None = None) -> EvalLayout:
        """Default env settings (for planner-only races)."""
        return cls(airframe or AIRFRAMES["cf2x"], sim or SimCfg(), EnvCfg(reward=EVAL_REWARD), "defaults")


KEEP = "keep"
"""A :class:`FlightOverride` separation setting that keeps each policy's own."""


@dataclass(frozen=True)
class FlightOverride:
    """Changes to the flight stack the policies were trained with, or to where the races start, for one evaluation
    (zero-shot tests).

    Every drone of the races flies with them, whichever method commands it.
    """

    separation: SeparationCfg | str | None = KEEP
    """A separation filter between policy and PID (``SeparationCfg``), ``None`` for none (the paper's stack), or
    ``"keep"``: the trained layout's own."""
    separation_team: Literal["all", "a", "b"] = "all"
    """Drones the separation filter acts on: every drone, or team A's (the evaluated method's; in cross-play they
    keep it when the sides are swapped) or team B's only."""
    downwash: bool | None = None
    """Switch the simulator's downwash on or off; None keeps the trained setting."""
    starts: Literal["box", "track", "file"] = "box"
    """Where the races start (``EpisodeCfg.eval_starts``): the start box, or off it, as a robustness check."""

    def apply(self, layout: EvalLayout) -> EvalLayout:
        """``layout`` with these changes."""
        env, sim = layout.env, layout.sim
        changes: dict[str, Any] = {} if self.separation == KEEP else {"separation": self.separation}
        if self.separation_team != "all":
            changes["separation_team"] = self.separation_team
        if changes:  # validated again: a one-team setting needs a filter
            action = ActionCfg.model_validate({**env.action.model_dump(), **changes})
            env = env.model_copy(update={"action": action})
        if self.downwash is not None:
            sim = sim.model_copy(update={"downwash": self.downwash})
        if self.starts != "box":
            env = env.with_eval_starts(self.starts)
        return replace(layout, env=env, sim=sim)

    def to_json(self) -> dict[str, Any]:
        """What changes, for evaluation files."""
        out: dict[str, Any] = {}
        if isinstance(self.separation, SeparationCfg) or self.separation is None:
            out["separation"] = None if self.separation is None else self.separation.model_dump()
        if self.separation_team != "all":
            out["separation_team"] = self.separation_team
        if self.downwash is not None:
            out["downwash"] = self.downwash
        if self.starts != "box":
            out["starts"] = self.starts
        return out

    def swapped(self) -> FlightOverride:
        """The same changes for races with the teams' slots swapped: a one-team filter follows its team."""
        other: dict[str, Literal["all", "a", "b"]] = {"all": "all", "a": "b", "b": "a"}
        return replace(self, separation_team=other[self.separation_team])


def parse_separation(text: str) -> SeparationCfg | str | None:
    """``keep``, ``none`` or ``DISTANCE,HORIZON_S,GAIN`` as a :class:`FlightOverride` separation setting."""
    if text in (KEEP, "none"):
        return None if text == "none" else KEEP
    try:
        distance, horizon, gain = (float(x) for x in text.split(","))
    except ValueError:
        raise UsageError(f"--separation: expected keep, none or DISTANCE,HORIZON_S,GAIN, got {text!r}") from None
    return SeparationCfg(distance=distance, horizon_s=horizon, gain=gain)


def race_device(device: str, checkpoints: Iterable[str | Path]) -> str:
    """The device a race of ``checkpoints`` (paths, or ``se-ibr``) runs on: the CPU when SE-IBR flies in it (it plans
    on the host, and on a CUDA env it would copy the race's state there at every plan), else ``device``."""
    return "cpu" if any(str(c).lower() == SE_IBR for c in checkpoints) else device


def load_method(checkpoint: str | Path, *, device: str = "cpu") -> MethodPolicy:
    """What a method races, loaded: the planner for ``se-ibr`` (any case), else the policy of the checkpoint at
    ``checkpoint``."""
    return SE_IBR if str(checkpoint).lower() == SE_IBR else load_policy(Path(checkpoint), device=device)


def eval_env_for(policy: FrozenPolicy, races: RaceSet, *, device: str = "cpu", team_a_only: bool = False) -> RaceEnv:
    """A non-resetting env of ``races`` with the policy's observation/action layout, airframe and simulator settings.

    Start placements depend on the seed and the scenario only, so every method races from the same ones.
    """
    return _race_env(EvalLayout.of_policy(policy), races, device=device, team_a_only=team_a_only)


def _race_env(layout: EvalLayout, races: RaceSet, *, device: str, team_a_only: bool) -> RaceEnv:
    if races.scenario not in TEAMS:
        raise UsageError(f"scenario: expected solo, 1v1 or 2v2, got {races.scenario!r}")
    drones = SCENARIO_DRONES[races.scenario]
    slots = TEAMS[races.scenario][0] if team_a_only else list(range(drones))
    return RaceEnv(RaceSetting(races.track, layout.airframe, layout.sim), layout.env, world_count=races.runs,
                   drones_per_world=drones, learner_slots=slots, device=device, seed=races.seed, training=False)


def setup_race(races: RaceSet, policy: MethodPolicy, opponent: MethodPolicy | None = None, *, device: str = "cpu",
               layout: EvalLayout | None = None, flight: FlightOverride | None = None) -> tuple[RaceEnv, Policy]:
    """A fresh race env and the policy of its learner slots: ``policy`` everywhere, or team A vs ``opponent``.

    The env takes ``policy``'s layout if it is learned, else ``opponent``'s, else ``layout`` (defaults when None),
    changed by ``flight``.
    """
    if opponent is not None and races.scenario == "solo":
        raise UsageError("cross-play needs a 1v1 or 2v2 scenario")
    if isinstance(policy, FrozenPolicy) and isinstance(opponent, FrozenPolicy):
        _check_compatible(policy, opponent, same_inputs=False)
    learned = [p for p in (policy, opponent) if isinstance(p, FrozenPolicy)]
    chosen = EvalLayout.of_policy(learned[0]) if learned else (layout or EvalLayout.default())
    if flight is not None:
        chosen = flight.apply(chosen)
    env = _race_env(chosen, races, device=device, team_a_only=opponent is not None)
    if opponent is not None:
        opp: OpponentPolicy = opponent_policy(env) if isinstance(opponent, str) else opponent
        own = policy_obs(opponent) if isinstance(opponent, FrozenPolicy) else None
        env.set_opponent_policy(opp, obs=own)  # a policy with other inputs reads its own layout
    learner: Policy = se_ibr_policy(env) if isinstance(policy, str) else policy
    return env, learner


def _check_compatible(a: FrozenPolicy, b: FrozenPolicy, *, same_inputs: bool = True) -> None:
    """Two policies can race each other if every drone flies the same action mapping; sharing a team's slots in one
    env (``same_inputs``) also needs the same observation layout, while opposing teams each read their own."""
    if same_inputs and a.meta["obs_layout"] != b.meta["obs_layout"]:
        raise UsageError("mixed teams need policies with the same obs_layout")
    if ActionCfg(**a.meta["env"]["action"]) != ActionCfg(**b.meta["env"]["action"]):  # as read: defaults filled in
        raise UsageError("cross-play needs policies with the same action mapping")


def race_policies(races: RaceSet, policy: MethodPolicy, opponent: MethodPolicy | None = None, *, device: str = "cpu",
                  layout: EvalLayout | None = None, record: bool = False, flight: FlightOverride | None = None,
                  planners: list | None = None) -> tuple[RaceResults, torch.Tensor | None]:
    """Race ``policy`` (self-match) or team ``policy`` against team ``opponent``; winners only in cross-play.

    ``planners``, when given, collects the planner policies that flew (for :func:`~spiral.baselines.planning_cost`).
    """
    env, learner = setup_race(races, policy, opponent, device=device, layout=layout, flight=flight)
    teams = TEAMS[races.scenario]
    res = run_races(env, learner, record=record, teams=teams)
    if planners is not None:
        planners.extend(p for p in (learner, env.opponent_policy) if isinstance(p, PlannerPolicy))
    return res, race_winner(res.finished, res.lap_time, teams) if opponent is not None else None


def evaluate_policy(policy: FrozenPolicy, races: RaceSet, *, device: str = "cpu", record: bool = False) -> RaceResults:
    """Self-match races: every drone of every race runs ``policy``."""
    return race_policies(races, policy, device=device, record=record)[0]


def cross_play(a: MethodPolicy, b: MethodPolicy, races: RaceSet, *, device: str = "cpu",
               layout: EvalLayout | None = None, sides: str = "both", flight: FlightOverride | None = None,
               planners: list | None = None) -> tuple[RaceResults, torch.Tensor]:
    """Team ``a`` against team ``b``: per-drone results and each race's winner (0 = ``a``, 1 = ``b``, −1 = none).

    ``sides="a"``: ``races.runs`` races with ``a`` on team A's slots (the first ones). ``sides="both"``: every
    placement is raced a second time with the slots swapped (``b`` starts where ``a`` started), so neither method
    keeps the luckier half of the start box; the swapped races follow the first ``races.runs``, their drones
    reordered so that ``a``'s are in team A's slots of the results as well.
    """
    check_sides(sides)
    res, winners = race_policies(races, a, b, device=device, layout=layout, flight=flight, planners=planners)
    assert winners is not None
    if sides == "a":
        return res, winners
    swapped, won = race_policies(races, b, a, device=device, layout=layout,
                                 flight=flight.swapped() if flight is not None else None, planners=planners)
    assert won is not None
    team_a, team_b = TEAMS[races.scenario][0], TEAMS[races.scenario][-1]
    back = swapped.permuted([*team_b, *team_a])
    return concat_results([res, back]), torch.cat([winners, torch.where(won >= 0, 1 - won, won)])


def evaluate_methods(races: RaceSet, methods: dict[str, str | Path], *, device: str = "cpu",
                     against: tuple[str, str | Path] | None = None, layout: EvalLayout | None = None,
                     sides: str = "both", flight: FlightOverride | None = None) -> dict[str, Any]:
    """The evaluation JSON of ``spiral eval``: metrics of each method in ``races``.

    ``methods`` maps each method's name to its checkpoint: a checkpoint path or ``se-ibr``. Without ``against``
    every drone of a race runs the method (self-match, as in the paper's tables). With ``against = (name,
    checkpoint)`` the method is team A and ``name`` team B; ``win_rate``, ``loss_rate`` and ``draws`` are added,
    over ``races.runs`` races per side (``sides``, see :func:`cross_play`; ``win_rate_by_side`` splits the win rate
    by where the method started).
    Planner-only races use the layout of the first learned method (else ``layout``, the defaults when None); the
    entry's ``layout`` says which. ``flight`` changes the flight stack of every drone (JSON ``flight``). Where the
    planner flew, ``planning`` is its cost (:func:`~spiral.baselines.planning_cost`: ms per plan per drone).
    """
    device = race_device(device, [*methods.values(), *([against[1]] if against is not None else [])])
    out = _eval_json(races, flight, device)
    check_sides(sides)
    if against is not None:
        out["against"] = {"name": against[0], "checkpoint": str(against[1])}
        out["sides"], out["races"] = sides, races.runs * (2 if sides == "both" else 1)
    policies = {name: load_method(checkpoint, device=device) for name, checkpoint in methods.items()}
    opponent = load_method(against[1], device=device) if against is not None else None
    fallback = _fallback_layout([*policies.items(), *([(against[0], opponent)] if against is not None else [])],
                                layout)
    for name, policy in policies.items():
        entry: dict[str, Any] = {"checkpoint": str(methods[name])}
        planners: list[PlannerPolicy] = []
        if opponent is None:
            res, _ = race_policies(races, policy, device=device, layout=fallback, flight=flight, planners=planners)
            entry.update(summarize_races(res))
        else:
            res, winners = cross_play(policy, opponent, races, device=device, layout=fallback, sides=sides,
                                      flight=flight, planners=planners)
            entry.update(_cross_play_metrics(res, winners, races))
        if isinstance(policy, str) and (opponent is None or isinstance(opponent, str)):
            entry["layout"] = fallback.source
        if planners:
            entry["planning"] = planning_cost(*planners)
        out["methods"][name] = entry
    return out


def _eval_json(races: RaceSet, flight: FlightOverride | None, device: str) -> dict[str, Any]:
    """The head of an evaluation's JSON: what was raced, on which device, and the flight changes, with no method
    yet."""
    out: dict[str, Any] = {"track": races.track.name, "scenario": races.scenario, "laps": races.track.laps,
                           "runs": races.runs, "seed": races.seed, "device": device, "methods": {}}
    if flight is not None and flight.to_json():
        out["flight"] = flight.to_json()
    return out


def _fallback_layout(policies: list[tuple[str, MethodPolicy | None]], layout: EvalLayout | None) -> EvalLayout:
    """The layout of planner-only races: the first learned method's among ``policies`` (method name, policy), else
    ``layout`` (the defaults when None)."""
    learned = [(n, p) for n, p in policies if isinstance(p, FrozenPolicy)]
    if learned:
        return EvalLayout.of_policy(learned[0][1], source=learned[0][0])
    return layout or EvalLayout.default()


def _cross_play_metrics(res: RaceResults, winners: torch.Tensor, races: RaceSet) -> dict[str, Any]:
    """A method's entry in cross-play: its team's metrics, its win, loss and draw rates (also by the side it started
    on), the opponent team's metrics and who led through the first gate."""
    team_a, team_b = TEAMS[races.scenario][0], TEAMS[races.scenario][-1]
    won = (winners == 0).float()
    return {**summarize_races(res, team_a), "win_rate": float(won.mean()),
            "loss_rate": float((winners == 1).float().mean()),
            "draws": float((winners == -1).float().mean()), "opponent": summarize_races(res, team_b),
            "win_rate_by_side": {side: float(part.mean()) for side, part in
                                 zip(("a", "b"), won.split(races.runs), strict=False)},
            "first_gate": first_gate_order(res, winners, (team_a, team_b))}


MIXED_SLOTS: tuple[list[int], list[int]] = ([0, 2], [1, 3])
"""2v2 slots of the first and second method in a mixed-team race: each team has one drone of each."""


class SlotPolicy:
    """Drives every slot of a race env's worlds, each slot with its own policy (rows are world-major)."""

    def __init__(self, policies: list[Policy]) -> None:
        self.policies = policies

    def __call__(self, obs: TensorDict) -> torch.Tensor:
        """Actions of every drone: slot ``s`` of each world from ``policies[s]``."""
        d = len(self.policies)
        slot = torch.arange(obs.batch_size[0], device=obs.device) % d
        actions = torch.zeros(obs.batch_size[0], 4, device=obs.device)
        for s, policy in enumerate(self.policies):
            actions[slot == s] = policy(obs[slot == s])
        return actions


def evaluate_mixed_teams(track: TrackSpec, methods: dict[str, str | Path], *, runs: int, seed: int,
                         device: str = "cpu", flight: FlightOverride | None = None) -> dict[str, Any]:
    """2v2 races of two learned methods in mixed teams: each team has one drone of each method
    (:data:`MIXED_SLOTS`), so every drone races a stranger as its team mate and as an opponent. Per method, the
    metrics of its drones (no win rate: the teams are alike)."""
    if len(methods) != 2:
        raise UsageError(f"mixed teams need exactly two methods, got {len(methods)}")
    policies = {name: load_method(checkpoint, device=device) for name, checkpoint in methods.items()}
    if any(not isinstance(p, FrozenPolicy) for p in policies.values()):
        raise UsageError("mixed teams are raced by learned policies only")
    a, b = policies.values()
    _check_compatible(a, b)  # type: ignore[arg-type]
    layout = EvalLayout.of_policy(a)  # type: ignore[arg-type]
    if flight is not None:
        layout = flight.apply(layout)
    env = _race_env(layout, RaceSet(track, "2v2", runs, seed), device=device, team_a_only=False)
    res = run_races(env, SlotPolicy([a, b, a, b]), teams=TEAMS["2v2"])  # type: ignore[list-item]
    out: dict[str, Any] = {"track": track.name, "scenario": "2v2", "runs": runs, "seed": seed, "device": device,
                           "mixed": True, "methods": {}}
    if flight is not None and flight.to_json():
        out["flight"] = flight.to_json()
    for (name, checkpoint), slots in zip(methods.items(), MIXED_SLOTS, strict=True):
        out["methods"][name] = {"checkpoint": str(checkpoint), "slots": slots, **summarize_races(res, slots)}
    return out


def _num(x: float | None, digits: int = 2) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def format_eval(result: dict[str, Any]) -> str:
    """A plain-text table of an evaluation result."""
    time_head = "lap [s]" if result.get("laps", 1) == 1 else "race [s]"
    lines = [_eval_title(result),
             f"{'method':<20} {'success':>8} {'95% CI':>15} {'races':>6} {time_head:>14} {'win':>6}  crashes"]
    lines += [_eval_row(name, m) for name, m in result["methods"].items()]
    lines.append("success: drones home; 95% CI with the race as the unit; races: share of races with every counted "
                 "drone home")
    return "\n".join([*lines, *_eval_notes(result["methods"])])


def _eval_title(result: dict[str, Any]) -> str:
    """What was raced: track, scenario, laps, races, seed, the opponent and changes from training."""
    laps = result.get("laps", 1)
    head = (f"{result['track']} {result['scenario']}{f', {laps} laps' if laps > 1 else ''}, {result['runs']} races, "
            f"seed {result['seed']}")
    if "against" in result:
        head += f", against {result['against']['name']}"
        if result.get("sides") == "both":
            head += " (each placement raced from both sides)"
    if "flight" in result:
        head += f", changed from training: {json.dumps(result['flight'])}"
    return head


def _eval_row(name: str, m: dict[str, Any]) -> str:
    """A method's row of the table."""
    lap = f"{m['lap_time_mean']:.2f} ± {m['lap_time_std']:.2f}" if m["lap_time_mean"] is not None else "-"
    lo, hi = m["success_ci95"]
    win = f"{m['win_rate']:.2f}" if "win_rate" in m else "-"
    crashes = ", ".join(f"{k} {v}" for k, v in m["crashes"].items() if v)
    return (f"{name:<20} {m['success_ratio']:>8.2f} {f'[{lo:.2f}, {hi:.2f}]':>15} "
            f"{m['race_success_ratio']:>6.2f} {lap:>14} {win:>6}  {crashes or 'none'}")


def _eval_notes(methods: dict[str, dict[str, Any]]) -> list[str]:
    """Lines under the table for the metrics some methods have: actions beyond range, passes, racing, first gate."""
    lines = []
    beyond = {name: m["action_beyond_range"] for name, m in methods.items() if m.get("action_beyond_range")}
    if beyond:
        lines.append("commanded action beyond the clamped range, share of racing steps (x / y / z / yaw): " + "; ".join(
            f"{name} {' / '.join(f'{v:.2f}' for v in shares.values())}" for name, shares in beyond.items()))
    passes = {name: m["passes"] for name, m in methods.items() if m.get("passes") and "win_rate" in m}
    if passes:
        lines.append("passes in flight per race, made / suffered: " + "; ".join(
            f"{name} {p['made_per_race']:.2f} / {p['suffered_per_race']:.2f}" for name, p in passes.items()))
    racing = {name: m["racing"] for name, m in methods.items() if m.get("racing")}
    if racing:
        lines.append("racing, per race: overtakes / lead changes / won from behind the first gate's leader; first lap, "
                     "flying lap [s]; drone contacts per lap: " + "; ".join(
                         f"{name} {_num(r['overtakes_per_race'])} / {_num(r['lead_changes_per_race'])} / "
                         f"{_num(r['won_from_behind'])}; {_num(r['first_lap'])}, {_num(r['flying_lap'])}; "
                         f"{_num(r['drone_contacts_per_lap'], 3)}" for name, r in racing.items()))
    gates = {name: m["first_gate"] for name, m in methods.items() if m.get("first_gate")}
    if gates:
        lines.append("first through the lap's first gate, share of races; the team first there won: " + "; ".join(
            f"{name} {g['led']:.2f}; " + ("-" if g["leader_won"] is None else f"{g['leader_won']:.2f}")
            for name, g in gates.items()))
    return lines
