"""Report sections beyond the paper's tables: the learned methods under the opt-in separation filter, the final
policy of each method in every scenario, racing strangers, and downwash they never trained with."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from spiral.config.env import SeparationCfg
from spiral.core.scenario import SCENARIO_DRONES
from spiral.eval.evaluate import SE_IBR, FlightOverride
from spiral.eval.runs import MODE_OF, Evaluations, RowResult, StageRun, final_stage

__all__ = ["ALL_SCENARIOS", "Robustness", "filter_rows", "final_stages", "race_learned", "race_se_ibr",
           "robustness_markdown"]

ALL_SCENARIOS = tuple(SCENARIO_DRONES)
"""Scenarios a final policy is raced in: all of them."""

SHORT_LABELS = {"spiral": "SPIRAL", "noselfplay": "PPO No Selfplay", "se-ibr": "SE-IBR"}
"""Each method's label in these sections, by name."""

OWN_FILTER = "+ separation filter on own drones"
"""Label of the strangers rows whose method flies with the separation filter and its opponent without."""


@dataclass
class Robustness:
    """What the extra sections measured (None where a method or its stage is missing)."""

    every_scenario: dict[str, dict[str, RowResult]] = field(default_factory=dict)
    """Method -> scenario -> self-match of the method's final policy."""
    strangers: dict[str, dict[str, dict[str, Any]]] = field(default_factory=dict)
    """Scenario -> method -> opponent label -> metrics of the method's drones (cross-play entries)."""
    downwash: dict[str, dict[str, RowResult]] = field(default_factory=dict)
    """Scenario -> method -> self-match with downwash on."""
    runs: int = 0
    seed: int = 0
    final_names: dict[str, str] = field(default_factory=dict)
    """Method -> the stage whose best is its final policy."""


def final_stages(stages: list[StageRun]) -> dict[str, StageRun]:
    """Each learned method's final policy: the stage published under a name (``publish_as``), else its last
    stage."""
    trained = {s.name: s for s in stages if s.best.is_file()}
    listed = [(s.name, s.mode, bool(s.spec["stage"].get("publish_as"))) for s in trained.values()]
    names = {method: final_stage(listed, mode) for method, mode in MODE_OF.items()}
    return {method: trained[name] for method, name in names.items() if name is not None}


def filter_rows(ev: Evaluations, separation: SeparationCfg) -> dict[str, list[RowResult]]:
    """Per scenario, the learned methods' self-matches with the separation filter, raced with ``ev``."""
    out = {}
    for scenario in ("1v1", "2v2"):
        out[scenario] = [ev.flown(scenario, method, checkpoint, FlightOverride(separation=separation), "filter")
                         for method, checkpoint in _learned_checkpoints(ev, scenario).items()]
    return out


def race_learned(ev: Evaluations, stages: list[StageRun], separation: SeparationCfg | None = None) -> Robustness:
    """The extra sections' races among learned policies, with ``ev``'s races and seed: each final policy in every
    scenario, downwash, and the learned methods against each other (pairings, mixed teams and, with ``separation``,
    each method with the filter on its own drones only)."""
    out = Robustness(runs=ev.protocol.runs, seed=ev.protocol.seed)
    finals = final_stages(stages)
    out.final_names = {method: stage.name for method, stage in finals.items()}
    for method, stage in finals.items():
        out.every_scenario[method] = {scenario: ev.flown(scenario, method, str(stage.best), FlightOverride(), "final")
                                      for scenario in ALL_SCENARIOS}
    for scenario in ("1v1", "2v2"):
        checkpoints = _learned_checkpoints(ev, scenario)
        out.downwash[scenario] = {method: ev.flown(scenario, method, c, FlightOverride(downwash=True), "downwash")
                                  for method, c in checkpoints.items()}
        out.strangers[scenario] = _strangers(ev, scenario, checkpoints, separation)
    return out


def _learned_checkpoints(ev: Evaluations, scenario: str) -> dict[str, str]:
    """Each learned method's checkpoint in ``scenario``, where its stage has a best policy."""
    return {method: c for method in MODE_OF if (c := ev.checkpoint(scenario, method)) is not None}


def race_se_ibr(rb: Robustness, ev: Evaluations) -> None:
    """Add each learned method's pairing with SE-IBR to ``rb``'s strangers, raced with ``ev``'s races and seed (the
    races of the cross-play tables)."""
    for scenario, rows in rb.strangers.items():
        for method, row in rows.items():
            row[f"{SHORT_LABELS['se-ibr']} ({ev.protocol.runs} races)"] = ev.cross(
                scenario, (method, ev.checkpoint(scenario, method)), ("se-ibr", SE_IBR))


def _strangers(ev: Evaluations, scenario: str, checkpoints: dict[str, str],
               separation: SeparationCfg | None) -> dict[str, dict[str, Any]]:
    """Method -> opponent label -> metrics of the method's drones (``checkpoints``: method -> its checkpoint); each
    pairing is raced once and read from both teams, and with ``separation`` twice more, the filter on one team's
    drones."""
    rows: dict[str, dict[str, Any]] = {m: {"itself": ev.self_match(scenario, m).metrics} for m in checkpoints}
    methods = list(checkpoints)
    for i, a in enumerate(methods):
        for b in methods[i + 1:]:
            entry = ev.cross(scenario, (a, checkpoints[a]), (b, checkpoints[b]))
            rows[a][SHORT_LABELS[b]] = entry
            rows[b][SHORT_LABELS[a]] = _other_side(entry)
            if separation is not None:
                on_a = FlightOverride(separation=separation, separation_team="a")
                for flight, own, other in ((on_a, a, b), (on_a.swapped(), b, a)):
                    filtered = ev.cross(scenario, (a, checkpoints[a]), (b, checkpoints[b]), flight=flight,
                                        variant=f"filter-{flight.separation_team}")
                    rows[own][f"{SHORT_LABELS[other]}, {OWN_FILTER}"] = (filtered if own == a
                                                                         else _other_side(filtered))
            if scenario == "2v2":
                mixed = ev.mixed((a, checkpoints[a]), (b, checkpoints[b]))
                rows[a]["mixed teams"], rows[b]["mixed teams"] = mixed[a], mixed[b]
    return rows


