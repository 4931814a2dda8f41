"""Race track spec: gates, start region, arena bounds."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, model_validator

from spiral.config.base import PosFloat, StrictModel, Vec3

__all__ = ["BoundsCfg", "GateSpec", "StartCfg", "TrackSpec", "gate_rotation"]


def gate_rotation(rpy_deg: Vec3) -> np.ndarray:
    """Rotation matrix R = Rz(yaw)·Ry(pitch)·Rx(roll) of a gate, angles in degrees."""
    r, p, y = np.deg2rad(rpy_deg)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


class GateSpec(StrictModel):
    """One square gate. Its opening lies in the local y-z plane; the local x axis is its normal."""

    position: Vec3 = Field(description="Centre of the opening [m]")
    rpy_deg: Vec3 = Field(default=(0.0, 0.0, 0.0), description="Roll, pitch, yaw of the frame [deg]")
    direction: Literal[1, -1] | None = Field(
        default=None, description="Passing direction along the normal; inferred from the gate order when absent"
    )
    opening: PosFloat | None = Field(default=None, description="Override of the track's opening [m]")
    bar: PosFloat | None = Field(default=None, description="Override of the track's bar thickness [m]")


class StartCfg(StrictModel):
    """Axis-aligned box in which drones are placed at the start of a race."""

    center: Vec3 = Field(description="Box centre [m]")
    size: tuple[PosFloat, PosFloat, PosFloat] = Field(description="Box side lengths [m]")
    min_separation: PosFloat = Field(default=0.3, description="Minimum distance between start positions [m]")
    yaw_deg: float = Field(default=0.0, description="Initial heading of the drones [deg]")


class BoundsCfg(StrictModel):
    """Axis-aligned arena; leaving it is a collision."""

    min: Vec3 = Field(description="Lower corner [m]")
    max: Vec3 = Field(description="Upper corner [m]")

    @model_validator(mode="after")
    def _ordered(self) -> BoundsCfg:
        if any(lo >= hi for lo, hi in zip(self.min, self.max, strict=True)):
            raise ValueError("bounds.min must be below bounds.max on every axis")
        return self


class TrackSpec(StrictModel):
    """A gated race track (``kind: track``)."""

    kind: Literal["track"]
    name: str = Field(min_length=1, description="Track name")
    gates: list[GateSpec] = Field(min_length=2, description="Gates in racing order")
    opening: PosFloat = Field(default=0.6, description="Inner side of the square opening [m]")
    bar: PosFloat = Field(default=0.05, description="Bar thickness of the frame [m]")
    start: StartCfg
    bounds: BoundsCfg
    laps: Annotated[int, Field(ge=1)] = Field(default=1, description="Laps in a race")
    time_limit_s: PosFloat = Field(default=20.0, description="Race time limit [s]")

    def with_laps(self, laps: int) -> TrackSpec:
        """This track raced over ``laps`` laps, its time limit scaled by as many laps (the limit is the race's)."""
        if laps < 1:
            raise ValueError(f"laps: expected at least 1, got {laps}")
        if laps == self.laps:
            return self
        return self.model_copy(update={"laps": laps, "time_limit_s": self.time_limit_s * laps / self.laps})

    def gate_opening(self, i: int) -> float:
        """Opening of gate ``i`` after its override [m]."""
        return self.gates[i].opening or self.opening

    def gate_bar(self, i: int) -> float:
        """Bar thickness of gate ``i`` after its override [m]."""
        return self.gates[i].bar or self.bar

    def gate_size(self, i: int) -> float:
        """Outer side of gate ``i``'s frame [m]."""
        return self.gate_opening(i) + 2.0 * self.gate_bar(i)

    def gate_centers(self) -> np.ndarray:
        """Gate centres, shape ``(G, 3)`` [m]."""
        return np.array([g.position for g in self.gates], dtype=np.float64)

    def gate_rotations(self) -> np.ndarray:
        """Gate rotation matrices, shape ``(G, 3, 3)``; columns are the local x (normal), y and z axes."""
        return np.stack([gate_rotation(g.rpy_deg) for g in self.gates])

    def gate_directions(self) -> np.ndarray:
        """Passing sign of each gate along its normal: given, or sign of n·(c[i+1] − c[i−1])."""
        c = self.gate_centers()
        n = self.gate_rotations()[:, :, 0]
        inferred = np.sign(np.einsum("gi,gi->g", n, np.roll(c, -1, axis=0) - np.roll(c, 1, axis=0)))
        given = [g.direction for g in self.gates]
        return np.array([d if d is not None else (s if s != 0 else 1.0) for d, s in zip(given, inferred, strict=True)])

    def gate_forward(self) -> np.ndarray:
        """Unit passing direction of each gate (normal times direction), shape ``(G, 3)``."""
        return self.gate_rotations()[:, :, 0] * self.gate_directions()[:, None]

    def gate_corners(self, i: int) -> np.ndarray:
        """The four outer corners of gate ``i``'s frame, shape ``(4, 3)`` [m]."""
        rot = gate_rotation(self.gates[i].rpy_deg)
        h = self.gate_size(i) / 2.0
        local = np.array([[0.0, sy * h, sz * h] for sy in (-1, 1) for sz in (-1, 1)])
        return np.asarray(self.gates[i].position) + local @ rot.T

    def centreline_points(self) -> np.ndarray:
        """Closed polyline through the gate centres in racing order, shape ``(G + 1, 3)``; last row = first [m]."""
        c = self.gate_centers()
        return np.concatenate([c, c[:1]], axis=0)

    def centreline_length(self) -> float:
        """Length of the closed centreline polyline (one lap through the gate centres) [m]."""
        return float(np.linalg.norm(np.diff(self.centreline_points(), axis=0), axis=1).sum())

    def summary(self) -> dict[str, Any]:
        """JSON-ready description of the track: gate count, centreline length, bounds, start and every gate.

        Gates are numbered from 0, as in error messages (``gates.0.position``). Each gate lists its passing
        direction (``+1``/``-1`` along its normal), whether that was inferred, and the resulting unit vector.
        """
        forward, signs = self.gate_forward(), self.gate_directions()
        gates = [
            {
                "index": i,
                "position": list(g.position),
                "rpy_deg": list(g.rpy_deg),
                "direction": int(signs[i]),
                "direction_inferred": g.direction is None,
                "forward": [round(float(v), 6) + 0.0 for v in forward[i]],  # + 0.0 turns -0.0 into 0.0
                "opening": self.gate_opening(i),
                "outer_size": self.gate_size(i),
            }
            for i, g in enumerate(self.gates)
        ]
        return {
            "name": self.name,
            "gate_count": len(self.gates),
            "centreline_length_m": self.centreline_length(),
            "bounds": {"min": list(self.bounds.min), "max": list(self.bounds.max)},
            "start": {"center": list(self.start.center), "size": list(self.start.size)},
            "laps": self.laps,
            "time_limit_s": self.time_limit_s,
            "gates": gates,
        }

    @model_validator(mode="after")
    def _geometry(self) -> TrackSpec:
        lo, hi = np.asarray(self.bounds.min), np.asarray(self.bounds.max)
        for i in range(len(self.gates)):
            corners = self.gate_corners(i)
            if (corners < lo).any() or (corners > hi).any():
                raise ValueError(f"gates.{i}.position: gate frame leaves the arena bounds")
        s_lo = np.asarray(self.start.center) - np.asarray(self.start.size) / 2
        s_hi = np.asarray(self.start.center) + np.asarray(self.start.size) / 2
        if (s_lo < lo).any() or (s_hi > hi).any():
            raise ValueError("start: start box leaves the arena bounds")
        c = self.gate_centers()
        for i in range(len(c)):
            for j in range(i + 1, len(c)):
                if np.linalg.norm(c[i] - c[j]) < max(self.gate_size(i), self.gate_size(j)):
                    raise ValueError(f"gates.{j}.position: closer to gates.{i} than the gate size")
            corners = self.gate_corners(i)
            if (corners.max(0) > s_lo).all() and (corners.min(0) < s_hi).all():
                raise ValueError(f"start: start box intersects gates.{i}")
        return self
