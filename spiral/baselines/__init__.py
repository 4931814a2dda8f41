"""Baselines behind the env API: the SE-IBR game-theoretic planner."""

from __future__ import annotations

from spiral.baselines.limits import FlightLimits, flight_limits
from spiral.baselines.se_ibr import (
    PlannerPolicy,
    SEIBRCfg,
    SEIBRPlanner,
    opponent_policy,
    planning_cost,
    se_ibr_policy,
)

__all__ = ["FlightLimits", "PlannerPolicy", "SEIBRCfg", "SEIBRPlanner", "flight_limits", "opponent_policy",
           "planning_cost", "se_ibr_policy"]
