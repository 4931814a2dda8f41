"""Seeded race tracks: closed circuits of N gates drawn in the ranges of the shipped Crazyflie-scale tracks, with the
geometric checks that reject what cannot be raced.

A candidate circuit goes once round an ellipse whose size gives the wanted mean gate spacing: each gate at a jittered
angle and radius, at a random height. Every gate faces along the circuit (its normal along the line from the gate
before it to the gate after it), turned by a random yaw within ``yaw_deg`` and a random pitch within ``tilt_deg`` of
that line, and rolled within ``roll_deg``: a gate set at an angle to the line through it is approached on a curve, as
on the shipped tracks. Each offset is the range times ``u ** offset_power`` (``u`` uniform in [0, 1], a random sign):
with the default power 2 most gates sit near their line and a few are set at a steep angle, the shipped tracks' mix
(their gates are turned 12 deg and pitched 10 deg off the line on average, at most 41 and 37 deg). The default ranges
hold every shipped track. The start box sits behind gate 0. A candidate is kept when :func:`track_faults` finds
nothing (and, when given, ``accept`` says yes, e.g. the point-mass reference flies it within the time limit); else the
next candidate of the same random stream is drawn, so a seed always gives the same track.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from pydantic import Field, model_validator

from spiral.config.base import PosFloat, StrictModel
from spiral.config.track import TrackSpec, gate_rotation

__all__ = ["TrackGenCfg", "gate_offsets", "generate_track", "track_faults", "track_yaml"]

START_SIZE = (0.6, 0.6, 0.3)
"""Sides of a generated track's start box [m] (as the shipped tracks')."""


class TrackGenCfg(StrictModel):
    """The ranges a generated track is drawn in and held to."""

    gates: int = Field(default=6, ge=3, le=16, description="Gates in the circuit")
    spacing: tuple[PosFloat, PosFloat] = Field(default=(1.6, 5.2), description="Range of the distance between "
                                               "consecutive gate centres [m]")
    max_turn_deg: float = Field(default=140.0, gt=0, le=180, description="Largest turn of the centreline at a gate "
                                "(between the segment into it and the one out of it) [deg]")
    max_climb_deg: float = Field(default=50.0, ge=0, lt=90, description="Steepest segment [deg]")
    height: tuple[PosFloat, PosFloat] = Field(default=(0.6, 2.2), description="Range of the gate centres' height [m]")
    yaw_deg: float = Field(default=45.0, ge=0, le=60, description="Largest yaw of a gate's passing direction away "
                           "from the line through it (from the gate before it to the gate after it) [deg]")
    tilt_deg: float = Field(default=40.0, ge=0, le=60, description="Largest pitch of a gate's passing direction "
                            "away from the line through it [deg]")
    roll_deg: float = Field(default=45.0, ge=0, le=90, description="Largest roll of a gate's square opening [deg]")
    offset_power: float = Field(default=2.0, ge=1.0, le=4.0, description="How the yaw, pitch and roll offsets spread "
                                "in their ranges: each is the range times u**power, u uniform in [0, 1] (1: uniform; "
                                "2: mean a third of the range, most gates near their line)")
    min_gap: PosFloat = Field(default=1.5, description="Least distance between two gate centres [m]")
    clearance: PosFloat = Field(default=0.4, description="Least distance from a segment's line to the frame of a gate "
                                "it does not join, and from the start box to any frame [m]")
    floor: PosFloat = Field(default=0.2, description="Least height of a frame's lowest corner [m]")
    margin: PosFloat = Field(default=1.0, description="Space between the gates and start box and the arena's walls "
                             "and ceiling [m]")
    opening: PosFloat = Field(default=0.6, description="Inner side of every gate's opening [m]")
    bar: PosFloat = Field(default=0.05, description="Bar thickness of every frame [m]")
    laps: int = Field(default=1, ge=1, description="Laps in a race")
    time_limit_s: PosFloat = Field(default=20.0, description="Time limit of a one-lap race [s]")
    tries: int = Field(default=2000, ge=1, description="Candidates drawn before giving up")

    @model_validator(mode="after")
    def _ordered_ranges(self) -> TrackGenCfg:
        for name in ("spacing", "height"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(f"{name}: the range's low end {lo} is above its high end {hi}")
        return self


def generate_track(cfg: TrackGenCfg, seed: int, *, name: str | None = None,
                   accept: Callable[[TrackSpec], bool] | None = None) -> TrackSpec:
    """The first candidate of ``seed``'s random stream without a fault that ``accept`` (if given) accepts; raises
    ``ValueError`` after ``cfg.tries`` candidates."""
    rng = np.random.default_rng(seed)
    for _ in range(cfg.tries):
        try:
            track = _candidate(cfg, rng, name or f"gen-s{seed}-g{cfg.gates}")
        except ValueError:  # the track spec's own checks (e.g. a start box that touches a frame) refuse it
            continue
        if not track_faults(track, cfg) and (accept is None or accept(track)):
            return track
    raise ValueError(f"no raceable track of {cfg.gates} gates in {cfg.tries} candidates of seed {seed}: widen the "
                     "generator's ranges")


def _candidate(cfg: TrackGenCfg, rng: np.random.Generator, name: str) -> TrackSpec:
    """One circuit drawn from ``rng`` (unchecked)."""
    n = cfg.gates
    radius = n * rng.uniform(*cfg.spacing) / (2.0 * math.pi)
    aspect = rng.uniform(0.6, 1.0)
    angle = 2.0 * math.pi * (np.arange(n) + rng.uniform(-0.3, 0.3, n)) / n * rng.choice([-1.0, 1.0])
    r = radius * rng.uniform(0.75, 1.25, n)
    centers = np.stack([r * np.cos(angle), aspect * r * np.sin(angle), rng.uniform(*cfg.height, n)], axis=1)
    through = np.roll(centers, -1, axis=0) - np.roll(centers, 1, axis=0)
    through /= np.linalg.norm(through, axis=1, keepdims=True)
    pitch = -np.degrees(np.arcsin(through[:, 2])) + _offsets(cfg.tilt_deg, cfg.offset_power, rng, n)
    roll = _offsets(cfg.roll_deg, cfg.offset_power, rng, n)
    yaw = np.degrees(np.arctan2(through[:, 1], through[:, 0])) + _offsets(cfg.yaw_deg, cfg.offset_power, rng, n)
    gates = [{"position": _rounded(c), "rpy_deg": _rounded((rl, p, y), 1)}
             for c, rl, p, y in zip(centers, roll, pitch, yaw, strict=True)]
    forward = gate_rotation((0.0, float(pitch[0]), float(yaw[0])))[:, 0]
    start = centers[0] - 1.2 * forward * np.sign(forward @ through[0])  # behind gate 0, on its passing line
    start[2] = max(start[2], cfg.floor + START_SIZE[2])
    lo, hi = _extent(centers, start, cfg)
    return TrackSpec.model_validate({
        "kind": "track", "name": name, "opening": cfg.opening, "bar": cfg.bar, "gates": gates,
        "start": {"center": _rounded(start), "size": START_SIZE, "yaw_deg": round(float(yaw[0]), 1)},
        "bounds": {"min": _rounded((*(lo[:2] - cfg.margin), 0.0)), "max": _rounded(hi + cfg.margin)},
        "laps": cfg.laps, "time_limit_s": cfg.time_limit_s * cfg.laps,
    })


def _offsets(limit: float, power: float, rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` angles within ``±limit`` [deg], each ``limit · u**power`` with a random sign."""
    return limit * rng.uniform(0.0, 1.0, n) ** power * rng.choice([-1.0, 1.0], n)