def _other_side(entry: dict[str, Any]) -> dict[str, Any]:
    """A head-to-head entry read from the opponent team: its drones' metrics and its wins and losses."""
    return {**entry["opponent"], "win_rate": entry["loss_rate"], "loss_rate": entry["win_rate"],
            "draws": entry["draws"]}


def robustness_markdown(rb: Robustness, sides: str) -> list[str]:
    """The sections' markdown lines."""
    where = f"{rb.runs} placements of seed {rb.seed}"
    finals = ", ".join(f"{SHORT_LABELS[m]}: stage {n}" for m, n in rb.final_names.items())
    lines = ["## One policy for every scenario", "",
             f"Each method's final policy ({finals}) in self-matches of every scenario, from {where}.", "",
             "| Method | " + " | ".join(ALL_SCENARIOS) + " |", "|---" * (len(ALL_SCENARIOS) + 1) + "|"]
    for method, by_scenario in rb.every_scenario.items():
        lines.append(f"| {SHORT_LABELS[method]} | "
                     + " | ".join(_self_cell(by_scenario[s].metrics) for s in ALL_SCENARIOS) + " |")
    side = "each placement from both sides" if sides == "both" else "on team A"
    lines += ["", "## Racing strangers", "",
              f"Each learned method (its stage's best, as in the tables) racing drones it did not train with, from "
              f"{where} ({side}): success of its drones with its 95% interval, races in which all of its drones "
              "finished, its crashes (gate frames / drone contacts), where the other drone was at its drone contacts "
              "(ahead / beside / behind, along its direction of travel one control step before: docs/evaluation.md), "
              "who flew into whom there (its drone closed in at least twice as fast as the other / neither / the "
              "other did), how many drones of the other team its drones passed in flight per race and how many "
              "passed them, and, against a team, its win / loss / draw. Mixed teams: 2v2 races whose teams each "
              "have one drone of each method."
              + (f" {OWN_FILTER}: the method's drones fly with the opt-in separation filter and the other team's "
                 "without, as a deployment layer would race drones that lack it." if _has_filter_rows(rb) else ""),
              "",
              "| Scenario | Method | Against | Success | Races all home | Crashes gate / drone "
              "| Contacts: other ahead / beside / behind | Contacts: flew in / even / was flown into "
              "| Passes per race: made / suffered | Win / loss / draw |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for scenario, by_method in rb.strangers.items():
        for method, rows in by_method.items():
            for label, m in rows.items():
                lines.append(f"| {scenario} | {SHORT_LABELS[method]} | {label} | {_stranger_cells(m)} |")
    lines += ["", "## Downwash (zero-shot)", "",
              f"Self-matches from {where} with the simulator's downwash on (a force under each drone on the drones "
              "below it; docs/physics.md); no policy trained with it.", "",
              "| Scenario | " + " | ".join(SHORT_LABELS[m] for m in MODE_OF) + " |",
              "|---" * (len(MODE_OF) + 1) + "|"]
    for scenario, by_method in rb.downwash.items():
        lines.append(f"| {scenario} | " + " | ".join(_self_cell(by_method[m].metrics) if m in by_method else "missing"
                                                       for m in MODE_OF) + " |")
    return [*lines, ""]


def _has_filter_rows(rb: Robustness) -> bool:
    return any(OWN_FILTER in label for by_method in rb.strangers.values() for rows in by_method.values()
               for label in rows)


def _self_cell(m: dict[str, Any] | None) -> str:
    if m is None:
        return "missing"
    lo, hi = m["success_ci95"]
    lap = "no finished lap" if m["lap_time_mean"] is None else f"{m['lap_time_mean']:.2f} s"
    return f"{m['success_ratio']:.3f} [{lo:.2f}, {hi:.2f}], {lap}"


def _stranger_cells(m: dict[str, Any] | None) -> str:
    if m is None:
        return "missing | – | – | – | – | – | –"
    lo, hi = m["success_ci95"]
    crashes = m["crashes"]
    where = m.get("contact_bearing")
    bearing = f"{where['ahead']} / {where['beside']} / {where['behind']}" if where else "–"
    fault = m.get("contact_fault")
    into = f"{fault['own']} / {fault['even']} / {fault['other']}" if fault else "–"
    races = f"{m['race_success_ratio']:.3f}" if "race_success_ratio" in m else "–"
    passes = m.get("passes")
    passed = f"{passes['made_per_race']:.2f} / {passes['suffered_per_race']:.2f}" if passes else "–"
    duel = f"{m['win_rate']:.2f} / {m['loss_rate']:.2f} / {m['draws']:.2f}" if "win_rate" in m else "–"
    return (f"{m['success_ratio']:.3f} [{lo:.2f}, {hi:.2f}] | {races} | {crashes['gate']} / {crashes['drone']} | "
            f"{bearing} | {into} | {passed} | {duel}")
