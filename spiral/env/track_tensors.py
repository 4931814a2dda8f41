"""The geometry of the tracks a race env's worlds fly as tensors on one device, built once per env so that the start
draws of an env step copy nothing from the host.

An env may fly several tracks, a track per world (:class:`~spiral.env.setting.RaceSetting`'s ``tracks``). Per-gate
arrays are padded to the most gates of any track and laid out track-major: gate ``g`` of track ``t`` is row
``t · max_gates + g`` of the flat arrays (:attr:`TrackTensors.flat_centers`), so that a drone's gate is found by
adding its track's first row to its gate index. With one track the arrays are that track's, unpadded.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from spiral.config.track import TrackSpec

__all__ = ["TrackTensors"]


@dataclass(frozen=True)
class TrackTensors:
    """The geometry of ``specs`` that start draws, start checks and observations read, as tensors on one device."""

    specs: tuple[TrackSpec, ...]
    gate_count: torch.Tensor
    """Gates of each track (T,), int64."""
    gate_centers: torch.Tensor
    """Gate centres (T, G, 3), G the most gates of any track; padding rows repeat the track's last gate."""
    gate_rotations: torch.Tensor
    """Gate frames (T, G, 3, 3), columns: normal, y, z."""
    gate_forward: torch.Tensor
    """Unit passing direction of each gate (T, G, 3)."""
    gate_half: torch.Tensor
    """Half side of each gate's opening (T, G)."""
    gate_bar: torch.Tensor
    """Bar width (and depth) of each gate's frame (T, G)."""
    bounds: tuple[torch.Tensor, torch.Tensor]
    """The arena's lower and upper corners (T, 3)."""
    box: tuple[torch.Tensor, torch.Tensor]
    """The start box's lower corner and size (T, 3)."""
    start_yaw: torch.Tensor
    """Yaw of a start-box start [rad] (T,)."""
    start_separation: torch.Tensor
    """Least distance between the drones of a start-box start [m] (T,)."""

    @classmethod
    def of(cls, track: TrackSpec | Sequence[TrackSpec] | TrackTensors, device: torch.device | str) -> TrackTensors:
        """The tensors of ``track`` (one or several) on ``device``: ``track`` itself when it already is that, else
        built (uploaded)."""
        device = torch.device(device)
        if isinstance(track, TrackTensors):
            if track.gate_centers.device == device:
                return track
            track = track.specs
        specs = (track,) if isinstance(track, TrackSpec) else tuple(track)
        if not specs:
            raise ValueError("tracks: give at least one track")
        most = max(len(s.gates) for s in specs)

        def tensor(values: object) -> torch.Tensor:
            return torch.tensor(values, dtype=torch.float32, device=device)

        def padded(rows: list) -> list:
            return rows + rows[-1:] * (most - len(rows))

        centers = [padded(s.gate_centers().tolist()) for s in specs]
        rotations = [padded(s.gate_rotations().tolist()) for s in specs]
        forward = [padded(s.gate_forward().tolist()) for s in specs]
        half = [padded([s.gate_opening(i) / 2 for i in range(len(s.gates))]) for s in specs]
        bar = [padded([s.gate_bar(i) for i in range(len(s.gates))]) for s in specs]
        center, size = tensor([s.start.center for s in specs]), tensor([s.start.size for s in specs])
        return cls(specs, torch.tensor([len(s.gates) for s in specs], device=device), tensor(centers),
                   tensor(rotations), tensor(forward), tensor(half), tensor(bar),
                   (tensor([s.bounds.min for s in specs]), tensor([s.bounds.max for s in specs])),
                   (center - size / 2, size), tensor([math.radians(s.start.yaw_deg) for s in specs]),
                   tensor([s.start.min_separation for s in specs]))

    @property
    def spec(self) -> TrackSpec:
        """The track, when there is one (the first of several)."""
        return self.specs[0]

    @property
    def track_count(self) -> int:
        """How many tracks."""
        return len(self.specs)

    @property
    def max_gates(self) -> int:
        """The most gates of any track: the padded per-gate length."""
        return self.gate_centers.shape[1]

    @property
    def flat_centers(self) -> torch.Tensor:
        """Gate centres (T · G, 3), track-major."""
        return self.gate_centers.view(-1, 3)

    @property
    def flat_forward(self) -> torch.Tensor:
        """Passing direction of every gate (T · G, 3), track-major."""
        return self.gate_forward.view(-1, 3)