def _rounded(values: object, digits: int = 3) -> list[float]:
    return [round(float(v), digits) for v in np.asarray(values)]


def _extent(centers: np.ndarray, start: np.ndarray, cfg: TrackGenCfg) -> tuple[np.ndarray, np.ndarray]:
    """Corners of the box around every gate's frame (at its largest) and the start box."""
    reach = (cfg.opening + 2.0 * cfg.bar) / math.sqrt(2.0)  # a frame's half-diagonal, whatever its rotation
    lo = np.minimum(centers.min(axis=0) - reach, start - np.array(START_SIZE) / 2)
    hi = np.maximum(centers.max(axis=0) + reach, start + np.array(START_SIZE) / 2)
    return lo, hi


def track_faults(track: TrackSpec, cfg: TrackGenCfg) -> list[str]:
    """What makes ``track`` fall outside ``cfg``'s ranges or unraceable: spacing, turns, climbs, gates too close to
    each other or to a segment they do not join, frames too low or outside the arena, a start box too close to a
    frame. Empty when it is fine."""
    c = track.gate_centers()
    seg = np.roll(c, -1, axis=0) - c
    length = np.linalg.norm(seg, axis=1)
    unit = seg / length[:, None]
    turn = np.degrees(np.arccos(np.clip((np.roll(unit, 1, axis=0) * unit).sum(axis=1), -1.0, 1.0)))
    climb = np.degrees(np.abs(np.arcsin(np.clip(unit[:, 2], -1.0, 1.0))))
    faults = [f"segment {i}->{(i + 1) % len(c)}: {v:.2f} m apart, outside {cfg.spacing}"
              for i, v in enumerate(length) if not cfg.spacing[0] <= v <= cfg.spacing[1]]
    faults += [f"gate {i}: turn of {v:.0f} deg" for i, v in enumerate(turn) if v > cfg.max_turn_deg]
    faults += [f"segment {i}: climb of {v:.0f} deg" for i, v in enumerate(climb) if v > cfg.max_climb_deg]
    yaw, pitch = gate_offsets(track)
    faults += [f"gate {i}: yawed {abs(v):.0f} deg off the line through it" for i, v in enumerate(yaw)
               if abs(v) > cfg.yaw_deg + 0.5]
    faults += [f"gate {i}: pitched {abs(v):.0f} deg off the line through it" for i, v in enumerate(pitch)
               if abs(v) > cfg.tilt_deg + 0.5]
    faults += [f"gate {i}: rolled {abs(g.rpy_deg[0]):.0f} deg" for i, g in enumerate(track.gates)
               if abs(g.rpy_deg[0]) > cfg.roll_deg + 0.5]
    gaps = np.linalg.norm(c[:, None] - c[None], axis=-1)
    np.fill_diagonal(gaps, np.inf)
    faults += [f"gates {i} and {j}: {gaps[i, j]:.2f} m apart" for i, j in zip(*np.nonzero(gaps < cfg.min_gap),
                                                                                 strict=True) if i < j]
    faults += _frame_faults(track, cfg)
    return faults


