"""Simulator settings: rates, control mode and optional aerodynamic terms."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from spiral.config.base import PosFloat, PosInt, StrictModel

__all__ = ["SimCfg"]


class SimCfg(StrictModel):
    """How the simulator steps. The control rate must divide the physics rate, so simulated time stays exact."""

    physics_hz: PosInt = Field(default=240, description="Physics and PID rate [Hz]")
    ctrl_hz: PosInt = Field(default=48, description="Policy (control step) rate [Hz]")
    control_mode: Literal["pid", "rpm"] = Field(default="pid", description="What a command sets")
    gravity: PosFloat = Field(default=9.81, description="Gravitational acceleration [m/s²]")
    ground_effect: bool = Field(default=False, description="Extra thrust near the ground")
    downwash: bool = Field(default=False, description="Downward force under other drones")
    motor_lag: bool = Field(default=False, description="First-order lag of motor speed")
    freeze_crashed: bool = Field(default=True, description="Crashed drones stop moving (racing); else fly on")

    @property
    def substeps(self) -> int:
        """Physics substeps in one control step."""
        return self.physics_hz // self.ctrl_hz

    @property
    def dt(self) -> float:
        """Physics step [s]."""
        return 1.0 / self.physics_hz

    @model_validator(mode="after")
    def _integer_ratio(self) -> SimCfg:
        if self.physics_hz % self.ctrl_hz:
            raise ValueError(f"ctrl_hz: {self.ctrl_hz} does not divide physics_hz {self.physics_hz} (e.g. 48 at 240)")
        return self
