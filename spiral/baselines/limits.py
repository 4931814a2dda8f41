"""What the airframe and its flight stack let a plan ask for: thrust, tilt, drag and the action's reach.

The cascaded PID (``spiral.sim.pid``) turns a target position ``p*`` into the net acceleration

    a = K_p∘(p* − p) + K_i∘I − K_d∘v                                  (drag is compensated inside the PID)

by commanding the thrust acceleration ``f = a + g·ẑ + c∘v`` (``c`` = drag / mass), which it limits to the tilt cone
``‖f_xy‖ ≤ tan θ·f_z``, the floor ``f_z ≥ 0.3·g`` and ``‖f‖ ≤ max_accel``; the motors then give at most
``TWR·g``. A plan is flyable through this stack when its thrust acceleration stays in that set and its PID target
stays where the action can put it (relative mode: within ``pos_scale`` of the drone on every axis). The closed forms
below summarise the set; the planner itself uses the exact cones and rows (:mod:`spiral.baselines.best_response`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from spiral.config.airframe import AirframeCfg
from spiral.config.env import ActionCfg

__all__ = ["PID_THRUST_FLOOR", "FlightLimits", "flight_limits"]

PID_THRUST_FLOOR = 0.3
"""Smallest vertical thrust acceleration the position loop commands, in g (``desired_acceleration`` in
``spiral/sim/pid.py``)."""


@dataclass(frozen=True)
class FlightLimits:
    """Limits of an airframe flown through the PID and the env's action; all in SI units."""

    gravity: float
    """Gravitational acceleration g [m/s²]."""
    thrust: float
    """Largest thrust acceleration f_max = min(TWR·g, pid.max_accel) [m/s²]."""
    tilt_deg: float
    """Largest tilt of the commanded thrust from the vertical [deg]."""
    drag_per_mass: tuple[float, float, float]
    """Linear drag over mass c = K_drag / m, per axis [1/s]."""
    kp: tuple[float, float, float]
    """PID position gain K_p [1/s²]."""
    kd: tuple[float, float, float]
    """PID velocity gain K_d [1/s]."""
    reach: float | None
    """Largest target offset on each axis in relative action mode [m]; None in absolute mode (the arena box)."""
    attitude_lag: float
    """Lag of the thrust direction behind a steadily turning command, 2ζ/ω_n = K_ω/K_R of the roll/pitch loop (the
    slower of the two) [s]."""

    @property
    def level_accel(self) -> float:
        """Largest horizontal acceleration at constant height and rest: min(g·tan θ, √(f_max² − g²)) [m/s²]."""
        g = self.gravity
        return min(g * math.tan(math.radians(self.tilt_deg)), math.sqrt(max(self.thrust**2 - g * g, 0.0)))

    @property
    def up_accel(self) -> float:
        """Largest upward acceleration from rest: f_max − g [m/s²]."""
        return self.thrust - self.gravity

    @property
    def down_accel(self) -> float:
        """Largest downward acceleration from rest: (1 − floor)·g, the PID's thrust floor [m/s²]."""
        return (1.0 - PID_THRUST_FLOOR) * self.gravity

    @property
    def terminal_speed(self) -> float:
        """Level speed at which drag uses up the largest horizontal thrust: level_accel / c_xy [m/s] (inf: no drag)."""
        c = max(self.drag_per_mass[0], self.drag_per_mass[1])
        return self.level_accel / c if c > 0 else math.inf

    @property
    def climb_speed(self) -> float:
        """Vertical speed at which drag uses up the thrust above weight: (f_max − g) / c_z [m/s] (inf: no drag)."""
        c = self.drag_per_mass[2]
        return self.up_accel / c if c > 0 else math.inf

    @property
    def action_speed(self) -> tuple[float, float, float] | None:
        """Fastest steady speed per axis whose PID target fits in the action: K_p·reach / K_d [m/s] (relative)."""
        if self.reach is None:
            return None
        kp, kd = np.asarray(self.kp), np.asarray(self.kd)
        return tuple(float(v) for v in kp * self.reach / kd)

    def to_json(self) -> dict[str, object]:
        """The limits and the closed forms derived from them."""
        return {"gravity": self.gravity, "thrust": self.thrust, "tilt_deg": self.tilt_deg,
                "drag_per_mass": list(self.drag_per_mass), "kp": list(self.kp), "kd": list(self.kd),
                "reach": self.reach, "attitude_lag": self.attitude_lag, "level_accel": self.level_accel,
                "up_accel": self.up_accel, "down_accel": self.down_accel, "terminal_speed": self.terminal_speed,
                "climb_speed": self.climb_speed,
                "action_speed": None if self.action_speed is None else list(self.action_speed)}


def flight_limits(airframe: AirframeCfg, action: ActionCfg, *, gravity: float = 9.81) -> FlightLimits:
    """The limits of ``airframe`` (thrust-to-weight, drag, PID gains and caps) flown through ``action``."""
    pid = airframe.pid
    return FlightLimits(
        gravity=gravity, thrust=min(airframe.thrust_to_weight * gravity, pid.max_accel), tilt_deg=pid.max_tilt_deg,
        drag_per_mass=tuple(float(d) / airframe.mass for d in airframe.drag),
        kp=tuple(float(k) for k in pid.pos_p), kd=tuple(float(k) for k in pid.pos_d),
        reach=action.pos_scale if action.mode == "relative" else None,
        attitude_lag=max(pid.att_d[0] / pid.att_p[0], pid.att_d[1] / pid.att_p[1]))
