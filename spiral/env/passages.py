"""Starts from states drones really fly: a buffer of the states drones had just after passing each gate in training,
drawn again (perturbed) as the start of a new episode.

Each gate keeps its newest ``capacity`` passage states: position, velocity and yaw at the end of the control step in
which a racing drone passed it. A start drawn from gate ``g``'s states heads for gate ``g + 1``. The drones of one
world start behind different gates of the world's track (a world with more drones than gates gets none of these
starts); each state is perturbed by Gaussian noise, and a draw whose position is out of bounds or touches a gate's
frame is not used. With several tracks (a track per world) every gate of every track keeps its own states.
"""

from __future__ import annotations

import torch

from spiral.config.env import PassageStartsCfg
from spiral.config.track import TrackSpec
from spiral.env.starts import Starts, world_tracks_or_first
from spiral.env.track_tensors import TrackTensors
from spiral.env.world_tracks import WorldTracks

__all__ = ["PassageBuffer", "PassageStarts", "clear_of_gates", "passage_share"]


def passage_share(cfg: PassageStartsCfg, fraction: float) -> float:
    """Share of episodes started from passage states ``fraction`` of the way through a stage: linear from
    ``cfg.share_start`` to ``cfg.share_end``."""
    fraction = min(max(fraction, 0.0), 1.0)
    return cfg.share_start + (cfg.share_end - cfg.share_start) * fraction


def clear_of_gates(pos: torch.Tensor, track: TrackSpec | TrackTensors, radius: float, *,
                   margin: float = 0.05, world_tracks: torch.Tensor | None = None) -> torch.Tensor:
    """Whether a sphere of ``radius`` at each position (..., 3) keeps ``margin`` from every gate's frame and from the
    arena's bounds; positions (W, D, 3) with ``world_tracks`` (W,) are checked against their world's track of
    ``track`` (default: the first track).

    A gate's frame is the square ring between the opening (half side ``h``) and the outer side (``h`` plus the bar),
    as deep as the bar. A sphere touches it when it reaches into that slab (``|x| < bar / 2 + r``) and is not inside
    the opening (``max(|y|, |z|) > h − r``) nor outside the frame (``max(|y|, |z|) < h + bar + r``); the test adds
    ``margin`` to ``r`` on every side.
    """
    r = radius + margin
    geometry = TrackTensors.of(track, pos.device)
    if world_tracks is None:
        centers, rot, half, bar = (x[0] for x in (geometry.gate_centers, geometry.gate_rotations, geometry.gate_half,
                                                  geometry.gate_bar))
        local = torch.einsum("gij,...gi->...gj", rot, pos[..., None, :] - centers)  # rot's columns: normal, y, z
        lo, hi = geometry.bounds[0][0] + r, geometry.bounds[1][0] - r
    else:  # (W, D, 3): each world's own track
        t = world_tracks.long()
        centers, rot, half, bar = (x[t][:, None] for x in (geometry.gate_centers, geometry.gate_rotations,
                                                           geometry.gate_half, geometry.gate_bar))
        local = torch.einsum("wdgij,wdgi->wdgj", rot, pos[..., None, :] - centers)
        lo, hi = geometry.bounds[0][t][:, None] + r, geometry.bounds[1][t][:, None] - r
    in_plane = local[..., 1:].abs().amax(dim=-1)
    touches = (local[..., 0].abs() < bar / 2 + r) & (in_plane > half - r) & (in_plane < half + bar + r)
    inside = ((pos >= lo) & (pos <= hi)).all(dim=-1)
    return inside & ~touches.any(dim=-1)


