"""Training worlds that race different scenarios (``StageSpec.mix``) stepped as one environment."""

from __future__ import annotations

import torch
from tensordict import TensorDict

from spiral.config.stage import StageSpec
from spiral.core.policy import OpponentPolicy
from spiral.core.scenario import SCENARIO_DRONES
from spiral.core.seeds import MIX_PART_STRIDE
from spiral.env.race_env import RaceEnv
from spiral.env.setting import RaceSetting
from spiral.env.stats import summarize_stats

__all__ = ["MixedRaceEnv", "training_env"]

class MixedRaceEnv:
    """Named :class:`RaceEnv` parts (one per scenario) stepped together; their learner rows
    are concatenated in part order.

    To PPO it is one env of ``num_envs = Σ part.num_envs`` learner drones. Each part keeps its own worlds, resets,
    opponents and statistics; :meth:`pop_stats` adds the parts' sums and also reports each part's success ratio.
    """

    def __init__(self, parts: dict[str, RaceEnv]) -> None:
        if not parts:
            raise ValueError("MixedRaceEnv needs at least one part")
        layouts = {name: env.obs_builder.layout() for name, env in parts.items()}
        if len({str(v) for v in layouts.values()}) > 1:
            raise ValueError(f"MixedRaceEnv: the parts' observation layouts differ: {layouts}")
        self.parts = parts
        first = next(iter(parts.values()))
        self.cfg, self.device, self.dt, self.obs_builder = first.cfg, first.device, first.dt, first.obs_builder
        self.max_episode_length = max(env.max_episode_length for env in parts.values())
        sizes = [env.num_envs for env in parts.values()]
        self.num_envs = sum(sizes)
        self._sizes = sizes

    @property
    def obs_dim(self) -> int:
        """Length of one observation vector."""
        return self.obs_builder.obs_dim

    @property
    def episode_length_buf(self) -> torch.Tensor:
        """Control steps since each learner drone's episode started, parts concatenated."""
        return torch.cat([env.episode_length_buf for env in self.parts.values()])

    @episode_length_buf.setter
    def episode_length_buf(self, value: torch.Tensor) -> None:
        for env, part in zip(self.parts.values(), value.split(self._sizes), strict=True):
            env.episode_length_buf = part

    def set_opponent_policies(self, policies: dict[str, OpponentPolicy | None]) -> None:
        """Drive each named part's opponent slots with its policy from the next reset on."""
        for name, policy in policies.items():
            self.parts[name].set_opponent_policy(policy)

    def set_training_progress(self, fraction: float) -> None:
        """Pass the stage's progress on to every part."""
        for env in self.parts.values():
            env.set_training_progress(fraction)

    def reset(self) -> TensorDict:
        """Reset every world of every part and return the learner observations."""
        return torch.cat([env.reset() for env in self.parts.values()])

    def current_observations(self) -> TensorDict:
        """The learner observations of the last step or reset."""
        return torch.cat([env.current_observations() for env in self.parts.values()])

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        """One control step of every part; the same returns as :meth:`RaceEnv.step`, rows in part order."""
        joint = self._joint_opponent_actions()
        out = [env.step(a, joint.get(name))
               for (name, env), a in zip(self.parts.items(), actions.split(self._sizes), strict=True)]
        obs = torch.cat([o[0] for o in out])
        rewards = torch.cat([o[1] for o in out])
        dones = torch.cat([o[2] for o in out])
        time_outs = torch.cat([o[3]["time_outs"] for o in out])
        return obs, rewards, dones, {"time_outs": time_outs}

    def _joint_opponent_actions(self) -> dict[str, torch.Tensor]:
        """The opponents' actions of the parts whose opponent policies can act together (``act_together``: pool
        opponents on the sync-free path, sharing one pool), in one pass; none when fewer than two parts can."""
        parts = {name: env for name, env in self.parts.items()
                 if env.opponent_idx.numel() and getattr(env.opponent_policy, "sync_free", False)
                 and hasattr(env.opponent_policy, "act_together")}
        if len(parts) < 2:
            return {}
        policies = [env.opponent_policy for env in parts.values()]
        actions = policies[0].act_together(policies, [env.opponent_observations() for env in parts.values()])
        return dict(zip(parts, actions, strict=True))

    def pop_stats(self) -> dict[str, float]:
        """Means over every part's ended learner episodes, and ``success/<part>`` of each part."""
        per_part = {name: env.stats.take() for name, env in self.parts.items()}
        total = {key: sum(s[key] for s in per_part.values()) for key in next(iter(per_part.values()))}
        out = summarize_stats(total)
        for name, s in per_part.items():
            out[f"success/{name}"] = s["successes"] / max(s["episodes"], 1.0)
        return out


def training_env(setting: RaceSetting, stage: StageSpec, *, device: str, seed: int) -> RaceEnv | MixedRaceEnv:
    """The training env of ``stage``: one :class:`RaceEnv` when all its worlds race alike, else a
    :class:`MixedRaceEnv` over :meth:`StageSpec.world_parts` (the other scenarios of ``stage.mix``), the first part
    with the stage's seed."""
    parts = {
        part.scenario: RaceEnv(setting, stage.env, world_count=part.worlds,
                               drones_per_world=SCENARIO_DRONES[part.scenario], learner_slots=part.learner_slots,
                               device=device, seed=seed + k * MIX_PART_STRIDE)
        for k, part in enumerate(stage.world_parts())
    }
    return next(iter(parts.values())) if len(parts) == 1 else MixedRaceEnv(parts)
