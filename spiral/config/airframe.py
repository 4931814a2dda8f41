"""Airframes as data: mass, geometry, motor constants, drag and controller gains."""

from __future__ import annotations

import math
from typing import Any

from pydantic import Field, ValidationError

from spiral.config.base import NonNegFloat, PosFloat, StrictModel, Vec3
from spiral.config.errors import SpecError, format_validation_error

__all__ = ["AIRFRAMES", "AirframeCfg", "AirframeSel", "PIDCfg", "resolve_airframe"]

GRAVITY = 9.81
"""Gravitational acceleration [m/s²]."""


class PIDCfg(StrictModel):
    """Cascaded controller gains in SI units (accelerations per metre, angular accelerations per radian)."""

    pos_p: Vec3 = Field(default=(8.0, 8.0, 10.0), description="Position gain [1/s²]")
    pos_i: Vec3 = Field(default=(1.0, 1.0, 2.0), description="Position integral gain [1/s³]")
    pos_d: Vec3 = Field(default=(4.0, 4.0, 5.0), description="Velocity gain [1/s]")
    pos_i_limit: PosFloat = Field(default=0.5, description="Clip of each position-integral component [m·s]")
    att_p: Vec3 = Field(default=(400.0, 400.0, 100.0), description="Attitude gain [1/s²]")
    att_d: Vec3 = Field(default=(40.0, 40.0, 20.0), description="Body-rate gain [1/s]")
    max_tilt_deg: float = Field(default=60.0, gt=0, lt=90, description="Largest tilt the position loop commands [deg]")
    max_accel: PosFloat = Field(default=25.0, description="Clip of the commanded acceleration norm [m/s²]")


class AirframeCfg(StrictModel):
    """A quadrotor airframe in X configuration."""

    name: str = Field(description="Airframe name")
    mass: PosFloat = Field(description="Mass [kg]")
    arm: PosFloat = Field(description="Distance from the centre of mass to each motor [m]")
    kf: PosFloat = Field(description="Thrust coefficient f = kf·rpm² [N/rpm²]")
    km: PosFloat = Field(description="Yaw-torque coefficient τ = km·rpm² [N·m/rpm²]")
    inertia: Vec3 = Field(description="Principal moments Ixx, Iyy, Izz [kg·m²]")
    thrust_to_weight: float = Field(gt=1.0, description="Total maximum thrust over weight")
    radius: PosFloat = Field(description="Collision sphere radius [m]")
    drag: tuple[NonNegFloat, NonNegFloat, NonNegFloat] = Field(description="Linear drag K_d, diagonal [N·s/m]")
    motor_tau: PosFloat = Field(default=0.02, description="Motor time constant when motor lag is on [s]")
    prop_radius: PosFloat = Field(default=0.0231, description="Propeller radius, for ground effect [m]")
    pid: PIDCfg = Field(default_factory=PIDCfg)

    @property
    def max_rpm(self) -> float:
        """Motor speed at which the four motors give thrust_to_weight·m·g [rpm]."""
        return math.sqrt(self.thrust_to_weight * self.mass * GRAVITY / (4.0 * self.kf))

    @property
    def hover_rpm(self) -> float:
        """Motor speed at which the four motors carry the weight [rpm]."""
        return math.sqrt(self.mass * GRAVITY / (4.0 * self.kf))


AIRFRAMES: dict[str, AirframeCfg] = {
    "cf2x": AirframeCfg(
        name="cf2x",
        mass=0.027,
        arm=0.0397,
        kf=3.16e-10,
        km=7.94e-12,
        inertia=(1.4e-5, 1.4e-5, 2.17e-5),
        thrust_to_weight=2.25,
        radius=0.06,
        drag=(0.01, 0.01, 0.02),
    ),
}
"""Built-in airframes by name. ``cf2x``: Crazyflie 2.x (Bitcraze data; drag is an estimate)."""


class AirframeSel(StrictModel):
    """Choice of a built-in airframe with optional field-by-field overrides."""

    name: str = Field(default="cf2x", description="Built-in airframe name")
    overrides: dict[str, Any] = Field(default_factory=dict, description="Fields of AirframeCfg to replace")


def resolve_airframe(sel: AirframeSel | str, *, source: str = "airframe") -> AirframeCfg:
    """Return the airframe ``sel`` names with its overrides applied and validated."""
    sel = AirframeSel(name=sel) if isinstance(sel, str) else sel
    if sel.name not in AIRFRAMES:
        raise SpecError([f"{source}: airframe.name: unknown airframe {sel.name!r} (known: {', '.join(AIRFRAMES)})"])
    data = AIRFRAMES[sel.name].model_dump()
    for key, value in sel.overrides.items():
        data[key] = {**data[key], **value} if isinstance(value, dict) and isinstance(data.get(key), dict) else value
    try:
        return AirframeCfg.model_validate(data)
    except ValidationError as exc:
        raise SpecError(format_validation_error(source, exc, prefix="airframe.overrides")) from exc
