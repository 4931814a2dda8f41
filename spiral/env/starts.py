"""Seeded start placements: inside the track's start box, or at random points along the track (training)."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

from spiral.config.env import EpisodeCfg
from spiral.config.track import TrackSpec
from spiral.core.errors import UsageError
from spiral.env.track_tensors import TrackTensors

__all__ = ["FILE_GAP", "FILE_JITTER", "UNCHECKED_ROUNDS", "Starts", "draw_device", "draw_starts", "sample_box_starts",
           "sample_file_starts", "sample_track_starts", "world_tracks_or_first"]

FILE_GAP = (0.4, 1.0)
"""Range of the distance [m] along the track between consecutive drones of a file start."""
FILE_JITTER = 0.05
"""Standard deviation [m] of the random offset of each drone of a file start from its place on the line."""
UNCHECKED_ROUNDS = 3
"""Placement rounds of an unchecked box draw (:func:`sample_box_starts`), which never reads a flag back."""


def draw_device(device: torch.device, *, training: bool) -> torch.device:
    """Where an env on ``device`` makes its random draws: on ``device`` in training (no copy to the device at every
    reset), on the CPU in evaluation, so that a seed means the same placements on any device (a CUDA generator draws
    other numbers than the CPU's for the same seed)."""
    return device if training else torch.device("cpu")


def _place_sequentially(
    lo: torch.Tensor, size: torch.Tensor, pos: torch.Tensor, todo: torch.Tensor, drones: int, min_sep: torch.Tensor,
    generator: torch.Generator, candidates: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Place the drones of the worlds in ``todo`` one by one in their boxes (``lo``, ``size`` (W, 1, 3), ``min_sep``
    (W, 1)); return positions and the worlds that got stuck."""
    w = pos.shape[0]
    new = pos.clone()
    stuck = torch.zeros(w, dtype=torch.bool, device=pos.device)
    for j in range(drones):
        cand = lo + torch.rand(w, candidates, 3, generator=generator, device=pos.device) * size
        if j == 0:
            new[:, 0] = cand[:, 0]
            continue
        ok = torch.cdist(cand, new[:, :j]).amin(dim=-1) >= min_sep
        stuck |= ~ok.any(dim=1)
        new[:, j] = cand[torch.arange(w, device=pos.device), ok.float().argmax(dim=1)]
    return torch.where(todo[:, None, None], new, pos), stuck & todo


def world_tracks_or_first(world_tracks: torch.Tensor | None, world_count: int, device: torch.device) -> torch.Tensor:
    """The track of each of ``world_count`` worlds (W,), int64: ``world_tracks``, or the first track for all."""
    if world_tracks is None:
        return torch.zeros(world_count, dtype=torch.long, device=device)
    return world_tracks.to(device=device, dtype=torch.long)


def sample_box_starts(
    track: TrackSpec | TrackTensors, world_count: int, drones: int, generator: torch.Generator, *, device: torch.device,
    candidates: int = 256, checked: bool = True, world_tracks: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Positions (W, D, 3) uniform in the start box with the minimum separation, and yaws (W, D); each world in the
    box of its track (``world_tracks`` (W,) of the tracks of ``track``; default: the first).

    Drones are placed one after another: each takes the first of ``candidates`` uniform draws that keeps the
    separation from the drones already placed; a world that gets stuck starts over. The result depends only on
    the generator's state. ``checked``: retry until every world is placed and raise ``UsageError`` when the box
    cannot hold the drones (reads a flag back every round); else :data:`UNCHECKED_ROUNDS` rounds, never read back (a
    world stuck in all of them, which a box that passed a checked draw makes vanishingly rare, keeps a drone at its
    first candidate).
    """
    geometry = TrackTensors.of(track, device)
    tracks = world_tracks_or_first(world_tracks, world_count, device)
    lo, size = (x[tracks][:, None] for x in geometry.box)
    min_sep = geometry.start_separation[tracks][:, None]
    pos = torch.zeros(world_count, drones, 3, device=device)
    todo = torch.ones(world_count, dtype=torch.bool, device=device)
    for _ in range(50 if checked else UNCHECKED_ROUNDS):  # worlds whose sequential placement got stuck start over
        pos, todo = _place_sequentially(lo, size, pos, todo, drones, min_sep, generator, candidates)
        if checked and not todo.any():
            break
    else:
        if checked:
            stuck = geometry.specs[int(tracks[todo.nonzero()[0, 0]])]
            raise UsageError(f"start box of track {stuck.name!r} cannot hold {drones} drones "
                             f"{stuck.start.min_separation} m apart")
    yaw = geometry.start_yaw[tracks][:, None].expand(world_count, drones).contiguous()
    return pos, yaw


def _random_segments(track: TrackSpec | TrackTensors, tracks: torch.Tensor, shape: tuple[int, ...],
                     generator: torch.Generator, device: torch.device
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A uniformly drawn next gate per entry of ``shape`` (on the track of the entry's world, ``tracks`` (W,)), the
    centre of the gate before it (where the segment starts) and the segment's vector to the next gate's centre."""
    geometry = TrackTensors.of(track, device)
    count = geometry.gate_count[tracks].view(-1, *[1] * (len(shape) - 1))
    target = torch.randint(0, _common_multiple(geometry), shape, generator=generator, device=device) % count
    row = tracks.view(-1, *[1] * (len(shape) - 1)) * geometry.max_gates
    centers = geometry.flat_centers
    origin = centers[row + (target - 1) % count]
    return target, origin, centers[row + target] - origin


def _common_multiple(geometry: TrackTensors) -> int:
    """The least common multiple of the tracks' gate counts: a uniform draw below it, modulo any track's count, is
    uniform over that track's gates (with one track, the count itself)."""
    return math.lcm(*(len(s.gates) for s in geometry.specs))


def sample_track_starts(
    track: TrackSpec | TrackTensors, world_count: int, drones: int, generator: torch.Generator, *, max_speed: float,
    device: torch.device, world_tracks: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Random points on the centreline segments between consecutive gates (of each world's track, ``world_tracks``;
    default: the first), heading for the segment's end gate.

    Returns positions (W, D, 3), velocities along the segment up to ``max_speed`` (W, D, 3), yaws (W, D) and the
    next gate (W, D). Drones of one world draw their points independently.
    """
    shape = (world_count, drones)
    tracks = world_tracks_or_first(world_tracks, world_count, device)
    target, origin, seg = _random_segments(track, tracks, shape, generator, device)
    u = 0.15 + 0.7 * torch.rand(*shape, 1, generator=generator, device=device)
    jitter = 0.1 * torch.randn(*shape, 3, generator=generator, device=device)
    pos = origin + u * seg + jitter
    direction = seg / seg.norm(dim=-1, keepdim=True)
    speed = max_speed * torch.rand(*shape, 1, generator=generator, device=device)
    yaw = torch.atan2(direction[..., 1], direction[..., 0])
    return pos, direction * speed, yaw, target


def sample_file_starts(
    track: TrackSpec | TrackTensors, world_count: int, drones: int, generator: torch.Generator, *, max_speed: float,
    device: torch.device, world_tracks: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The drones of each world in single file on one centreline segment between consecutive gates (of the world's
    track, ``world_tracks``; default: the first).

    The file's lead is at a random point of the segment's middle 70 %, each next drone a distance drawn from
    :data:`FILE_GAP` behind the one before (the gaps shrink in proportion on a segment too short for them), each
    offset by Gaussian noise of :data:`FILE_JITTER` per axis; which drone takes which place is random. Every drone
    heads for the segment's end gate at its own speed, uniform up to ``max_speed``. Returns positions (W, D, 3),
    velocities (W, D, 3), yaws (W, D) and the next gate (W, D).
    """
    tracks = world_tracks_or_first(world_tracks, world_count, device)
    target, origin, seg = _random_segments(track, tracks, (world_count,), generator, device)
    length = seg.norm(dim=-1, keepdim=True)
    direction = seg / length
    lo, hi = FILE_GAP
    gaps = lo + (hi - lo) * torch.rand(world_count, drones - 1, generator=generator, device=device)
    behind = torch.cat([torch.zeros(world_count, 1, device=device), gaps.cumsum(dim=1)], dim=1)
    behind = behind * (0.7 * length / behind[:, -1:].clamp(min=1e-6)).clamp(max=1.0)
    first = 0.15 * length + behind[:, -1:]
    lead = first + (0.85 * length - first) * torch.rand(world_count, 1, generator=generator, device=device)
    order = torch.rand(world_count, drones, generator=generator, device=device).argsort(dim=1)
    along = (lead - behind).gather(1, order)
    jitter = FILE_JITTER * torch.randn(world_count, drones, 3, generator=generator, device=device)
    pos = origin[:, None] + along[..., None] * direction[:, None] + jitter
    speed = max_speed * torch.rand(world_count, drones, 1, generator=generator, device=device)
    yaw = torch.atan2(direction[:, 1], direction[:, 0])[:, None].expand(world_count, drones)
    return pos, direction[:, None] * speed, yaw.contiguous(), target[:, None].expand(world_count, drones)


@dataclass(frozen=True)
class Starts:
    """Start states of the drones of some worlds."""

    pos: torch.Tensor
    """Positions (W, D, 3)."""
    vel: torch.Tensor
    """Velocities (W, D, 3)."""
    yaw: torch.Tensor
    """Yaws (W, D)."""
    gate: torch.Tensor
    """Next gate (W, D), int32."""
    box: torch.Tensor
    """Whether each world starts in the start box (W,), else along the track (at a random point or, in evaluation, in
    single file)."""

    def to(self, device: torch.device) -> Starts:
        """These starts on ``device``."""
        return Starts(*(getattr(self, f.name).to(device) for f in fields(self)))


def draw_starts(track: TrackSpec | TrackTensors, episode: EpisodeCfg, worlds: int | torch.Tensor, drones: int,
                generator: torch.Generator, *, training: bool, device: torch.device, checked: bool = True) -> Starts:
    """Starts in the start box, and in training a share ``episode.track_start_prob`` of worlds along the track.
    Evaluation starts every world where ``episode.eval_starts`` says. ``worlds``: how many, all on the first track
    of ``track``, or the track of each (W,).

    The draws depend only on the generator's state: box placements for every world first, then track starts and
    the choice between them (training with track starts only).
    ``checked``: the box draw's (:func:`sample_box_starts`).
    """
    world_tracks = worlds if torch.is_tensor(worlds) else None
    world_count = worlds.numel() if torch.is_tensor(worlds) else worlds
    where = {"device": device, "world_tracks": world_tracks}
    pos, yaw = sample_box_starts(track, world_count, drones, generator, checked=checked, **where)
    state = (pos, torch.zeros_like(pos), yaw, torch.zeros(world_count, drones, dtype=torch.int32, device=device))
    box = torch.ones(world_count, dtype=torch.bool, device=device)
    if not training and episode.eval_starts != "box":  # a robustness check: every world starts off the box
        sample = sample_track_starts if episode.eval_starts == "track" else sample_file_starts
        drawn = sample(track, world_count, drones, generator, max_speed=episode.track_start_speed, **where)
        return Starts(*(new.to(old.dtype) for new, old in zip(drawn, state, strict=True)), ~box)
    if training and episode.track_start_prob > 0:
        drawn = sample_track_starts(track, world_count, drones, generator, max_speed=episode.track_start_speed,
                                    **where)
        use = torch.rand(world_count, generator=generator, device=device) < episode.track_start_prob
        state = tuple(torch.where(use.view(-1, *[1] * (old.dim() - 1)), new.to(old.dtype), old)
                      for new, old in zip(drawn, state, strict=True))
        box = box & ~use
    return Starts(*state, box)
