"""Batched drone races on torch tensors over zero-copy views of the Warp simulator state: what a race env holds (the
simulator's views, who drives each slot, each drone's race so far, the episode statistics) and how it steps. Term math
is in :mod:`spiral.env.events` and :mod:`spiral.env.rewards`; which track each world flies in
:mod:`spiral.env.world_tracks`."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import warp as wp
from tensordict import TensorDict

from spiral.config.env import EnvCfg, ObsCfg
from spiral.core.errors import UsageError
from spiral.core.host_syncs import put_rows
from spiral.core.outcome import race_winner
from spiral.core.policy import OpponentPolicy, RecordingOpponent, ResettingOpponent
from spiral.core.scenario import race_teams, team_slots
from spiral.env.actions import ActionMap
from spiral.env.events import RaceEvents, closing_in, heading, lap_splits, nearest_distance, race_result
from spiral.env.observations import Observer, ObsSource
from spiral.env.passages import PassageStarts
from spiral.env.records import RaceRecords
from spiral.env.rewards import StepOutcome, compute_rewards
from spiral.env.setting import RaceSetting
from spiral.env.slots import per_row, slot_map
from spiral.env.starts import Starts, draw_device, draw_starts
from spiral.env.stats import EpisodeStats
from spiral.env.track_tensors import TrackTensors
from spiral.env.world_tracks import WorldTracks
from spiral.sim import World

__all__ = ["EpisodeEnds", "RaceEnv", "draw_world_tracks", "learner_won", "restart_worlds", "step_outcome",
           "track_place"]


@dataclass(frozen=True)
class EpisodeEnds:
    """Which learner episodes (num_envs,) and worlds (W,) end at a step."""

    dones: torch.Tensor
    time_outs: torch.Tensor
    """Ended without a terminal state (time limit, a cut start, or another drone of the world ended it)."""
    worlds: torch.Tensor


def observed_tensors(env: RaceEnv) -> ObsSource:
    """The tensors of ``env`` that the observations are made of, named one by one."""
    t = env.world_tracks
    return ObsSource(pos=env.pos, vel=env.vel, rpy=env.rpy, omega=env.omega, integral=env.integral, out=env.out,
                     next_gate=env.next_gate, race_team=env.race_team, gate_center=t.gate_center,
                     gate_forward=t.gate_forward, gate_count=t.gate_count, gate_base=t.gate_base)


def step_outcome(env: RaceEnv, ev: RaceEvents) -> StepOutcome:
    """The reward terms' view of the step of ``env`` (progress distances, headings, the nearest drones, closing in);
    frozen drones make no progress."""
    racing, zero = ev.racing, torch.zeros_like(ev.dist_before)
    reward, w, d = env.cfg.reward, env.world_count, env.drones_per_world
    nearest = None
    if reward.proximity > 0:
        nearest = nearest_distance(env.pos, env.out, world_count=w, drones_per_world=d)
    return StepOutcome(
        dist_before=torch.where(racing, ev.dist_before, zero),
        dist_after=torch.where(racing, progress_distance(env, ev.gate), zero),
        gates_passed=torch.where(racing, env.step_passes, torch.zeros_like(env.step_passes)),
        crashed_now=ev.crashed_now,
        heading=heading(env.quat),
        to_gate=env.world_tracks.to_gate(env.pos, env.next_gate),
        lap_time=ev.lap_split,
        nearest=nearest,
        race_result=ev.race_result,
        closing=closing_in(env.pos, env.vel, env.out, distance=reward.closing_distance, world_count=w,
                           drones_per_world=d) if reward.closing > 0 else None,
    )


def draw_env_starts(env: RaceEnv, world_count: int, *, checked: bool = True,
                    world_tracks: torch.Tensor | None = None) -> Starts:
    """Starts of ``world_count`` worlds of ``env`` (passage starts among them in training) on their tracks
    (``world_tracks`` (W,); default: the first), drawn with its generator on the generator's device
    (:func:`~spiral.env.starts.draw_device`) and moved to the env's; ``checked``: the box draw's
    (:func:`~spiral.env.starts.sample_box_starts`)."""
    if world_tracks is not None:
        world_tracks = world_tracks.to(env.generator.device)
    worlds = world_count if world_tracks is None else world_tracks
    starts = draw_starts(env.track_geometry, env.cfg.episode, worlds, env.drones_per_world, env.generator,
                         training=env.training, device=env.generator.device, checked=checked)
    return env.passages.apply(starts, env.generator, world_tracks).to(env.device)


def draw_world_tracks(env: RaceEnv, worlds: torch.Tensor, idx: torch.Tensor | None) -> torch.Tensor | None:
    """The tracks of the worlds of ``env`` that the bool mask ``worlds`` selects (``idx``: its indices; None: every
    world's), drawn anew for those worlds with the env's generator (with ``idx`` None drawn for every world and kept
    where the mask is set): in training each world's (:meth:`~spiral.env.world_tracks.WorldTracks.draw`), in
    evaluation where the tracks begin (:meth:`~spiral.env.world_tracks.WorldTracks.rotate`: world ``w`` races track
    ``(w + k) mod T``, so that races of fewer worlds than tracks do not race the first tracks only). None for an env of
    one track (nothing is drawn)."""
    if len(env.tracks) == 1:
        return None
    tracks = env.world_tracks
    if env.training:
        count = env.world_count if idx is None else idx.numel()
        put_rows(tracks.world_track, tracks.draw(count, env.generator).to(env.device), worlds, idx)
    else:
        put_rows(tracks.world_track, tracks.rotate(env.generator).to(env.device), worlds, None)
    tracks.follow()
    return tracks.world_track if idx is None else tracks.world_track[idx]


def contests(env: RaceEnv) -> bool:
    """Whether the drones that race in ``env`` are of more than one team: a start-box race has a winner to find."""
    driven = env.learner_slots + (env.opponent_slots if env.opponent_policy is not None else [])
    teams = race_teams(env.drones_per_world)
    return len({teams[s] for s in driven}) > 1


def progress_distance(env: RaceEnv, gate: torch.Tensor) -> torch.Tensor:
    """Progress distance of every drone of ``env`` to ``gate`` (N,) (:func:`~spiral.env.events.gate_distance`)."""
    return env.world_tracks.gate_distance(env.pos, gate, env.cfg.reward.progress_lateral)


def track_place(env: RaceEnv) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each drone of ``env`` is in the race: gates passed and distance to the next gate's centre [m] (N,)
    each."""
    return env.gates_passed.clone(), env.world_tracks.to_gate(env.pos, env.next_gate).norm(dim=-1)


def learner_won(env: RaceEnv) -> torch.Tensor:
    """Per world of ``env``, whether the learner's team won the race against the opponent slots (bool, (W,))."""
    w, d = env.world_count, env.drones_per_world
    teams = [env.learner_slots, env.opponent_slots]
    return race_winner(env.records.finished.view(w, d), env.records.lap_time.view(w, d), teams) == 0


# The step's phases, in their order (:meth:`RaceEnv.step`)


def apply_actions(env: RaceEnv, actions: torch.Tensor, opponent_actions: torch.Tensor | None = None) -> None:
    """Apply action: the learner's ``actions`` (num_envs, 4) and the opponent policy's (on the last observations,
    unless ``opponent_actions`` gives them) become the PID targets of the drones still racing."""
    commanded = torch.zeros(env.drone_count, 4, device=env.device)
    commanded.index_copy_(0, env.learner_idx, actions.to(env.device, commanded.dtype))
    if opponent_actions is None and env.opponent_policy is not None and env.opponent_idx.numel():
        with torch.no_grad():
            opponent_actions = env.opponent_policy(env.opponent_observations())
    if opponent_actions is not None:
        commanded.index_copy_(0, env.opponent_idx, opponent_actions.to(env.device, commanded.dtype))
    env.commanded = commanded
    all_actions = commanded.clamp(-1.0, 1.0)
    racing = ~(env.out.bool())
    target = env.action_map.targets(all_actions, env.pos, env.vel, env.rpy[:, 2], racing)
    env.cmd.copy_(torch.where(racing[:, None], target, env.cmd))
    env.last_action = all_actions


def simulate(env: RaceEnv) -> tuple[torch.Tensor, torch.Tensor]:
    """Simulate one control step; return the gate each drone targeted and its progress distance from before."""
    gate = env.next_gate.long().clone()
    dist_before = progress_distance(env, gate)
    env.world.step()
    return gate, dist_before


def race_events(env: RaceEnv, gate: torch.Tensor, dist_before: torch.Tensor) -> RaceEvents:
    """Race events: a collision ends a drone's race, its last lap finishes it (frozen, no longer an obstacle),
    each lap's split is taken; a contested race is decided by its first finisher."""
    rec = env.records
    racing = rec.racing()
    crashed_now = racing & (env.step_collision != 0)
    flying = racing & ~crashed_now
    finished_now = flying & (env.gates_passed >= env.world_tracks.race_passes)
    rec.end(crashed_now, env.step_collision, finished_now, env.pass_time)
    env.out.masked_fill_(finished_now, 1)
    split, rec.lap_start = lap_splits(env.gates_passed, env.step_passes, env.pass_time, rec.lap_start,
                                      flying, env.world_tracks.gate_count)
    env.passages.record(flying, env.step_passes, env.next_gate, env.world_tracks, env.pos, env.vel,
                        env.rpy[:, 2])
    result = None
    if env.cfg.reward.win > 0:
        result, decided = race_result(finished_now, rec.lap_time, flying, env.contested,
                                      env.race_team, team_slots(env.drones_per_world))
        env.contested &= ~decided
    return RaceEvents(racing, crashed_now, finished_now, gate, dist_before, result, split)


def step_rewards(env: RaceEnv, ev: RaceEvents) -> torch.Tensor:
    """Rewards: the weighted reward terms of every drone (N,); each term's episode sum is kept."""
    rewards, terms = compute_rewards(step_outcome(env, ev), env.cfg.reward)
    for name, value in terms.items():
        env.records.term_sums[name] += value
    return rewards


def episode_ends(env: RaceEnv, ev: RaceEvents) -> EpisodeEnds:
    """Dones: a learner drone's crash or finish terminates its episode; its world ends with it, at the time limit
    (or a start's cut) or on a non-finite state, and the world's other learner episodes time out."""
    terminated = (ev.crashed_now | ev.finished_now).index_select(0, env.learner_idx)
    time_up = env.world_time() >= torch.minimum(env.cut_time, env.world_tracks.world_time_limit) - 1e-6
    worlds = terminated.view(env.world_count, -1).any(dim=1) | time_up | (env.world_nonfinite != 0)
    time_outs = per_row(worlds, len(env.learner_slots)) & ~terminated
    dones = terminated | time_outs
    env.episode_length_buf += 1
    env.stats.add(dones, env.records, env.learner_idx)
    env.world_tracks.count_ended(env.learner_idx, dones, env.records.finished)
    return EpisodeEnds(dones, time_outs, worlds)


def reset_ended(env: RaceEnv, ends: EpisodeEnds) -> None:
    """Reset: tell the opponent policy who won the ended races, then (training) start new ones after
    :meth:`RaceEnv.before_auto_reset`."""
    ended = env.sync_free or bool(ends.worlds.any())  # on a CPU: a step in which no race ended has nothing to do
    if ended and _implements(env, RecordingOpponent):
        env.opponent_policy.record(ends.worlds, learner_won(env))
    if env.training and ended:
        env.stats.sums["nonfinite_resets"] += ((env.world_nonfinite != 0) & ends.worlds).sum()
        env.before_auto_reset(ends.worlds)
        restart_worlds(env, ends.worlds, every_world=env.sync_free)
        env.episode_length_buf.masked_fill_(per_row(ends.worlds, len(env.learner_slots)), 0)
    else:
        env.fresh = torch.zeros_like(env.records.finished)


def restart_worlds(env: RaceEnv, worlds: torch.Tensor, *, every_world: bool = False) -> None:
    """Draw new starts for the worlds of ``env`` in the bool mask ``worlds`` and reset them in the simulator: drawn
    for those worlds only, in world order (so a reset of every world draws what it always did), or with
    ``every_world`` for every world and kept where the mask is set, without a host read (``env.sync_free``)."""
    d, generator = env.drones_per_world, env.generator
    idx = None if every_world else worlds.nonzero().squeeze(1)
    count = env.world_count if idx is None else idx.numel()
    tracks = draw_world_tracks(env, worlds, idx)
    starts = draw_env_starts(env, count, checked=idx is not None, world_tracks=tracks)
    buf, views = env.start_buffers, env.start_views
    views["mask"].copy_(worlds.int())
    for name in ("pos", "vel", "yaw", "gate"):
        value = getattr(starts, name)
        put_rows(views[name].view(-1, d, *value.shape[2:]), value, worlds, idx)
    env.world.reset(buf["mask"], buf["pos"], buf["yaw"], init_vel=buf["vel"], init_next_gate=buf["gate"])
    env.reset_drone_buffers(per_row(worlds, d))
    put_rows(env.contested, starts.box & contests(env), worlds, idx)
    episode = env.cfg.episode
    if env.training and episode.start_cut_prob > 0:
        cut = starts.box & (torch.rand(count, generator=generator, device=generator.device) < episode.start_cut_prob)
        put_rows(env.cut_time, torch.where(cut, episode.start_cut_s, math.inf), worlds, idx)
    if _implements(env, ResettingOpponent):
        env.opponent_policy.reset(worlds)


def _implements(env: RaceEnv, protocol: type) -> bool:
    """``isinstance(env.opponent_policy, protocol)``, found once per policy (a runtime-checkable protocol's
    ``isinstance`` looks every member up at each call)."""
    policy, (known, found) = env.opponent_policy, env.opponent_hooks
    if known is not policy:
        found = {}
        env.opponent_hooks = (policy, found)
    if protocol not in found:
        found[protocol] = isinstance(policy, protocol)
    return found[protocol]


class RaceEnv:
    """``world_count`` races of ``drones_per_world`` drones, flat and world-major (drone ``i`` is slot ``i % D`` of
    world ``i // D``); the learner drives ``learner_slots`` of each world.

    Each learner drone is one PPO environment (``num_envs = world_count · len(learner_slots)``); opponent slots act
    from an injected :class:`~spiral.core.policy.OpponentPolicy`, or are absent without one. A world resets when one
    of its learner drones crashes or finishes, at its time limit, or on a non-finite state (``nonfinite_resets``);
    learner drones cut short by another's end get ``time_outs``. ``training=False`` is evaluation mode (starts from
    ``episode.eval_starts``, no start cuts): every world races once, done drones stay frozen. :meth:`step` runs apply
    action → simulate → race events → rewards → dones → reset → observe."""

    def __init__(self, setting: RaceSetting, cfg: EnvCfg, *, world_count: int, drones_per_world: int,
                 learner_slots: Sequence[int] = (0,), device: str = "cpu", seed: int = 0,
                 training: bool = True) -> None:
        if setting.sim.control_mode != "pid":
            raise UsageError("RaceEnv drives the PID: sim.control_mode must be 'pid'")
        self.cfg, self.training, self.world_count, self.drones_per_world = cfg, training, world_count, drones_per_world
        self.drone_count, self.device = world_count * drones_per_world, torch.device(device)
        self.world = World(list(setting.tracks), setting.airframe, setting.sim, world_count=world_count,
                           drones_per_world=drones_per_world, device=device, cpu_threads=setting.sim_threads)
        self.world_tracks = WorldTracks(setting.tracks, cfg.episode, world_count=world_count,
                                        drones_per_world=drones_per_world, device=self.device,
                                        simulator_tracks=wp.to_torch(self.world.race.world_track))
        self.tracks, self.track = self.world_tracks.tracks, self.world_tracks.track
        """The tracks the worlds race, with the env's laps, and the first of them."""
        self.slots = s = slot_map(world_count, drones_per_world, learner_slots, device=self.device)
        """Who drives which slot; its fields are attributes of the env too (``learner_idx``, ``race_team``, ...)."""
        self.learner_slots, self.opponent_slots, self.learner_idx, self.opponent_idx = (
            s.learner_slots, s.opponent_slots, s.learner_idx, s.opponent_idx)
        self.slot_team, self.race_team = s.slot_team, s.race_team
        self.num_envs, self.dt = self.learner_idx.numel(), self.world.time_step
        self.max_episode_length = self.world_tracks.max_steps(self.dt)
        self.passes_needed = self.world_tracks.passes_needed
        self.generator = torch.Generator(device=draw_device(self.device, training=training)).manual_seed(seed)
        self.opponent_policy: OpponentPolicy | None = None
        self.opponent_hooks: tuple[object, dict[type, bool]] = (None, {})
        """The opponent policy whose hooks were looked up, and which protocols it implements (:func:`_implements`)."""
        self.sync_free = self.device.type != "cpu"
        """Steps without a host synchronisation (the default off a CPU): every auto-reset draws starts for every
        world and keeps those of the ended ones (:func:`restart_worlds`), and no shortcut reads a flag back; on a CPU,
        where a read costs nothing, the env finds the ended worlds and draws for them alone. The two paths are valid
        training runs of different draws."""
        self._bind_views()
        self._alloc_buffers()
        self._build_parts(setting)
        self.reset()

    def _build_parts(self, setting: RaceSetting) -> None:
        cfg = self.cfg
        arena = self.world_tracks.one("action.mode absolute") if cfg.action.mode == "absolute" else self.track
        self.action_map = ActionMap(cfg, arena, world_count=self.world_count, drones_per_world=self.drones_per_world,
                                    device=self.device)
        self._obs_source = observed_tensors(self)
        self.observer = Observer(cfg, self._obs_source, device=self.device)
        self.obs_builder = self.observer.builder
        """The observation layout and history buffer."""
        self.opponent_observer: Observer | None = None
        """The opponent slots' own observer when their policy reads another observation layout (cross-play)."""
        self.passages = PassageStarts(cfg.episode.passage_starts, self.world_tracks.geometry,
                                      setting.airframe.radius, training=self.training, device=self.device)
        self.track_geometry = TrackTensors.of(self.world_tracks.geometry, self.generator.device)
        """The tracks' geometry where starts are drawn, so that a draw copies nothing from the host."""

    def _bind_views(self) -> None:
        s, r, t = self.world.state, self.world.race, wp.to_torch
        self.pos, self.vel, self.quat, self.omega = t(s.pos), t(s.vel), t(s.quat), t(s.omega)
        self.rpy, self.integral, self.cmd = t(self.world.rpy), t(self.world.integral), t(self.world.cmd)
        self.next_gate, self.gates_passed, self.step_passes = t(r.next_gate), t(r.gates_passed), t(r.step_passes)
        self.pass_time, self.step_collision, self.out = t(r.pass_time), t(r.step_collision), t(r.out)
        self.crash_time = t(r.crash_time)
        self.world_substeps, self.world_nonfinite = t(r.world_substeps), t(r.world_nonfinite)

    def _alloc_buffers(self) -> None:
        n, w, dev = self.drone_count, self.world_count, self.device
        self.last_action = torch.zeros(n, 4, device=dev)
        """Actions applied at the last control step, clamped to [-1, 1]."""
        self.commanded = torch.zeros(n, 4, device=dev)
        """Actions the policies commanded at the last control step, before that clamp."""
        self.records = RaceRecords(n, dev)
        """Each drone's race since its world's reset."""
        self.episode_length_buf = torch.zeros(self.num_envs, dtype=torch.long, device=dev)
        self.cut_time = torch.full((w,), math.inf, device=dev)
        """Race time at which each world's episode is cut short (``episode.start_cut_prob``), else inf [s]."""
        self.contested = torch.zeros(w, dtype=torch.bool, device=dev)
        """Start-box race against opponents whose winner is not known yet."""
        self.start_buffers = {name: wp.zeros(size, dtype=dtype, device=self.world.device) for name, size, dtype in (
            ("mask", w, wp.int32), ("pos", n, wp.vec3), ("vel", n, wp.vec3), ("yaw", n, wp.float32),
            ("gate", n, wp.int32))}
        """Warp buffers of the start states a reset hands the simulator."""
        self.start_views = {name: wp.to_torch(buf) for name, buf in self.start_buffers.items()}
        """Torch views of :attr:`start_buffers`, where a reset writes the start states."""
        self.stats = EpisodeStats(dev)
        """Sums over the learner episodes that ended since training last read them."""
        self.world_tracks.follow()

    def set_opponent_policy(self, policy: OpponentPolicy | None, *, obs: ObsCfg | None = None) -> None:
        """Drive the opponent slots with ``policy`` from the next reset on (``None``: absent); ``obs``: the layout
        ``policy`` reads if not the env's (cross-play), with which its slots are then observed too."""
        self.opponent_policy = policy
        self.opponent_observer = None
        if obs is not None and obs != self.cfg.obs:  # observes the current state at once, each history afresh
            cfg = self.cfg.model_copy(update={"obs": obs})
            self.opponent_observer = Observer(cfg, self._obs_source, device=self.device)
            self.opponent_observer.record(self.last_action, torch.ones_like(self.records.finished))

    def set_training_progress(self, fraction: float) -> None:
        """Tell the env how far its training stage is (fraction of its iterations; once per iteration): schedules
        follow it, and the per-track episode counts of ``episode.hard_tracks`` decay."""
        self.passages.set_training_progress(fraction)
        self.world_tracks.decay()

    # Step: the phases in their order (module functions)

    def step(self, actions: torch.Tensor, opponent_actions: torch.Tensor | None = None
             ) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        """Apply learner ``actions`` (num_envs, 4), advance one control step, reset ended worlds, observe.
        ``opponent_actions``: the opponent rows' actions when acted for elsewhere (a mixed stage's joint pass).

        Returns:
            Learner observations, rewards (num_envs,), dones (num_envs,) and extras with ``time_outs``.
        """
        apply_actions(self, actions, opponent_actions)
        gate, dist_before = simulate(self)
        events = race_events(self, gate, dist_before)
        rewards = step_rewards(self, events)
        ends = episode_ends(self, events)
        reset_ended(self, ends)
        obs = self.get_observations()
        return obs, rewards.index_select(0, self.learner_idx), ends.dones, {"time_outs": ends.time_outs}

    def before_auto_reset(self, worlds: torch.Tensor) -> None:
        """Hook: called in :meth:`step` just before the worlds in the bool mask ``worlds`` reset, with the step's end
        state in place (:meth:`peek_observations` observes it). Does nothing here."""

    def get_observations(self) -> TensorDict:
        """Observe: record this step in the history and return the learner drones' ``policy`` and ``critic`` groups
        (the same tensor)."""
        self.observer.record(self.last_action, self.fresh)
        if self.opponent_observer is not None:
            self.opponent_observer.record(self.last_action, self.fresh)
        return self.observer.rows(self.learner_idx)

    # Reset

    def reset(self) -> TensorDict:
        """Reset every world and return the learner observations."""
        restart_worlds(self, torch.ones(self.world_count, dtype=torch.bool, device=self.device))
        self.episode_length_buf.zero_()
        return self.get_observations()

    def reset_drone_buffers(self, drones: torch.Tensor) -> None:
        """Start the race afresh for the drones in the bool mask ``drones``; opponent slots without a policy are out."""
        self.last_action.masked_fill_(drones[:, None], 0)
        absent = torch.zeros_like(drones)
        if self.opponent_policy is None and self.opponent_idx.numel():
            absent[self.opponent_idx] = True
        self.records.restart(drones, absent)
        self.out.masked_fill_(drones & absent, 1)
        self.cmd.copy_(torch.where(drones[:, None], torch.cat([self.pos, self.rpy[:, 2:3]], dim=-1), self.cmd))
        self.fresh = drones
        """Drones whose observation history starts afresh at the next observation."""

    # Observations

    @property
    def obs_dim(self) -> int:
        """Length of one observation vector."""
        return self.obs_builder.obs_dim

    def current_observations(self) -> TensorDict:
        """The learner observations of the last step or reset (no new history entry)."""
        return self.observer.rows(self.learner_idx)

    def opponent_observations(self) -> TensorDict:
        """What the opponent policy reads: the opponent rows of the last observation, in its layout."""
        return (self.opponent_observer or self.observer).rows(self.opponent_idx)

    def peek_observations(self) -> torch.Tensor:
        """Observation rows of every drone (N, obs_dim) for the current state, as if it were observed now, without
        recording it in the history (what :meth:`get_observations` would return, leaving the env unchanged)."""
        return self.observer.peek(self.last_action)

    # Queries

    def world_time(self) -> torch.Tensor:
        """Simulated time of each world since its reset [s]."""
        return self.world_substeps.float() * self.world.sim.dt

    def pop_stats(self) -> dict[str, float]:
        """Means over the learner episodes ended since the last call, then start counting afresh."""
        return self.stats.pop()