class PassageBuffer:
    """The newest ``capacity`` passage states of each gate (positions, velocities, yaws), on the env's device.

    Gates are rows of the tracks' flat gate layout (:class:`~spiral.env.track_tensors.TrackTensors`: gate ``g`` of
    track ``t`` is row ``t · max_gates + g``), ``gate_count`` (T,) the gates of each track (default: one track of
    ``rows`` gates)."""

    def __init__(self, rows: int, capacity: int, *, device: torch.device,
                 gate_count: torch.Tensor | None = None) -> None:
        self.rows, self.capacity = rows, capacity
        self.gate_count = torch.tensor([rows], device=device) if gate_count is None else gate_count.to(device)
        """Gates of each track (T,)."""
        self.max_gates = rows // self.gate_count.numel()
        self.pos = torch.zeros(rows + 1, capacity, 3, device=device)  # a spare row past the last takes the states
        self.vel = torch.zeros(rows + 1, capacity, 3, device=device)  # of drones that passed none
        self.yaw = torch.zeros(rows + 1, capacity, device=device)
        self.count = torch.zeros(rows, dtype=torch.long, device=device)
        """States recorded per gate, at most ``capacity``."""
        self.head = torch.zeros(rows, dtype=torch.long, device=device)
        """Slot of each gate's next recorded state (the oldest once full)."""

    def record(self, gate: torch.Tensor, pos: torch.Tensor, vel: torch.Tensor, yaw: torch.Tensor) -> None:
        """Keep the states of the drones that passed gate row ``gate`` (N,; −1 for a drone that passed none) in this
        step.

        Every drone's state is written, those of drones that passed no gate to a spare row past the last gate, so
        that no count is read on the host."""
        g = torch.where(gate >= 0, gate.long(), self.rows)
        passed = g[:, None] == torch.arange(self.rows + 1, device=g.device)
        rank = passed.long().cumsum(dim=0).gather(1, g[:, None]).squeeze(1) - 1
        slot = (torch.cat([self.head, self.head.new_zeros(1)])[g] + rank) % self.capacity
        self.pos[g, slot], self.vel[g, slot], self.yaw[g, slot] = pos, vel, yaw
        added = passed[:, :-1].sum(dim=0)
        self.head = (self.head + added) % self.capacity
        self.count = (self.count + added).clamp(max=self.capacity)

    def sample(self, world_count: int, drones: int, generator: torch.Generator, *, pos_noise: float,
               vel_noise: float, world_tracks: torch.Tensor | None = None
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Starts for ``world_count`` worlds of ``drones`` (on the tracks ``world_tracks`` (W,); default: the first):
        positions and velocities (W, D, 3), yaws and next gates (W, D), and whether each world could be given such
        starts (W,): every drone's gate has recorded states, and the world's track has at least as many gates as
        drones. The drones of a world start behind different gates."""
        device = self.pos.device
        tracks = world_tracks_or_first(world_tracks, world_count, device)
        count = self.gate_count[tracks][:, None]
        keys = torch.rand(world_count, self.max_gates, generator=generator, device=device)
        if self.gate_count.numel() > 1:  # a shorter track's padding rows sort last
            keys = keys.masked_fill(torch.arange(self.max_gates, device=device) >= count, 2.0)
        order = keys.argsort(dim=1)
        gate = order.gather(1, torch.arange(drones, device=device).expand(world_count, -1) % count)
        row = tracks[:, None] * self.max_gates + gate
        pick = torch.rand(world_count, drones, generator=generator, device=device)
        slot = (pick * self.count[row]).long().clamp(max=self.capacity - 1)
        pos = self.pos[row, slot] + pos_noise * torch.randn(world_count, drones, 3, generator=generator,
                                                           device=device)
        vel = self.vel[row, slot] + vel_noise * torch.randn(world_count, drones, 3, generator=generator,
                                                           device=device)
        ok = (self.count[row] > 0).all(dim=1) & (drones <= count[:, 0])
        return pos, vel, self.yaw[row, slot], (gate + 1) % count, ok


class PassageStarts:
    """What a training env does with passage starts (``episode.passage_starts``): records the states of its racing
    drones at each gate passage, and turns a share of the starts it draws into starts from those states. Inert
    without the setting, and in evaluation (an env that does not reset by itself)."""

    def __init__(self, cfg: PassageStartsCfg | None, track: TrackSpec | TrackTensors, radius: float, *,
                 training: bool, device: torch.device) -> None:
        self.cfg = cfg if training else None
        self.radius, self.share = radius, 0.0 if self.cfg is None else self.cfg.share_start
        self.geometry = TrackTensors.of(track, device)
        """The tracks' gates and bounds on the buffer's device, for the checks of a draw."""
        g = self.geometry
        self.buffer = None if self.cfg is None else PassageBuffer(
            g.track_count * g.max_gates, self.cfg.capacity, device=device, gate_count=g.gate_count)

    def set_training_progress(self, fraction: float) -> None:
        """Move the share of passage starts along the stage's schedule."""
        if self.cfg is not None:
            self.share = passage_share(self.cfg, fraction)

    def record(self, racing: torch.Tensor, step_passes: torch.Tensor, next_gate: torch.Tensor, tracks: WorldTracks,
               pos: torch.Tensor, vel: torch.Tensor, yaw: torch.Tensor) -> None:
        """Keep the state after this step (``pos``, ``vel``, ``yaw``) of each drone that raced the step without a
        crash (``racing``) and passed a gate in it (``step_passes``), as a state of the gate before its
        ``next_gate`` on its track (nothing without a buffer)."""
        if self.buffer is not None:
            passed = racing & (step_passes > 0)
            self.buffer.record(torch.where(passed, tracks.gate_rows(next_gate.long() - 1), -1), pos, vel, yaw)

    def apply(self, starts: Starts, generator: torch.Generator, world_tracks: torch.Tensor | None = None) -> Starts:
        """``starts`` with a share of its worlds started from passage states instead (those worlds are not box
        starts); a world whose draw is not clear of the gates and bounds keeps its start. ``world_tracks`` (W,):
        the track of each world (default: the first)."""
        if self.buffer is None or self.share <= 0:
            return starts
        world_count, drones = starts.yaw.shape
        device = starts.pos.device
        pos, vel, yaw, gate, ok = self.buffer.sample(world_count, drones, generator, pos_noise=self.cfg.pos_noise,
                                                     vel_noise=self.cfg.vel_noise, world_tracks=world_tracks)
        use = torch.rand(world_count, generator=generator, device=device) < self.share
        clear = clear_of_gates(pos, self.geometry, self.radius,
                               world_tracks=world_tracks if self.geometry.track_count > 1 else None)
        use &= ok & clear.all(dim=1)
        w, v = use[:, None, None], use[:, None]
        return Starts(torch.where(w, pos, starts.pos), torch.where(w, vel, starts.vel), torch.where(v, yaw, starts.yaw),
                      torch.where(v, gate.to(starts.gate.dtype), starts.gate), starts.box & ~use)
