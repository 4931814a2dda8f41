"""Which track each world of a race env flies, and what a drone's race on it takes: its gates' rows in the env's gate
arrays, the gate passages that finish it, its time limit; with ``episode.hard_tracks``, how often the learner finished
on each track, which weighs the track draws."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from spiral.config.env import EpisodeCfg
from spiral.config.track import TrackSpec
from spiral.core.errors import UsageError
from spiral.env.events import gate_distance
from spiral.env.track_tensors import TrackTensors

__all__ = ["WorldTracks"]


class WorldTracks:
    """The tracks of ``world_count`` worlds of ``drones_per_world`` drones: one track, or a track per world drawn anew
    at each reset in training (in evaluation world ``w`` races track ``(w + k) mod T``, ``k`` drawn at each race,
    :meth:`rotate`)."""

    def __init__(self, tracks: Sequence[TrackSpec], episode: EpisodeCfg, *, world_count: int, drones_per_world: int,
                 device: torch.device, simulator_tracks: torch.Tensor) -> None:
        self.tracks = tuple(t.with_laps(episode.laps or t.laps) for t in tracks)
        """The tracks, with the env's laps."""
        self.track = self.tracks[0]
        """The track, when there is one (the first of several)."""
        self.geometry = TrackTensors.of(self.tracks, device)
        """The tracks' geometry on the env's device."""
        self.hard = episode.hard_tracks if len(self.tracks) > 1 else None
        self.drones_per_world = drones_per_world
        limits = [episode.time_limit_s or t.time_limit_s for t in self.tracks]
        passes = [len(t.gates) * t.laps + 1 for t in self.tracks]
        self.time_limit = max(limits)
        """The longest time limit of any track [s]."""
        self.passes_needed = max(passes)
        """Gate passages that finish the longest race of any track (its start line's included)."""
        self._limits, self._passes = torch.tensor(limits, device=device), torch.tensor(passes, device=device)
        self.ended = torch.zeros(len(self.tracks), device=device)
        """Learner episodes ended on each track (with ``episode.hard_tracks``), decayed every training iteration."""
        self.finished = torch.zeros_like(self.ended)
        """Those of them that finished."""
        n = world_count * drones_per_world
        self.world_track = torch.arange(world_count, device=device) % len(self.tracks)
        """Track of each world (W,), an index into :attr:`tracks`."""
        self.gate_count = torch.zeros(n, dtype=torch.long, device=device)
        """Gates of each drone's track (N,)."""
        self.gate_base = torch.zeros(n, dtype=torch.long, device=device)
        """Row of each drone's track's first gate in :attr:`gate_center` (N,)."""
        self.race_passes = torch.zeros(n, dtype=torch.long, device=device)
        """Gate passages that finish each drone's race (N,)."""
        self.world_time_limit = torch.zeros(world_count, device=device)
        """Time limit of each world's race [s] (W,)."""
        self.gate_center, self.gate_forward = self.geometry.flat_centers, self.geometry.flat_forward
        """Every track's gate centres and passing directions, track-major (T · G, 3)."""
        self.simulator_tracks = simulator_tracks
        """The simulator's track of each world (W,), int32: a view of its state that :meth:`follow` sets."""

    def max_steps(self, dt: float) -> int:
        """Control steps of ``dt`` [s] in the longest time limit."""
        return math.ceil(self.time_limit / dt)

    def follow(self) -> None:
        """Bring the per-drone figures and the simulator's track of each world in line with :attr:`world_track`."""
        drone_track = self.world_track.repeat_interleave(self.drones_per_world)
        self.gate_count.copy_(self.geometry.gate_count[drone_track])
        self.gate_base.copy_(drone_track * self.geometry.max_gates)
        self.race_passes.copy_(self._passes[drone_track])
        self.world_time_limit.copy_(self._limits[self.world_track])
        self.simulator_tracks.copy_(self.world_track)

    def one(self, user: str) -> TrackSpec:
        """The track, for ``user`` (what needs a single track, named in the error); several tracks are refused."""
        if len(self.tracks) > 1:
            raise UsageError(f"{user} needs every world on one track; this env flies {len(self.tracks)} (a track "
                             f"per world is for training)")
        return self.track

    def draw(self, count: int, generator: torch.Generator) -> torch.Tensor:
        """``count`` track indices drawn with ``generator``: uniformly, or with ``episode.hard_tracks`` a share of the
        draws weighted by each track's failure rate, its success smoothed as (finished + 1) / (ended + 2) over the
        learner's recent episodes on it."""
        tracks = len(self.tracks)
        if self.hard is None:
            return torch.randint(0, tracks, (count,), generator=generator, device=generator.device)
        fail = 1.0 - (self.finished + 1.0) / (self.ended + 2.0)
        weights = (1.0 - self.hard.share) / tracks + self.hard.share * fail / fail.sum()
        return torch.multinomial(weights.to(generator.device), count, replacement=True, generator=generator)

    def rotate(self, generator: torch.Generator) -> torch.Tensor:
        """Every world's track for an evaluation race, ``(w + k) mod T`` for world ``w`` with ``k`` drawn uniformly
        with ``generator``: every track races as often as any other, ± 1, whichever tracks the worlds begin at."""
        k = torch.randint(0, len(self.tracks), (1,), generator=generator, device=generator.device)
        return (torch.arange(len(self.world_track), device=generator.device) + k) % len(self.tracks)

    def count_ended(self, drones: torch.Tensor, dones: torch.Tensor, finished: torch.Tensor) -> None:
        """Count the episodes of ``drones`` (indices) ending where ``dones``, and those of them ``finished`` (a mask
        over every drone), on their worlds' tracks (with ``episode.hard_tracks`` only: nothing else reads them)."""
        if self.hard is not None:
            track = self.world_track[drones // self.drones_per_world]
            self.ended.index_add_(0, track, dones.float())
            self.finished.index_add_(0, track, (dones & finished[drones]).float())

    def decay(self) -> None:
        """Scale the episode counts by ``episode.hard_tracks.decay`` (once per training iteration)."""
        if self.hard is not None:
            self.ended.mul_(self.hard.decay)
            self.finished.mul_(self.hard.decay)

    def gate_distance(self, pos: torch.Tensor, gate: torch.Tensor, kappa: float) -> torch.Tensor:
        """Progress distance of drones at ``pos`` (N, 3) to their ``gate`` (N,)
        (:func:`~spiral.env.events.gate_distance`, funnel factor ``kappa``)."""
        row = gate + self.gate_base
        return gate_distance(pos, self.gate_center.index_select(0, row), self.gate_forward.index_select(0, row), kappa)

    def gate_rows(self, gate: torch.Tensor) -> torch.Tensor:
        """Rows in :attr:`gate_center` of each drone's ``gate`` (N,), an index taken modulo its track's gates."""
        return gate % self.gate_count + self.gate_base

    def to_gate(self, pos: torch.Tensor, gate: torch.Tensor) -> torch.Tensor:
        """Vectors from drones at ``pos`` (N, 3) to the centres of their ``gate`` (N,) [m] (N, 3)."""
        return self.gate_center.index_select(0, gate.long() + self.gate_base) - pos
