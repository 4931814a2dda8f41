"""Batched drone races on torch tensors over zero-copy views of the Warp simulator state."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import warp as wp
from tensordict import TensorDict

from spiral.config.airframe import AirframeCfg
from spiral.config.env import EnvCfg, SeparationCfg
from spiral.config.sim import SimCfg
from spiral.config.track import TrackSpec
from spiral.core.outcome import race_winner
from spiral.core.policy import OpponentPolicy, RecordingOpponent, ResettingOpponent
from spiral.core.scenario import race_teams, team_slots
from spiral.env.observations import ObservationBuilder, nearest_others
from spiral.env.rewards import REWARD_TERMS, StepOutcome, compute_rewards
from spiral.env.separation import separation_offsets
from spiral.env.starts import sample_box_starts, sample_track_starts
from spiral.sim import COLLISION_KINDS, World

__all__ = ["RaceEnv", "summarize_stats"]


def _heading(quat: torch.Tensor) -> torch.Tensor:
    """Body x axis in the world frame from (x, y, z, w) quaternions."""
    x, y, z, w = quat.unbind(-1)
    return torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], dim=-1)


def summarize_stats(s: dict[str, float]) -> dict[str, float]:
    """Means per ended learner episode from the sums of :meth:`RaceEnv.take_stats` (sums of several envs add)."""
    n = max(s["episodes"], 1.0)
    out = {"episodes": s["episodes"], "success": s["successes"] / n,
           "lap_time": s["lap_time_sum"] / s["laps"] if s["laps"] else float("nan"),
           "health/nonfinite_resets": s["nonfinite_resets"]}
    out.update({f"crash/{k}": s[f"crash_{k}"] / n for k in COLLISION_KINDS})
    out.update({f"Episode_Reward/{k}": s[f"term_{k}"] / n for k in REWARD_TERMS})
    return out


class RaceEnv:
    """``world_count`` races of ``drones_per_world`` drones; the learner drives ``learner_slots`` of each world.

    Each learner drone is one environment for PPO (``num_envs = world_count · len(learner_slots)``). Opponent
    slots act from an injected :data:`OpponentPolicy`, or are absent when none is set. A world is reset when any
    of its learner drones crashes or finishes, at its time limit, or when its state turns non-finite
    (``health/nonfinite_resets``); learner drones cut short by another's end get ``time_outs``. With
    ``auto_reset=False`` (evaluation) drones that are done stay frozen and nothing resets.
    """

    def __init__(
        self,
        track: TrackSpec,
        airframe: AirframeCfg,
        sim: SimCfg,
        cfg: EnvCfg,
        *,
        world_count: int,
        drones_per_world: int,
        learner_slots: Sequence[int] = (0,),
        device: str = "cpu",
        seed: int = 0,
        auto_reset: bool = True,
    ) -> None:
        if sim.control_mode != "pid":
            raise ValueError("RaceEnv drives the PID: sim.control_mode must be 'pid'")
        self.track, self.cfg, self.auto_reset = track, cfg, auto_reset
        self.world = World(track, airframe, sim, world_count=world_count, drones_per_world=drones_per_world,
                           device=device)
        self.device = torch.device(device)
        self.world_count, self.drones_per_world = world_count, drones_per_world
        self.drone_count = world_count * drones_per_world
        self.learner_slots = list(learner_slots)
        self.opponent_slots = [s for s in range(drones_per_world) if s not in self.learner_slots]
        base = torch.arange(world_count, device=self.device)[:, None] * drones_per_world
        self.learner_idx = (base + torch.tensor(self.learner_slots, device=self.device)).flatten()
        self.opponent_idx = (base + torch.tensor(self.opponent_slots, device=self.device, dtype=torch.long)).flatten()
        self.slot_team = torch.tensor([s in self.opponent_slots for s in range(drones_per_world)],
                                      dtype=torch.long, device=self.device)
        """Team of each slot: 0 learners, 1 opponents."""
        self.race_team = torch.tensor(race_teams(drones_per_world), dtype=torch.long, device=self.device)
        """Team of each slot in the race format, whoever drives it (:func:`~spiral.core.scenario.race_teams`).
        Observed with ``obs.teammates``."""
        team = self.slot_team.tolist()
        self.other_slots = torch.tensor(
            [sorted((j for j in range(drones_per_world) if j != s), key=lambda j: (team[j] == team[s], j))
             for s in range(drones_per_world)], dtype=torch.long, device=self.device).view(drones_per_world, -1)
        """(D, D - 1): the other slots of each slot's world as the race critic lists them, opponents first."""
        self.num_envs = self.learner_idx.numel()
        self.dt = self.world.time_step
        self.time_limit = cfg.episode.time_limit_s or track.time_limit_s
        self.max_episode_length = math.ceil(self.time_limit / self.dt)
        self.passes_needed = len(track.gates) * track.laps + 1
        self.generator = torch.Generator(device=self.device).manual_seed(seed)
        self.opponent_policy: OpponentPolicy | None = None
        self.shield_scale = 1.0 if cfg.shield is not None and auto_reset else 0.0
        """Gain factor of the training shield (``cfg.shield``; never in a non-resetting, evaluation env)."""
        self.obs_builder = ObservationBuilder(cfg.obs, self.drone_count, device=self.device)
        self._bind_views()
        self._alloc_buffers()
        self.reset()

    # Setup

    def _bind_views(self) -> None:
        s, r = self.world.state, self.world.race
        t = wp.to_torch
        self.pos, self.vel, self.quat, self.omega = t(s.pos), t(s.vel), t(s.quat), t(s.omega)
        self.rpy, self.integral, self.cmd = t(self.world.rpy), t(self.world.integral), t(self.world.cmd)
        self.next_gate, self.gates_passed, self.step_passes = t(r.next_gate), t(r.gates_passed), t(r.step_passes)
        self.pass_time, self.step_collision, self.out = t(r.pass_time), t(r.step_collision), t(r.crashed)
        self.crash_time = t(r.crash_time)
        self.world_substeps, self.world_nonfinite = t(r.world_substeps), t(r.world_nonfinite)
        self.gate_center = torch.tensor(self.track.gate_centers(), dtype=torch.float32, device=self.device)
        self.gate_forward = torch.tensor(self.track.gate_forward(), dtype=torch.float32, device=self.device)

    def _alloc_buffers(self) -> None:
        n, dev = self.drone_count, self.device
        self.last_action = torch.zeros(n, 4, device=dev)
        self.finished = torch.zeros(n, dtype=torch.bool, device=dev)
        """Lap(s) completed without collision."""
        self.crashed = torch.zeros(n, dtype=torch.bool, device=dev)
        """Collided since the reset."""
        self.absent = torch.zeros(n, dtype=torch.bool, device=dev)
        """Slot not in the race (an opponent slot with no opponent policy)."""
        self.lap_time = torch.zeros(n, device=dev)
        self.priority = torch.zeros(n, device=dev)
        """Random priority of each drone for the race, drawn at its start (observed with ``obs.priority``)."""
        self.intervention = torch.zeros(n, device=dev)
        """Length of the training shield's target shift at full gain in the last step [m]."""
        self.crash_kind = torch.zeros(n, dtype=torch.int32, device=dev)
        self.episode_length_buf = torch.zeros(self.num_envs, dtype=torch.long, device=dev)
        self.term_sums = {name: torch.zeros(n, device=dev) for name in REWARD_TERMS}
        self.cut_time = torch.full((self.world_count,), math.inf, device=dev)
        """Race time at which each world's episode is cut short (``episode.start_cut_prob``), else inf [s]."""
        self.contested = torch.zeros(self.world_count, dtype=torch.bool, device=dev)
        """Start-box race against opponents whose winner is not known yet."""
        self._wp_mask = wp.zeros(self.world_count, dtype=wp.int32, device=self.world.device)
        self._wp_pos = wp.zeros(n, dtype=wp.vec3, device=self.world.device)
        self._wp_vel = wp.zeros(n, dtype=wp.vec3, device=self.world.device)
        self._wp_yaw = wp.zeros(n, dtype=wp.float32, device=self.world.device)
        self._wp_gate = wp.zeros(n, dtype=wp.int32, device=self.world.device)
        self.stats = self._empty_stats()

    def _empty_stats(self) -> dict[str, float]:
        stats = {"episodes": 0.0, "successes": 0.0, "lap_time_sum": 0.0, "laps": 0.0, "nonfinite_resets": 0.0}
        stats.update({f"crash_{kind}": 0.0 for kind in COLLISION_KINDS})
        stats.update({f"term_{name}": 0.0 for name in REWARD_TERMS})
        return stats

    def set_training_progress(self, fraction: float) -> None:
        """Tell the env how far its training stage is (fraction of its iterations): schedules follow it."""
        if self.cfg.shield is not None and self.auto_reset:
            self.shield_scale = self.cfg.shield.scale(fraction)

    def set_opponent_policy(self, policy: OpponentPolicy | None) -> None:
        """Drive the opponent slots with ``policy`` from the next reset on (``None``: the slots are absent)."""
        self.opponent_policy = policy

    # Reset

    def reset(self) -> TensorDict:
        """Reset every world and return the learner observations."""
        self._reset_worlds(torch.ones(self.world_count, dtype=torch.bool, device=self.device))
        self.episode_length_buf.zero_()
        return self.get_observations()

    def _reset_worlds(self, worlds: torch.Tensor) -> None:
        """Draw new starts for the worlds in the bool mask ``worlds`` and reset them in the simulator.

        Starts are drawn for those worlds only, in world order, so a reset of every world draws what it always did.
        """
        d = self.drones_per_world
        idx = worlds.nonzero().squeeze(1)
        n = idx.numel()
        pos, yaw = sample_box_starts(self.track, n, d, self.generator, device=self.device)
        vel = torch.zeros_like(pos)
        gate = torch.zeros(n, d, dtype=torch.int32, device=self.device)
        box = torch.ones(n, dtype=torch.bool, device=self.device)
        if self.auto_reset and self.cfg.episode.track_start_prob > 0:
            t_pos, t_vel, t_yaw, t_gate = sample_track_starts(
                self.track, n, d, self.generator, max_speed=self.cfg.episode.track_start_speed, device=self.device)
            use = (torch.rand(n, generator=self.generator, device=self.device) < self.cfg.episode.track_start_prob)
            pos, vel = torch.where(use[:, None, None], t_pos, pos), torch.where(use[:, None, None], t_vel, vel)
            yaw, gate = torch.where(use[:, None], t_yaw, yaw), torch.where(use[:, None], t_gate.int(), gate)
            box = ~use
        t = wp.to_torch
        t(self._wp_mask).copy_(worlds.int())
        t(self._wp_pos).view(-1, d, 3)[idx] = pos
        t(self._wp_vel).view(-1, d, 3)[idx] = vel
        t(self._wp_yaw).view(-1, d)[idx] = yaw
        t(self._wp_gate).view(-1, d)[idx] = gate
        self.world.reset(self._wp_mask, self._wp_pos, self._wp_yaw, init_vel=self._wp_vel,
                         init_next_gate=self._wp_gate)
        drones = worlds.repeat_interleave(d)
        self._reset_drone_buffers(drones)
        if self.cfg.obs.priority:
            self.priority[drones] = torch.rand(n * d, generator=self.generator, device=self.device)
        self.contested[idx] = box & self._teams_race()
        if self.auto_reset and self.cfg.episode.start_cut_prob > 0:
            cut = box & (torch.rand(n, generator=self.generator, device=self.device) < self.cfg.episode.start_cut_prob)
            self.cut_time[idx] = torch.where(cut, self.cfg.episode.start_cut_s, math.inf)
        if isinstance(self.opponent_policy, ResettingOpponent):
            self.opponent_policy.reset(worlds)

    def _teams_race(self) -> bool:
        """Whether drones of both race teams take part (opponents are driven, or the learner drives both teams)."""
        driven = self.learner_slots + (self.opponent_slots if self.opponent_policy is not None else [])
        return len({int(self.race_team[s]) for s in driven}) > 1

    def _reset_drone_buffers(self, drones: torch.Tensor) -> None:
        for buf in (self.last_action, self.lap_time, self.crash_kind, *self.term_sums.values()):
            buf[drones] = 0
        self.finished[drones] = False
        self.crashed[drones] = False
        absent = torch.zeros_like(drones)
        if self.opponent_policy is None and self.opponent_idx.numel():
            absent[self.opponent_idx] = True
        self.absent[drones] = absent[drones]
        self.out[drones & absent] = 1
        self.cmd[drones] = torch.cat([self.pos[drones], self.rpy[drones, 2:3]], dim=-1)
        self._fresh = drones

    # Step

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        """Apply learner ``actions`` (num_envs, 4), advance one control step, reset finished worlds.

        Returns:
            Learner observations, rewards (num_envs,), dones (num_envs,) and extras with ``time_outs`` and ``log``.
        """
        all_actions = self._gather_actions(actions)
        prev_gate = self.next_gate.long().clone()
        dist_before = self._gate_distance(prev_gate)
        self._apply_actions(all_actions)
        self.world.step()
        outcome, crashed_now, finished_now = self._race_events(prev_gate, dist_before)
        rewards, terms = compute_rewards(outcome, self.cfg.reward)
        for name, value in terms.items():
            self.term_sums[name] += value
        terminated = (crashed_now | finished_now)[self.learner_idx]
        world_done = self._world_done(terminated)
        learner_world_done = world_done.repeat_interleave(len(self.learner_slots))
        time_outs = learner_world_done & ~terminated
        dones = terminated | time_outs
        self.episode_length_buf += 1
        log = self._log_episodes(dones, world_done)
        if world_done.any() and isinstance(self.opponent_policy, RecordingOpponent):
            ended = world_done.nonzero().squeeze(1)
            self.opponent_policy.record(ended, self.learner_won()[ended])
        if self.auto_reset and world_done.any():
            self.stats["nonfinite_resets"] += float((self.world_nonfinite != 0).sum())
            self._reset_worlds(world_done)
            self.episode_length_buf[learner_world_done] = 0
        else:
            self._fresh = torch.zeros_like(self.finished)
        obs = self.get_observations()
        return obs, rewards[self.learner_idx], dones, {"time_outs": time_outs, "log": log}

    def _gather_actions(self, learner_actions: torch.Tensor) -> torch.Tensor:
        actions = torch.zeros(self.drone_count, 4, device=self.device)
        actions[self.learner_idx] = learner_actions.to(self.device).clamp(-1.0, 1.0)
        if self.opponent_policy is not None and self.opponent_idx.numel():
            with torch.no_grad():
                opp = self.opponent_policy(self._observe(self.opponent_idx))
            actions[self.opponent_idx] = opp.to(self.device).clamp(-1.0, 1.0)
        return actions

    def _apply_actions(self, actions: torch.Tensor) -> None:
        a = self.cfg.action
        if a.mode == "relative":
            target = self.pos + a.pos_scale * actions[:, :3]
            yaw = self.rpy[:, 2] + math.radians(a.yaw_scale_deg) * actions[:, 3]
        else:
            lo = torch.tensor(self.track.bounds.min, device=self.device)
            hi = torch.tensor(self.track.bounds.max, device=self.device)
            target = lo + (actions[:, :3] + 1.0) * 0.5 * (hi - lo)
            yaw = math.pi * actions[:, 3]
        racing = ~(self.out.bool())
        if a.separation is not None:
            target = target + self._separation_shift(racing, a.separation)
        shield = self.cfg.shield
        if shield is not None and self.auto_reset:
            shift = self._separation_shift(racing, shield.filter)
            self.intervention = shift.norm(dim=-1)
            target = target + self.shield_scale * shift
        self.cmd[racing] = torch.cat([target, yaw[:, None]], dim=-1)[racing]
        self.last_action = actions

    def _separation_shift(self, racing: torch.Tensor, cfg: SeparationCfg) -> torch.Tensor:
        """Target shift (N, 3) of every drone away from the others by the separation rule ``cfg``."""
        w, d = self.world_count, self.drones_per_world
        shift = separation_offsets(self.pos.view(w, d, 3), self.vel.view(w, d, 3), racing.view(w, d), cfg)
        return shift.view(-1, 3)

    def _race_events(self, prev_gate: torch.Tensor, dist_before: torch.Tensor):
        """Collisions, gate passes and finished laps of the step, as a reward outcome."""
        racing = ~(self.crashed | self.finished | self.absent)
        crashed_now = racing & (self.step_collision != 0)
        self.crashed |= crashed_now
        self.crash_kind = torch.where(crashed_now, self.step_collision, self.crash_kind)
        finished_now = racing & ~crashed_now & (self.gates_passed >= self.passes_needed)
        self.finished |= finished_now
        self.lap_time = torch.where(finished_now, self.pass_time, self.lap_time)
        self.out[finished_now] = 1  # a finished drone leaves the race: frozen, no longer an obstacle
        passes = torch.where(racing, self.step_passes, torch.zeros_like(self.step_passes))
        outcome = StepOutcome(
            dist_before=dist_before,
            dist_after=self._gate_distance(prev_gate),
            gates_passed=passes,
            crashed_now=crashed_now,
            heading=_heading(self.quat),
            to_gate=self.gate_center[self.next_gate.long()] - self.pos,
            lap_time=torch.where(finished_now, self.lap_time, torch.zeros_like(self.lap_time)),
            nearest=self._nearest_distance() if self.cfg.reward.proximity > 0 else None,
            race_result=(self._race_result(racing & ~crashed_now, finished_now, crashed_now)
                         if self.cfg.reward.win > 0 else None),
            intervention=torch.where(racing, self.intervention, 0.0) if self.cfg.shield is not None else None,
        )
        for name in ("dist_before", "dist_after"):  # no reward for frozen drones
            setattr(outcome, name, torch.where(racing, getattr(outcome, name), torch.zeros_like(dist_before)))
        return outcome, crashed_now, finished_now

    def _race_result(self, racing: torch.Tensor, finished_now: torch.Tensor, crashed_now: torch.Tensor) -> torch.Tensor:
        """+1 / −1 per racing drone of the winning / losing race team in the contested worlds decided this step.

        The winner (:func:`~spiral.core.outcome.race_winner`) is the team of the step's earliest finisher (lap times
        are interpolated within the step); drones already out (crashed, finished, absent) are not paid, nor anyone
        when two teams finish at exactly the same time. With ``reward.forfeit`` a drone that crashes while its
        race is undecided gets −1 at that step (a crash forfeits the race).
        """
        w, d = self.world_count, self.drones_per_world
        fin = finished_now.view(w, d)
        decided = self.contested & fin.any(dim=1)
        result = torch.zeros(w, d, device=self.device)
        if self.cfg.reward.forfeit:
            result = -(self.contested[:, None] & crashed_now.view(w, d)).float()
        if decided.any():
            winner = race_winner(fin, self.lap_time.view(w, d), team_slots(d))
            same_team = self.race_team[None, :] == winner[:, None]
            paid = decided[:, None] & (winner >= 0)[:, None] & racing.view(w, d)
            result = result + torch.where(same_team, 1.0, -1.0) * paid
            self.contested &= ~decided
        return result.flatten()

    def _nearest_distance(self) -> torch.Tensor:
        """Distance of every racing drone to the nearest other drone of its world still racing (else inf)."""
        w, d = self.world_count, self.drones_per_world
        dist = torch.cdist(self.pos.view(w, d, 3), self.pos.view(w, d, 3))
        out = (self.out != 0).view(w, d)
        gone = torch.eye(d, dtype=torch.bool, device=self.device)[None] | out[:, None, :] | out[:, :, None]
        return dist.masked_fill(gone, float("inf")).amin(dim=-1).flatten()

    def _gate_distance(self, gate: torch.Tensor) -> torch.Tensor:
        """Funnel distance sqrt(a² + κ²·l²) of every drone to ``gate``: a along the gate's normal, l across it.

        With κ > 1 lateral error costs more than distance along the normal, so progress pays for lining up in
        front of a gate before crossing its plane rather than for a straight line into its frame.
        """
        rel = self.pos - self.gate_center[gate]
        along = (rel * self.gate_forward[gate]).sum(-1, keepdim=True)
        lateral = rel - along * self.gate_forward[gate]
        kappa = self.cfg.reward.progress_lateral
        return (along.squeeze(-1) ** 2 + kappa**2 * (lateral**2).sum(-1)).sqrt()

    def _world_done(self, terminated: torch.Tensor) -> torch.Tensor:
        """Worlds that end now: a learner drone terminated, the time limit (or the cut of a start), or a non-finite
        state."""
        time_up = self.world_time() >= torch.clamp(self.cut_time, max=self.time_limit) - 1e-6
        return terminated.view(self.world_count, -1).any(dim=1) | time_up | (self.world_nonfinite != 0)

    def _log_episodes(self, dones: torch.Tensor, world_done: torch.Tensor) -> dict[str, float]:
        """Accumulate the ended learner episodes into :attr:`stats` and return their means for rsl-rl's log."""
        if not dones.any():
            return {}
        idx = self.learner_idx[dones]
        fin, crashed = self.finished[idx], self.crashed[idx]
        s = self.stats
        s["episodes"] += idx.numel()
        s["successes"] += float(fin.sum())
        s["laps"] += float(fin.sum())
        s["lap_time_sum"] += float(self.lap_time[idx][fin].sum())
        for kind, bit in COLLISION_KINDS.items():
            s[f"crash_{kind}"] += float(((self.crash_kind[idx] & bit) != 0).sum())
        log = {f"Episode_Reward/{name}": self.term_sums[name][idx].mean() for name in REWARD_TERMS}
        for name in REWARD_TERMS:
            s[f"term_{name}"] += float(self.term_sums[name][idx].sum())
        log["Episode/success"] = fin.float().mean()
        log["Episode/crash"] = crashed.float().mean()
        return log

    def learner_won(self) -> torch.Tensor:
        """Per world, whether the learner's team won the race against the opponent slots (bool, (W,))."""
        w, d = self.world_count, self.drones_per_world
        teams = [self.learner_slots, self.opponent_slots]
        return race_winner(self.finished.view(w, d), self.lap_time.view(w, d), teams) == 0

    def pop_stats(self) -> dict[str, float]:
        """Means over the learner episodes ended since the last call, then start counting afresh."""
        return summarize_stats(self.take_stats())

    def take_stats(self) -> dict[str, float]:
        """Sums over the learner episodes ended since the last call (see :func:`summarize_stats`); counting
        starts afresh."""
        s, self.stats = self.stats, self._empty_stats()
        return s

    def current_observations(self) -> TensorDict:
        """The learner observations of the last step or reset (no new history entry)."""
        return self._observe(self.learner_idx)

    # Observations


    def get_observations(self) -> TensorDict:
        """Observations of the learner drones: ``policy`` and ``critic`` groups (the same tensor unless the
        environment's ``critic`` is ``race``)."""
        self._update_history()
        self._obs_all = self._build_observations()
        if self.cfg.critic == "race":
            self._critic_all = torch.cat([self._obs_all, self._race_state()], dim=-1)
        return self._observe(self.learner_idx)

    def _update_history(self) -> None:
        w, d = self.world_count, self.drones_per_world
        present = (self.out == 0).view(w, d)
        pos_w = self.pos.view(w, d, 3)
        near_idx, near_mask = nearest_others(pos_w, present)
        near_pos = torch.gather(pos_w, 1, near_idx.view(w, -1, 1).expand(-1, -1, 3)).view(w, d, 2, 3)
        rel_opp = (near_pos - pos_w[:, :, None]) * near_mask[..., None]
        gate_idx = torch.stack([self.next_gate.long(), (self.next_gate.long() + 1) % self.gate_center.shape[0]], 1)
        rel_gates = self.gate_center[gate_idx] - self.pos[:, None]
        features = torch.cat([rel_opp.view(-1, 6), rel_gates.view(-1, 6), self.last_action], dim=-1)
        self.obs_builder.push(features, self._fresh)
        self._near = (near_idx, near_mask, gate_idx)

    def _observe(self, idx: torch.Tensor) -> TensorDict:
        """Observation rows of drones ``idx`` (from the last :meth:`get_observations`)."""
        obs = self._obs_all[idx]
        critic = self._critic_all[idx] if self.cfg.critic == "race" else obs
        return TensorDict({"policy": obs, "critic": critic}, batch_size=[idx.numel()])

    def _race_state(self) -> torch.Tensor:
        """Critic inputs of every drone about every other drone of its world (:attr:`other_slots` order), shape
        (N, 8 (D - 1)): relative position and velocity (zero once the other left the race), whether it still races,
        and how many more gates it has passed."""
        w, d = self.world_count, self.drones_per_world
        others = self.other_slots
        pos, vel = self.pos.view(w, d, 3), self.vel.view(w, d, 3)
        racing = (self.out == 0).view(w, d)[:, others].float()[..., None]
        gates = self.gates_passed.view(w, d).float()
        features = [(pos[:, others] - pos[:, :, None]) * racing, (vel[:, others] - vel[:, :, None]) * racing, racing,
                    (gates[:, others] - gates[:, :, None])[..., None]]
        return torch.cat(features, dim=-1).reshape(w * d, 8 * (d - 1))

    def _build_observations(self) -> torch.Tensor:
        """Observation of every drone, shape (N, obs_dim)."""
        c = self.cfg.obs
        near_idx, near_mask, gate_idx = self._near
        ego = torch.cat([self.pos, self.vel, self.rpy, self.omega], dim=-1)
        presence = near_mask.view(-1, 2).float()
        extras = []
        if c.gate_normals:
            extras.append(self.gate_forward[gate_idx].view(-1, 6))
        if c.pid_integral:
            extras.append(self.integral)
        w, d = self.world_count, self.drones_per_world
        if c.opponent_velocity or c.closest_approach:
            vel_w = self.vel.view(w, d, 3)
            near_vel = torch.gather(vel_w, 1, near_idx.view(w, -1, 1).expand(-1, -1, 3)).view(w, d, 2, 3)
            rel_vel = (near_vel - vel_w[:, :, None]) * near_mask[..., None]
        if c.opponent_velocity:
            extras.append(rel_vel.view(-1, 6))
        if c.teammates:
            mate = self.race_team[near_idx] == self.race_team[None, :, None]
            extras.append((mate & near_mask).view(-1, 2).float())
        if c.closest_approach:
            extras.append(self._closest_approach(near_idx, near_mask, rel_vel))
        if c.priority:
            prio = self.priority.view(self.world_count, self.drones_per_world)
            higher = (torch.gather(prio, 1, near_idx.view(self.world_count, -1)).view(near_idx.shape)
                      - prio[:, :, None]) * near_mask
            extras.append(torch.cat([self.priority[:, None], higher.view(-1, 2)], dim=-1))
        return self.obs_builder.build(ego, presence, extras)

    def _closest_approach(self, near_idx: torch.Tensor, near_mask: torch.Tensor, rel_vel: torch.Tensor) -> torch.Tensor:
        """Per nearest drone (N, 2 · 4): its position relative to the drone at their closest approach within the
        horizon, both at constant velocity, and the time of that approach over the horizon (zeros when absent)."""
        w, d = self.world_count, self.drones_per_world
        pos_w = self.pos.view(w, d, 3)
        near_pos = torch.gather(pos_w, 1, near_idx.view(w, -1, 1).expand(-1, -1, 3)).view(w, d, 2, 3)
        rel = (near_pos - pos_w[:, :, None]) * near_mask[..., None]
        horizon = self.cfg.obs.approach_horizon_s
        t = (-(rel * rel_vel).sum(-1) / rel_vel.square().sum(-1).clamp_min(1e-9)).clamp(0.0, horizon)
        miss = rel + rel_vel * t[..., None]
        return torch.cat([miss, (t / horizon)[..., None]], dim=-1).view(-1, 8)

    @property
    def obs_dim(self) -> int:
        """Length of one observation vector."""
        return self.obs_builder.obs_dim

    def world_time(self) -> torch.Tensor:
        """Simulated time of each world since its reset [s]."""
        return self.world_substeps.float() * self.world.sim.dt