def gate_offsets(track: TrackSpec) -> tuple[np.ndarray, np.ndarray]:
    """Each gate's passing direction against the line through it (from the gate before it to the gate after it):
    the difference of their headings and of their elevations [deg], each ``(G,)``."""
    c = track.gate_centers()
    through = np.roll(c, -1, axis=0) - np.roll(c, 1, axis=0)
    through /= np.linalg.norm(through, axis=1, keepdims=True)
    passing = track.gate_forward()
    yaw = np.degrees(np.arctan2(passing[:, 1], passing[:, 0]) - np.arctan2(through[:, 1], through[:, 0]))
    pitch = np.degrees(np.arcsin(np.clip(passing[:, 2], -1, 1)) - np.arcsin(np.clip(through[:, 2], -1, 1)))
    return (yaw + 180.0) % 360.0 - 180.0, pitch


def _frame_faults(track: TrackSpec, cfg: TrackGenCfg) -> list[str]:
    """Frames near a segment they do not join, below the floor or outside the arena; a start box near a frame."""
    c, faults = track.gate_centers(), []
    lo, hi = np.asarray(track.bounds.min), np.asarray(track.bounds.max)
    start = np.asarray(track.start.center)
    for g in range(len(c)):
        corners = track.gate_corners(g)
        reach = track.gate_size(g) / 2.0 + cfg.clearance
        if corners[:, 2].min() < cfg.floor or (corners < lo).any() or (corners > hi).any():
            faults.append(f"gate {g}: frame below {cfg.floor} m or outside the arena")
        for i in range(len(c)):
            if g not in (i, (i + 1) % len(c)) and _segment_distance(c[g], c[i], c[(i + 1) % len(c)]) < reach:
                faults.append(f"gate {g}: within {cfg.clearance} m of segment {i}->{(i + 1) % len(c)}")
        if np.linalg.norm(start - c[g]) < reach + max(track.start.size) / 2 and g != 0:
            faults.append(f"start box: within {cfg.clearance} m of gate {g}")
    return faults


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Distance from point ``p`` to the segment from ``a`` to ``b``."""
    ab = b - a
    u = float(np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0))
    return float(np.linalg.norm(p - (a + u * ab)))


def track_yaml(track: TrackSpec, header: str) -> str:
    """``track`` as a track file in the shipped tracks' layout (one line per gate), after the comment ``header``."""
    def vec(values: object) -> str:
        return "[" + ", ".join(f"{float(v):g}" for v in values) + "]"  # type: ignore[union-attr]

    lines = [f"# {line}" for line in header.splitlines()]
    lines += ["kind: track", f"name: {track.name}", f"opening: {track.opening:g}", f"bar: {track.bar:g}", "gates:"]
    lines += [f"  - {{position: {vec(g.position)}, rpy_deg: {vec(g.rpy_deg)}}}" for g in track.gates]
    start = track.start
    lines += ["start:", f"  center: {vec(start.center)}", f"  size: {vec(start.size)}",
              f"  min_separation: {start.min_separation:g}", f"  yaw_deg: {start.yaw_deg:g}",
              "bounds:", f"  min: {vec(track.bounds.min)}", f"  max: {vec(track.bounds.max)}",
              f"laps: {track.laps}", f"time_limit_s: {track.time_limit_s:g}"]
    return "\n".join(lines) + "\n"
