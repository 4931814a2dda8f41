"""A track's geometry as tensors on one device, built once per env so that the start draws of an env step copy
nothing from the host."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from spiral.config.track import TrackSpec

__all__ = ["TrackTensors"]


@dataclass(frozen=True)
class TrackTensors:
    """The geometry of ``spec`` that start draws and start checks read, as float32 tensors on one device."""

    spec: TrackSpec
    gate_centers: torch.Tensor
    """Gate centres (G, 3)."""
    gate_rotations: torch.Tensor
    """Gate frames (G, 3, 3), columns: normal, y, z."""
    gate_half: torch.Tensor
    """Half side of each gate's opening (G,)."""
    gate_bar: torch.Tensor
    """Bar width (and depth) of each gate's frame (G,)."""
    bounds: tuple[torch.Tensor, torch.Tensor]
    """The arena's lower and upper corners (3,)."""
    box: tuple[torch.Tensor, torch.Tensor]
    """The start box's lower corner and size (3,)."""

    @classmethod
    def of(cls, track: TrackSpec | TrackTensors, device: torch.device | str) -> TrackTensors:
        """``track``'s tensors on ``device``: ``track`` itself when it already is that, else built (uploaded)."""
        device = torch.device(device)
        if isinstance(track, TrackTensors):
            if track.gate_centers.device == device:
                return track
            track = track.spec
        gates = range(len(track.gates))

        def tensor(values: object) -> torch.Tensor:
            return torch.tensor(values, dtype=torch.float32, device=device)

        center, size = tensor(track.start.center), tensor(track.start.size)
        return cls(track, tensor(track.gate_centers()), tensor(track.gate_rotations()),
                   tensor([track.gate_opening(i) / 2 for i in gates]), tensor([track.gate_bar(i) for i in gates]),
                   (tensor(track.bounds.min), tensor(track.bounds.max)), (center - size / 2, size))
