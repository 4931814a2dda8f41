"""The paper's reward terms, one function each; ``compute_rewards`` weights them from ``RewardCfg``."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from spiral.config.env import RewardCfg

__all__ = ["REWARD_TERMS", "StepOutcome", "compute_rewards"]


@dataclass
class StepOutcome:
    """What happened to every drone during one control step (all tensors shaped (N,) or (N, 3))."""

    dist_before: torch.Tensor
    """Distance to the step's target gate before the step [m]."""
    dist_after: torch.Tensor
    """Distance to the same gate after the step [m]."""
    gates_passed: torch.Tensor
    """Gates passed in order during the step."""
    crashed_now: torch.Tensor
    """Whether the drone collided during the step (bool)."""
    heading: torch.Tensor
    """Body x axis in the world frame (N, 3)."""
    to_gate: torch.Tensor
    """Vector from the drone to its next gate (N, 3) [m]."""
    lap_time: torch.Tensor
    """Duration of the lap a drone completed during the step, else 0 [s]; over one lap the race time."""
    nearest: torch.Tensor | None = None
    """Distance to the nearest other drone still racing after the step, inf when there is none [m]."""
    race_result: torch.Tensor | None = None
    """+1 / −1 for the winning / losing team's drones at the step their race is decided, else 0."""
    closing: torch.Tensor | None = None
    """How fast the drone closes in on its nearest racing drone, by its share and nearness after the step
    (:func:`~spiral.env.events.closing_in`) [m/s]."""


def _reward_progress(o: StepOutcome, cfg: RewardCfg) -> torch.Tensor:
    """Δd: metres gained towards the gate targeted at the start of the step (the centreline's next vertex)."""
    return o.dist_before - o.dist_after


def _reward_gate(o: StepOutcome, cfg: RewardCfg) -> torch.Tensor:
    """G_t: gates passed in order during the step."""
    return o.gates_passed.float()


def _reward_collision(o: StepOutcome, cfg: RewardCfg) -> torch.Tensor:
    """−1 once, at the step of the collision (the weight is the paper's C)."""
    return -o.crashed_now.float()


def _reward_alignment(o: StepOutcome, cfg: RewardCfg) -> torch.Tensor:
    """max(0, cos θ − cos θ_th), θ the angle between the heading and the direction to the next gate."""
    cos = torch.nn.functional.cosine_similarity(o.heading, o.to_gate, dim=-1)
    return (cos - math.cos(math.radians(cfg.alignment_threshold_deg))).clamp(min=0.0)


def _reward_proximity(o: StepOutcome, cfg: RewardCfg) -> torch.Tensor:
    """−max(0, 1 − d / d_safe) per step, d the distance to the nearest other racing drone (not in the paper)."""
    if o.nearest is None:
        return torch.zeros_like(o.dist_before)
    return -(1.0 - o.nearest / cfg.proximity_distance).clamp(min=0.0)


def _reward_closing(o: StepOutcome, cfg: RewardCfg) -> torch.Tensor:
    """−(closing rate · share · nearness) per step: closing in on the nearest drone, charged to the drone that
    flies into the other (not in the paper)."""
    if o.closing is None:
        return torch.zeros_like(o.dist_before)
    return -o.closing


def _reward_lap(o: StepOutcome, cfg: RewardCfg) -> torch.Tensor:
    """100 / T_lap at the step a lap is completed, for each lap of the race (T_lap that lap's time)."""
    done = o.lap_time > 0
    return torch.where(done, 100.0 / o.lap_time.clamp(min=1e-3), torch.zeros_like(o.lap_time))


def _reward_win(o: StepOutcome, cfg: RewardCfg) -> torch.Tensor:
    """+1 to the team whose drone completes the lap first, −1 to the other team's racing drones (not in the paper)."""
    if o.race_result is None:
        return torch.zeros_like(o.dist_before)
    return o.race_result


REWARD_TERMS = {
    "progress": _reward_progress,
    "gate": _reward_gate,
    "collision": _reward_collision,
    "alignment": _reward_alignment,
    "proximity": _reward_proximity,
    "closing": _reward_closing,
    "lap": _reward_lap,
    "win": _reward_win,
}
"""Reward term functions by the name of their weight in ``RewardCfg``."""


def compute_rewards(outcome: StepOutcome, cfg: RewardCfg) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Total reward per drone and each weighted term. The terms are added one at a time in :data:`REWARD_TERMS` order,
    so a term at weight 0 adds an exact zero and leaves every total bit for bit (one reduction over a stack of the
    terms would group its additions by the stack's size)."""
    terms = {name: fn(outcome, cfg) * getattr(cfg, name) for name, fn in REWARD_TERMS.items()}
    names = iter(REWARD_TERMS)
    total = terms[next(names)]
    for name in names:
        total = total + terms[name]
    return total, terms
