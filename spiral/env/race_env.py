"""Batched drone races on torch tensors over zero-copy views of the Warp simulator state."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import warp as wp
from tensordict import TensorDict

from spiral.config.env import EnvCfg, ObsCfg
from spiral.core.host_syncs import put_rows
from spiral.core.policy import OpponentPolicy, RecordingOpponent, ResettingOpponent
from spiral.core.scenario import race_teams, team_slots
from spiral.env.actions import ActionMap
from spiral.env.events import RaceEvents, lap_splits, race_result
from spiral.env.observations import Observer, ObsSource
from spiral.env.outcome import step_outcome
from spiral.env.passages import PassageStarts
from spiral.env.rewards import compute_rewards
from spiral.env.setting import RaceSetting
from spiral.env.slots import per_row
from spiral.env.starts import Starts, draw_starts
from spiral.env.state import RaceState
from spiral.env.track_tensors import TrackTensors

__all__ = ["EpisodeEnds", "RaceEnv", "draw_tracks", "draw_world_tracks", "restart_worlds"]


@dataclass(frozen=True)
class EpisodeEnds:
    """Which learner episodes (num_envs,) and worlds (W,) end at a step."""

    dones: torch.Tensor
    time_outs: torch.Tensor
    """Ended without a terminal state (time limit, a cut start, or another drone of the world ended it)."""
    worlds: torch.Tensor


def observed_tensors(state: RaceState) -> ObsSource:
    """The tensors of ``state`` that the observations are made of, named one by one."""
    return ObsSource(pos=state.pos, vel=state.vel, rpy=state.rpy, omega=state.omega, integral=state.integral,
                     out=state.out, next_gate=state.next_gate, gates_passed=state.gates_passed,
                     race_team=state.race_team, gate_center=state.gate_center,
                     gate_forward=state.gate_forward, gate_count=state.gate_count, gate_base=state.gate_base,
                     other_slots=state.other_slots)


def draw_env_starts(env: RaceEnv, world_count: int, *, checked: bool = True,
                    world_tracks: torch.Tensor | None = None) -> Starts:
    """Starts of ``world_count`` worlds of ``env`` (passage starts among them in training) on their tracks
    (``world_tracks`` (W,); default: the first), drawn with its generator on the generator's device
    (:func:`~spiral.env.state.draw_device`) and moved to the env's; ``checked``: the box draw's
    (:func:`~spiral.env.starts.sample_box_starts`)."""
    if world_tracks is not None:
        world_tracks = world_tracks.to(env.generator.device)
    worlds = world_count if world_tracks is None else world_tracks
    starts = draw_starts(env.track_geometry, env.cfg.episode, worlds, env.drones_per_world, env.generator,
                         training=env.training, device=env.generator.device, checked=checked)
    return env.passages.apply(starts, env.generator, world_tracks).to(env.device)


def draw_world_tracks(env: RaceEnv, worlds: torch.Tensor, idx: torch.Tensor | None) -> torch.Tensor | None:
    """The tracks of the worlds of ``env`` that the bool mask ``worlds`` selects (``idx``: its indices; None: every
    world's), drawn anew for those worlds in training (uniformly, with the env's generator; with ``idx`` None drawn
    for every world and kept where the mask is set); None for an env of one track (nothing is drawn)."""
    if len(env.tracks) == 1:
        return None
    if env.training:
        count = env.world_count if idx is None else idx.numel()
        put_rows(env.world_track, draw_tracks(env, count).to(env.device), worlds, idx)
        env.follow_world_tracks()
    return env.world_track if idx is None else env.world_track[idx]


def draw_tracks(env: RaceState, count: int) -> torch.Tensor:
    """``count`` track indices drawn with the env's generator: uniformly, or with ``episode.hard_tracks`` a share of
    the draws weighted by each track's failure rate, its success smoothed as (finished + 1) / (ended + 2) over the
    learner's recent episodes on it."""
    generator, hard, tracks = env.generator, env.cfg.episode.hard_tracks, len(env.tracks)
    if hard is None:
        return torch.randint(0, tracks, (count,), generator=generator, device=generator.device)
    fail = 1.0 - (env.track_finished + 1.0) / (env.track_ended + 2.0)
    weights = (1.0 - hard.share) / tracks + hard.share * fail / fail.sum()
    return torch.multinomial(weights.to(generator.device), count, replacement=True, generator=generator)


