"""What a race env holds: the simulator with zero-copy views of its state, who drives each slot, each drone's race so
far and the episode statistics (:class:`~spiral.env.RaceEnv` adds how it steps; :mod:`spiral.env.outcome` reads
the step for the reward terms)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import warp as wp

from spiral.config.env import EnvCfg
from spiral.config.track import TrackSpec
from spiral.core.errors import UsageError
from spiral.core.outcome import race_winner
from spiral.core.policy import OpponentPolicy
from spiral.env.events import (
    gate_distance,
)
from spiral.env.rewards import REWARD_TERMS
from spiral.env.setting import RaceSetting
from spiral.env.slots import slot_map
from spiral.env.stats import add_ended_episodes, empty_stats, read_stats, summarize_stats
from spiral.env.track_tensors import TrackTensors
from spiral.sim import World

__all__ = ["RaceState", "draw_device"]


def draw_device(device: torch.device, *, training: bool) -> torch.device:
    """Where an env on ``device`` makes its random draws: on ``device`` in training (no copy to the device at every
    reset), on the CPU in evaluation, so that a seed means the same placements on any device (a CUDA generator draws
    other numbers than the CPU's for the same seed)."""
    return device if training else torch.device("cpu")


class RaceState:
    """``world_count`` worlds of ``drones_per_world`` drones, flat and world-major: drone ``i`` is slot ``i % D`` of
    world ``i // D``. The learner drives ``learner_slots``; the other slots are opponents (see :attr:`slots`)."""

    def __init__(self, setting: RaceSetting, cfg: EnvCfg, *, world_count: int, drones_per_world: int,
                 learner_slots: Sequence[int] = (0,), device: str = "cpu", seed: int = 0,
                 training: bool = True) -> None:
        if setting.sim.control_mode != "pid":
            raise UsageError("RaceEnv drives the PID: sim.control_mode must be 'pid'")
        self.tracks = tuple(t.with_laps(cfg.episode.laps or t.laps) for t in setting.tracks)
        """The tracks the worlds race, with the env's laps (one, or a track per world drawn at each reset)."""
        self.track = self.tracks[0]
        """The track, when there is one (the first of several)."""
        self.world = World(list(setting.tracks), setting.airframe, setting.sim, world_count=world_count,
                           drones_per_world=drones_per_world, device=device, cpu_threads=setting.sim_threads)
        self.device = torch.device(device)
        self.track_set = TrackTensors.of(self.tracks, self.device)
        """The tracks' geometry on the env's device."""
        self.cfg, self.training, self.world_count, self.drones_per_world = cfg, training, world_count, drones_per_world
        self.drone_count = world_count * drones_per_world
        self.slots = slot_map(world_count, drones_per_world, learner_slots, device=self.device)
        """Who drives which slot; its fields are attributes of the env too (``learner_idx``, ``race_team``, ...)."""
        s = self.slots
        self.learner_slots, self.opponent_slots, self.learner_idx, self.opponent_idx = (
            s.learner_slots, s.opponent_slots, s.learner_idx, s.opponent_idx)
        self.slot_team, self.race_team, self.other_slots = s.slot_team, s.race_team, s.other_slots
        self.num_envs = self.learner_idx.numel()
        self.dt = self.world.time_step
        self._set_race_lengths()
        self.generator = torch.Generator(device=draw_device(self.device, training=training)).manual_seed(seed)
        self.opponent_policy: OpponentPolicy | None = None
        self.sync_free = self.device.type != "cpu"
        """Steps without a host synchronisation (the default off a CPU): every auto-reset draws starts for every
        world and keeps those of the ended ones (:func:`~spiral.env.race_env.restart_worlds`), and no shortcut reads
        a flag back; on a CPU, where a read costs nothing, the env finds the ended worlds and draws for them alone.
        The two paths are valid training runs of different draws."""
        self._bind_views()
        self._alloc_buffers()

    def _set_race_lengths(self) -> None:
        """Each track's time limit and the gate passages that finish its race, the longest of them, and the counts of
        the learner's episodes on it."""
        limits = [self.cfg.episode.time_limit_s or t.time_limit_s for t in self.tracks]
        passes = [len(t.gates) * t.laps + 1 for t in self.tracks]
        self.time_limit = max(limits)
        """The longest time limit of any track [s]."""
        self.max_episode_length = math.ceil(self.time_limit / self.dt)
        self.passes_needed = max(passes)
        """Gate passages that finish the longest race of any track (its start line's included)."""
        self._track_limits = torch.tensor(limits, device=self.device)
        self._track_passes = torch.tensor(passes, device=self.device)
        self.track_ended = torch.zeros(len(self.tracks), device=self.device)
        """Learner episodes ended on each track (with a track per world and ``episode.hard_tracks``), decayed every
        training iteration."""
        self.track_finished = torch.zeros_like(self.track_ended)
        """Those of them that finished (``episode.hard_tracks`` draws by the two)."""

    def _bind_views(self) -> None:
        s, r, t = self.world.state, self.world.race, wp.to_torch
        self.pos, self.vel, self.quat, self.omega = t(s.pos), t(s.vel), t(s.quat), t(s.omega)
        self.rpy, self.integral, self.cmd = t(self.world.rpy), t(self.world.integral), t(self.world.cmd)
        self.next_gate, self.gates_passed, self.step_passes = t(r.next_gate), t(r.gates_passed), t(r.step_passes)
        self.pass_time, self.step_collision, self.out = t(r.pass_time), t(r.step_collision), t(r.out)
        self.crash_time = t(r.crash_time)
        self.world_substeps, self.world_nonfinite = t(r.world_substeps), t(r.world_nonfinite)
        self.world_track_view = t(r.world_track)
        """The simulator's track of each world (W,), int32."""
        self.gate_center, self.gate_forward = self.track_set.flat_centers, self.track_set.flat_forward
        """Every track's gate centres and passing directions, track-major (T · G, 3)."""

    def _alloc_buffers(self) -> None:
        n, w, dev = self.drone_count, self.world_count, self.device
        self.last_action = torch.zeros(n, 4, device=dev)
        """Actions applied at the last control step, clamped to [-1, 1]."""
        self.commanded = torch.zeros(n, 4, device=dev)
        """Actions the policies commanded at the last control step, before that clamp."""
        self.finished = torch.zeros(n, dtype=torch.bool, device=dev)
        """Lap(s) completed without collision."""
        self.crashed = torch.zeros(n, dtype=torch.bool, device=dev)
        """Collided since the reset."""
        self.absent = torch.zeros(n, dtype=torch.bool, device=dev)
        """Slot not in the race (an opponent slot with no opponent policy)."""
        self.lap_time = torch.zeros(n, device=dev)
        self.lap_start = torch.zeros(n, device=dev)
        """Race time at which each drone's current lap began (its start or its last lap's end) [s]."""
        self.crash_kind = torch.zeros(n, dtype=torch.int32, device=dev)
        self.episode_length_buf = torch.zeros(self.num_envs, dtype=torch.long, device=dev)
        self.term_sums = {name: torch.zeros(n, device=dev) for name in REWARD_TERMS}
        self.cut_time = torch.full((w,), math.inf, device=dev)
        """Race time at which each world's episode is cut short (``episode.start_cut_prob``), else inf [s]."""
        self.contested = torch.zeros(w, dtype=torch.bool, device=dev)
        """Start-box race against opponents whose winner is not known yet."""
        self.start_buffers = {name: wp.zeros(size, dtype=dtype, device=self.world.device) for name, size, dtype in (
            ("mask", w, wp.int32), ("pos", n, wp.vec3), ("vel", n, wp.vec3), ("yaw", n, wp.float32),
            ("gate", n, wp.int32))}
        """Warp buffers of the start states a reset hands the simulator."""
        self.stats = empty_stats(dev)
        self.world_track = torch.arange(w, device=dev) % len(self.tracks)
        """Track of each world (W,), an index into :attr:`tracks`: in training drawn anew at every reset of the
        world, in evaluation world ``w`` races track ``w mod T``."""
        self.gate_count = torch.zeros(n, dtype=torch.long, device=dev)
        """Gates of each drone's track (N,)."""
        self.gate_base = torch.zeros(n, dtype=torch.long, device=dev)
        """Row of each drone's track's first gate in :attr:`gate_center` (N,)."""
        self.race_passes = torch.zeros(n, dtype=torch.long, device=dev)
        """Gate passages that finish each drone's race (N,)."""
        self.world_time_limit = torch.zeros(w, device=dev)
        """Time limit of each world's race [s] (W,)."""
        self.follow_world_tracks()

    def follow_world_tracks(self) -> None:
        """Bring the per-drone track figures and the simulator's tracks in line with :attr:`world_track`."""
        drone_track = self.world_track.repeat_interleave(self.drones_per_world)
        self.gate_count.copy_(self.track_set.gate_count[drone_track])
        self.gate_base.copy_(drone_track * self.track_set.max_gates)
        self.race_passes.copy_(self._track_passes[drone_track])
        self.world_time_limit.copy_(self._track_limits[self.world_track])
        self.world_track_view.copy_(self.world_track)

    def one_track(self, user: str) -> TrackSpec:
        """The env's track, for ``user`` (what needs a single track, named in the error), which an env flying a
        track per world refuses."""
        if len(self.tracks) > 1:
            raise UsageError(f"{user} needs every world on one track; this env flies {len(self.tracks)} (a track "
                             f"per world is for training)")
        return self.track

    def set_opponent_policy(self, policy: OpponentPolicy | None) -> None:
        """Drive the opponent slots with ``policy`` from the next reset on (``None``: the slots are absent)."""
        self.opponent_policy = policy

    def reset_drone_buffers(self, drones: torch.Tensor) -> None:
        """Start the race afresh for the drones in the bool mask ``drones``; opponent slots without a policy are out."""
        for buf in (self.last_action, self.lap_time, self.lap_start, self.crash_kind, *self.term_sums.values()):
            buf.masked_fill_(drones.view(-1, *[1] * (buf.dim() - 1)), 0)
        self.finished &= ~drones
        self.crashed &= ~drones
        absent = torch.zeros_like(drones)
        if self.opponent_policy is None and self.opponent_idx.numel():
            absent[self.opponent_idx] = True
        self.absent.copy_(torch.where(drones, absent, self.absent))
        self.out.masked_fill_(drones & absent, 1)
        self.cmd.copy_(torch.where(drones[:, None], torch.cat([self.pos, self.rpy[:, 2:3]], dim=-1), self.cmd))
        self._fresh = drones
        """Drones whose observation history starts afresh at the next observation."""

    def gate_distance(self, gate: torch.Tensor) -> torch.Tensor:
        """Progress distance of every drone to ``gate`` (:func:`~spiral.env.events.gate_distance`)."""
        kappa = self.cfg.reward.progress_lateral
        row = gate + self.gate_base
        return gate_distance(self.pos, self.gate_center[row], self.gate_forward[row], kappa)

    def track_place(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Where each drone is in the race: gates passed and distance to the next gate's centre [m] (N,) each."""
        return self.gates_passed.clone(), self.to_next_gate().norm(dim=-1)

    def to_next_gate(self) -> torch.Tensor:
        """Every drone's vector to the centre of its next gate [m] (N, 3)."""
        return self.gate_center[self.next_gate.long() + self.gate_base] - self.pos

    def learner_won(self) -> torch.Tensor:
        """Per world, whether the learner's team won the race against the opponent slots (bool, (W,))."""
        w, d = self.world_count, self.drones_per_world
        teams = [self.learner_slots, self.opponent_slots]
        return race_winner(self.finished.view(w, d), self.lap_time.view(w, d), teams) == 0

    def world_time(self) -> torch.Tensor:
        """Simulated time of each world since its reset [s]."""
        return self.world_substeps.float() * self.world.sim.dt

    def _count_ended(self, dones: torch.Tensor) -> None:
        """Add the learner episodes ending where ``dones`` (num_envs,) to :attr:`stats`."""
        idx = self.learner_idx
        add_ended_episodes(self.stats, dones, finished=self.finished[idx], lap_time=self.lap_time[idx],
                           crash_kind=self.crash_kind[idx], term_sums={k: v[idx] for k, v in self.term_sums.items()})
        if self.cfg.episode.hard_tracks is not None and len(self.tracks) > 1:  # only its draws read them
            track = self.world_track[idx // self.drones_per_world]
            self.track_ended.index_add_(0, track, dones.float())
            self.track_finished.index_add_(0, track, (dones & self.finished[idx]).float())

    def pop_stats(self) -> dict[str, float]:
        """Means over the learner episodes ended since the last call, then start counting afresh."""
        return summarize_stats(self.take_stats())

    def take_stats(self) -> dict[str, float]:
        """Sums over the learner episodes ended since the last call, read from the device; counting restarts."""
        s, self.stats = self.stats, empty_stats(self.device)
        return read_stats(s)
