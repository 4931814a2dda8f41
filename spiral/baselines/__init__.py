"""Baselines behind the env API: the SE-IBR game-theoretic planner."""

from __future__ import annotations

from spiral.baselines.se_ibr import PlannerPolicy, SEIBRCfg, SEIBRPlanner, opponent_policy, se_ibr_policy

__all__ = ["PlannerPolicy", "SEIBRCfg", "SEIBRPlanner", "opponent_policy", "se_ibr_policy"]