def contests(env: RaceState) -> bool:
    """Whether the drones that race in ``env`` are of more than one team: a start-box race has a winner to find."""
    driven = env.learner_slots + (env.opponent_slots if env.opponent_policy is not None else [])
    teams = race_teams(env.drones_per_world)
    return len({teams[s] for s in driven}) > 1


def restart_worlds(env: RaceEnv, worlds: torch.Tensor, *, every_world: bool = False) -> None:
    """Draw new starts for the worlds of ``env`` in the bool mask ``worlds`` and reset them in the simulator: drawn
    for those worlds only, in world order (so a reset of every world draws what it always did), or with
    ``every_world`` for every world and kept where the mask is set, without a host read (``env.sync_free``)."""
    d, generator = env.drones_per_world, env.generator
    idx = None if every_world else worlds.nonzero().squeeze(1)
    count = env.world_count if idx is None else idx.numel()
    tracks = draw_world_tracks(env, worlds, idx)
    starts = draw_env_starts(env, count, checked=idx is not None, world_tracks=tracks)
    buf, t = env.start_buffers, wp.to_torch
    t(buf["mask"]).copy_(worlds.int())
    for name in ("pos", "vel", "yaw", "gate"):
        value = getattr(starts, name)
        put_rows(t(buf[name]).view(-1, d, *value.shape[2:]), value, worlds, idx)
    env.world.reset(buf["mask"], buf["pos"], buf["yaw"], init_vel=buf["vel"], init_next_gate=buf["gate"])
    env.reset_drone_buffers(per_row(worlds, d))
    put_rows(env.contested, starts.box & contests(env), worlds, idx)
    episode = env.cfg.episode
    if env.training and episode.start_cut_prob > 0:
        cut = starts.box & (torch.rand(count, generator=generator, device=generator.device) < episode.start_cut_prob)
        put_rows(env.cut_time, torch.where(cut, episode.start_cut_s, math.inf), worlds, idx)
    if isinstance(env.opponent_policy, ResettingOpponent):
        env.opponent_policy.reset(worlds)


