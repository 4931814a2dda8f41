"""Scenarios (what a race is: solo, 1v1 or 2v2): how many drones race, which slots form each team, and which slots
a training stage's learner drives.

Plain Python (no torch), so the specs in :mod:`spiral.config` can use it.
"""

from __future__ import annotations

from typing import Literal

__all__ = ["SCENARIO_DRONES", "TEAMS", "Scenario", "learner_slots", "race_teams", "team_slots"]

Scenario = Literal["solo", "1v1", "2v2"]
"""A scenario: what a race is."""

SCENARIO_DRONES: dict[str, int] = {"solo": 1, "1v1": 2, "2v2": 4}
"""Drones per world of each scenario."""


def race_teams(drones: int) -> list[int]:
    """Race team of each slot of a world of ``drones`` drones, whoever drives it: the first half of the slots against
    the second (1v1: 0 against 1; 2v2: 0, 1 against 2, 3; a solo drone is team 0)."""
    return [slot // max(1, drones // 2) for slot in range(drones)]


def team_slots(drones: int) -> list[list[int]]:
    """The slots of each race team (:func:`race_teams`), team by team."""
    team = race_teams(drones)
    return [[slot for slot in range(drones) if team[slot] == t] for t in range(max(team) + 1)] if drones else []


TEAMS: dict[str, list[list[int]]] = {scenario: team_slots(drones) for scenario, drones in SCENARIO_DRONES.items()}
"""Drone slots of each team in each scenario: ``{"solo": [[0]], "1v1": [[0], [1]], "2v2": [[0, 1], [2, 3]]}``."""


def learner_slots(scenario: str) -> list[int]:
    """Drone slots of team A in ``scenario``: the ones a training stage's learner drives (the rest are opponents)."""
    return list(TEAMS[scenario][0])