class RaceEnv(RaceState):
    """``world_count`` races of ``drones_per_world`` drones; the learner drives ``learner_slots`` of each world.

    Each learner drone is one PPO environment (``num_envs = world_count · len(learner_slots)``); opponent slots act
    from an injected :class:`~spiral.core.policy.OpponentPolicy`, or are absent without one. A world resets when one
    of its learner drones crashes or finishes, at its time limit, or on a non-finite state (``nonfinite_resets``);
    learner drones cut short by another's end get ``time_outs``. ``training=False`` is evaluation mode (starts from
    ``episode.eval_starts``, no start cuts): every world races once, done drones stay
    frozen. :meth:`step` runs apply action → simulate → race events → rewards → dones → reset → observe."""

    def __init__(self, setting: RaceSetting, cfg: EnvCfg, *, world_count: int, drones_per_world: int,
                 learner_slots: Sequence[int] = (0,), device: str = "cpu", seed: int = 0,
                 training: bool = True) -> None:
        super().__init__(setting, cfg, world_count=world_count, drones_per_world=drones_per_world,
                         learner_slots=learner_slots, device=device, seed=seed, training=training)
        arena = self.one_track("action.mode absolute") if cfg.action.mode == "absolute" else self.track
        self.action_map = ActionMap(cfg, arena, world_count=world_count, drones_per_world=drones_per_world,
                                    device=self.device)
        self._obs_source = observed_tensors(self)
        self.observer = Observer(cfg, self._obs_source, device=self.device)
        self.obs_builder = self.observer.builder
        """The observation layout and history buffer."""
        self.opponent_observer: Observer | None = None
        """The opponent slots' own observer when their policy reads another observation layout (cross-play)."""
        self.passages = PassageStarts.of(self, setting.airframe.radius)
        self.track_geometry = TrackTensors.of(self.track_set, self.generator.device)
        """The tracks' geometry where starts are drawn, so that a draw copies nothing from the host."""
        self.reset()

    def set_opponent_policy(self, policy: OpponentPolicy | None, *, obs: ObsCfg | None = None) -> None:
        """Drive the opponent slots with ``policy`` from the next reset on (``None``: absent); ``obs``: the layout
        ``policy`` reads if not the env's (cross-play), with which its slots are then observed too."""
        super().set_opponent_policy(policy)
        self.opponent_observer = None
        if obs is not None and obs != self.cfg.obs:  # observes the current state at once, each history afresh
            cfg = self.cfg.model_copy(update={"obs": obs, "critic": "policy"})
            self.opponent_observer = Observer(cfg, self._obs_source, device=self.device)
            self.opponent_observer.record(self.last_action, torch.ones_like(self.finished))

    def set_training_progress(self, fraction: float) -> None:
        """Tell the env how far its training stage is (fraction of its iterations; once per iteration): schedules
        follow it, and the per-track episode counts of ``episode.hard_tracks`` decay."""
        self.passages.set_training_progress(fraction)
        hard = self.cfg.episode.hard_tracks
        if hard is not None:
            self.track_ended.mul_(hard.decay)
            self.track_finished.mul_(hard.decay)

    # Step: the hooks in their order

    def step(self, actions: torch.Tensor, opponent_actions: torch.Tensor | None = None
             ) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        """Apply learner ``actions`` (num_envs, 4), advance one control step, reset ended worlds, observe.
        ``opponent_actions``: the opponent rows' actions when acted for elsewhere (a mixed stage's joint pass).

        Returns:
            Learner observations, rewards (num_envs,), dones (num_envs,) and extras with ``time_outs``.
        """
        self.apply_actions(actions, opponent_actions)
        gate, dist_before = self.simulate()
        events = self.race_events(gate, dist_before)
        rewards = self.rewards(events)
        ends = self.dones(events)
        self.reset_ended(ends)
        obs = self.get_observations()
        return obs, rewards[self.learner_idx], ends.dones, {"time_outs": ends.time_outs}

    def apply_actions(self, actions: torch.Tensor, opponent_actions: torch.Tensor | None = None) -> None:
        """Apply action: the learner's ``actions`` (num_envs, 4) and the opponent policy's (on the last observations,
        unless ``opponent_actions`` gives them) become the PID targets of the drones still racing."""
        commanded = torch.zeros(self.drone_count, 4, device=self.device)
        commanded[self.learner_idx] = actions.to(self.device)
        if opponent_actions is None and self.opponent_policy is not None and self.opponent_idx.numel():
            with torch.no_grad():
                opponent_actions = self.opponent_policy(self.opponent_observations())
        if opponent_actions is not None:
            commanded[self.opponent_idx] = opponent_actions.to(self.device)
        self.commanded = commanded
        all_actions = commanded.clamp(-1.0, 1.0)
        racing = ~(self.out.bool())
        target = self.action_map.targets(all_actions, self.pos, self.vel, self.rpy[:, 2], racing)
        self.cmd.copy_(torch.where(racing[:, None], target, self.cmd))
        self.last_action = all_actions

    def simulate(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Simulate one control step; return the gate each drone targeted and its progress distance from before."""
        gate = self.next_gate.long().clone()
        dist_before = self.gate_distance(gate)
        self.world.step()
        return gate, dist_before

    def race_events(self, gate: torch.Tensor, dist_before: torch.Tensor) -> RaceEvents:
        """Race events: a collision ends a drone's race, its last lap finishes it (frozen, no longer an obstacle),
        each lap's split is taken; a contested race is decided by its first finisher."""
        racing = ~(self.crashed | self.finished | self.absent)
        crashed_now = racing & (self.step_collision != 0)
        self.crashed |= crashed_now
        self.crash_kind = torch.where(crashed_now, self.step_collision, self.crash_kind)
        finished_now = racing & ~crashed_now & (self.gates_passed >= self.race_passes)
        self.finished |= finished_now
        self.lap_time = torch.where(finished_now, self.pass_time, self.lap_time)
        self.out.masked_fill_(finished_now, 1)
        split, self.lap_start = lap_splits(self.gates_passed, self.step_passes, self.pass_time, self.lap_start,
                                           racing & ~crashed_now, self.gate_count)
        self.passages.record(self, racing, crashed_now)
        result = None
        if self.cfg.reward.win > 0:
            result, decided = race_result(finished_now, self.lap_time, racing & ~crashed_now, self.contested,
                                          self.race_team, team_slots(self.drones_per_world))
            self.contested &= ~decided
        return RaceEvents(racing, crashed_now, finished_now, gate, dist_before, result, split)

    def rewards(self, ev: RaceEvents) -> torch.Tensor:
        """Rewards: the weighted reward terms of every drone (N,); each term's episode sum is kept."""
        rewards, terms = compute_rewards(step_outcome(self, ev), self.cfg.reward)
        for name, value in terms.items():
            self.term_sums[name] += value
        return rewards

    def dones(self, ev: RaceEvents) -> EpisodeEnds:
        """Dones: a learner drone's crash or finish terminates its episode; its world ends with it, at the time limit
        (or a start's cut) or on a non-finite state, and the world's other learner episodes time out."""
        terminated = (ev.crashed_now | ev.finished_now)[self.learner_idx]
        time_up = self.world_time() >= torch.minimum(self.cut_time, self.world_time_limit) - 1e-6
        worlds = terminated.view(self.world_count, -1).any(dim=1) | time_up | (self.world_nonfinite != 0)
        time_outs = per_row(worlds, len(self.learner_slots)) & ~terminated
        dones = terminated | time_outs
        self.episode_length_buf += 1
        self._count_ended(dones)
        return EpisodeEnds(dones, time_outs, worlds)

    def reset_ended(self, ends: EpisodeEnds) -> None:
        """Reset: tell the opponent policy who won the ended races, then (training) start new ones after
        :meth:`before_auto_reset`."""
        if isinstance(self.opponent_policy, RecordingOpponent):
            self.opponent_policy.record(ends.worlds, self.learner_won())
        if self.training and (self.sync_free or ends.worlds.any()):
            self.stats["nonfinite_resets"] += ((self.world_nonfinite != 0) & ends.worlds).sum()
            self.before_auto_reset(ends.worlds)
            restart_worlds(self, ends.worlds, every_world=self.sync_free)
            self.episode_length_buf.masked_fill_(per_row(ends.worlds, len(self.learner_slots)), 0)
        else:
            self._fresh = torch.zeros_like(self.finished)

    def before_auto_reset(self, worlds: torch.Tensor) -> None:
        """Hook: called in :meth:`step` just before the worlds in the bool mask ``worlds`` reset, with the step's end
        state in place (:meth:`peek_observations` observes it). Does nothing here."""

    def get_observations(self) -> TensorDict:
        """Observe: record this step in the history and return the learner drones' ``policy`` and ``critic`` groups
        (the same tensor unless the environment's ``critic`` is ``race``)."""
        self.observer.record(self.last_action, self._fresh)
        if self.opponent_observer is not None:
            self.opponent_observer.record(self.last_action, self._fresh)
        return self.observer.rows(self.learner_idx)

    # Reset

    def reset(self) -> TensorDict:
        """Reset every world and return the learner observations."""
        restart_worlds(self, torch.ones(self.world_count, dtype=torch.bool, device=self.device))
        self.episode_length_buf.zero_()
        return self.get_observations()

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
