"""gymnasium adapters: ``spiral/Race-v0`` as a batched ``VectorEnv`` over one :class:`RaceEnv`, and as a single Env.

``gymnasium.make_vec("spiral/Race-v0", num_envs=N, track="oval4")`` returns :class:`RaceVectorEnv`: N learner drones
stepped together by one :class:`RaceEnv` (no Python loop, no subprocesses). ``gymnasium.make("spiral/Race-v0")``
returns :class:`RaceSingleEnv`, one learner drone, for tools that expect a plain ``gymnasium.Env``.

Both take the fields of :class:`spiral.env.factory.RaceOptions` as keyword arguments: the track (a YAML path, a shipped
track's name or a ``TrackSpec``), the scenario, the opponents (none, a checkpoint path, ``"se-ibr"`` or any
``OpponentPolicy``), the environment, simulator and airframe settings, the device and the seed. ``import spiral.env``
registers the id; this module sits above ``spiral.baselines`` because it offers the SE-IBR planner as an opponent.
"""

from __future__ import annotations

from typing import Any, ClassVar, Literal

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from spiral.baselines import opponent_policy
from spiral.core.errors import UsageError
from spiral.env.factory import OpponentFactory, RaceOptions, make_race_env
from spiral.env.race_env import RaceEnv

__all__ = ["NAMED_OPPONENTS", "RaceSingleEnv", "RaceVectorEnv"]

NAMED_OPPONENTS: dict[str, OpponentFactory] = {"se-ibr": opponent_policy}
"""Opponents the adapters accept by name: ``"se-ibr"``, the game-theoretic planner (any case)."""


class _RaceEnvWithFinalObs(RaceEnv):
    """A :class:`RaceEnv` that keeps its learner drones' last observation before each automatic world reset.

    RaceEnv resets finished worlds inside ``step`` and returns the first observation of the new episode; gymnasium's
    same-step autoreset also wants the last one of the old episode (``final_obs``). The env's
    :meth:`~RaceEnv.before_auto_reset` hook builds it just before the reset, without moving the history buffer, along
    with how the episode ended.
    """

    final_obs: torch.Tensor
    """Learner observations as the last step left them, before its resets (rows of reset worlds matter)."""
    final_outcome: dict[str, torch.Tensor]
    """Per learner row at the last reset: ``success`` (finished without collision), ``crashed``, ``lap_time`` [s]
    (NaN when not finished)."""

    def before_auto_reset(self, worlds: torch.Tensor) -> None:
        """Record :attr:`final_obs` and :attr:`final_outcome` of the learner rows before ``worlds`` reset."""
        idx, rec = self.learner_idx, self.records
        self.final_obs = self.peek_observations()[idx]
        self.final_outcome = {"success": rec.finished[idx].clone(), "crashed": rec.crashed[idx].clone(),
                              "lap_time": torch.where(rec.finished[idx], rec.lap_time[idx],
                                                      torch.full_like(rec.lap_time[idx], float("nan")))}


def _spaces(obs_dim: int) -> tuple[spaces.Box, spaces.Box]:
    obs = spaces.Box(-np.inf, np.inf, shape=(obs_dim,), dtype=np.float32)
    act = spaces.Box(-1.0, 1.0, shape=(4,), dtype=np.float32)
    return obs, act


class RaceVectorEnv(VectorEnv):
    """``num_envs`` learner drones of one batched :class:`RaceEnv` as a gymnasium vector env.

    Each sub-environment is one learner drone (in ``2v2`` both learner drones of a world, so ``num_envs`` must be
    even). Autoreset mode is ``SAME_STEP``: when a race ends, ``step`` returns the first observation of the next
    race, and ``infos["final_obs"]`` (a dense ``(num_envs, obs_dim)`` array; rows flagged in ``infos["_final_obs"]``
    hold the last observation of the ended episode, the other rows equal the returned observation) plus
    ``infos["final_info"]`` (``success``, ``crashed``, ``lap_time`` per row, flagged by ``_final_info``) describe
    the ended one. ``truncated`` is RaceEnv's ``time_outs`` (time limit, or a team mate's race ended the world's);
    ``terminated`` is a crash or a finished race.

    Args:
        num_envs: Learner drones.
        array_type: ``"numpy"`` (float32 arrays on the CPU) or ``"torch"`` (tensors on ``device``).
        **kwargs: :class:`~spiral.env.factory.RaceOptions` fields (``track``, ``scenario``, ``opponent``,
            ``env_cfg``, ``sim``, ``airframe``, ``device``, ``seed``).
    """

    metadata: ClassVar[dict[str, Any]] = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, num_envs: int = 1, *, array_type: Literal["numpy", "torch"] = "numpy", **kwargs: Any) -> None:
        if array_type not in ("numpy", "torch"):
            raise UsageError(f"array_type: expected 'numpy' or 'torch', got {array_type!r}")
        per_world = 2 if kwargs.get("scenario") == "2v2" and kwargs.get("learner_slots") is None else 1
        if num_envs < 1 or num_envs % per_world:
            raise UsageError(f"num_envs: expected a positive multiple of {per_world}, got {num_envs}")
        self.race = make_race_env(RaceOptions(**kwargs), world_count=num_envs // per_world,
                                  env_class=_RaceEnvWithFinalObs, named_opponents=NAMED_OPPONENTS)
        if self.race.num_envs != num_envs:
            raise UsageError(f"num_envs: {num_envs} is not a multiple of the learner slots {self.race.learner_slots}")
        self.num_envs, self.array_type = num_envs, array_type
        self.single_observation_space, self.single_action_space = _spaces(self.race.obs_dim)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)

    @property
    def device(self) -> torch.device:
        """Device of the simulation and of torch outputs."""
        return self.race.device

    def _out(self, x: torch.Tensor) -> Any:
        return x if self.array_type == "torch" else x.detach().cpu().numpy().copy()

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        """Start new races in every world (``seed`` reseeds the start placements)."""
        super().reset(seed=seed)
        if seed is not None:
            self.race.generator.manual_seed(seed)
        return self._out(self.race.reset()["policy"]), {}

    def step(self, actions: Any) -> tuple[Any, Any, Any, Any, dict[str, Any]]:
        """One control step of every race; ended races restart in the same step (``SAME_STEP``)."""
        actions = torch.as_tensor(actions, dtype=torch.float32, device=self.race.device).reshape(self.num_envs, 4)
        obs, rewards, dones, extras = self.race.step(actions)
        truncated = extras["time_outs"].bool()
        terminated = dones.bool() & ~truncated
        infos: dict[str, Any] = {}
        if bool(dones.any()):
            final = torch.where(dones[:, None], self.race.final_obs, obs["policy"])
            mask = self._out(dones.bool())
            infos = {"final_obs": self._out(final), "_final_obs": mask,
                     "final_info": {k: self._out(v) for k, v in self.race.final_outcome.items()},
                     "_final_info": self._out(dones.bool())}
        return self._out(obs["policy"]), self._out(rewards.float()), self._out(terminated), self._out(truncated), infos

    def close_extras(self, **kwargs: Any) -> None:
        """Drop the simulation."""
        self.race = None  # type: ignore[assignment]


class RaceSingleEnv(gymnasium.Env):
    """One learner drone as a plain ``gymnasium.Env`` (numpy float32 observations, Box action in [−1, 1]⁴).

    ``step`` returns the last observation of a race when it ends (``terminated``: crash or finish; ``truncated``:
    time limit); call ``reset`` to race again. ``info`` holds ``success``, ``crashed`` and ``lap_time`` at the end.
    The arguments are the fields of :class:`~spiral.env.factory.RaceOptions`; ``scenario`` is ``solo`` or ``1v1`` (use
    the vector or PettingZoo env for ``2v2``, where the caller drives two drones).
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, **kwargs: Any) -> None:
        if kwargs.get("scenario") == "2v2":
            raise UsageError("scenario: the single env drives one drone; use gymnasium.make_vec or PettingZoo for 2v2")
        kwargs.pop("render_mode", None)
        self.race = make_race_env(RaceOptions(**kwargs), world_count=1, env_class=_RaceEnvWithFinalObs,
                                  named_opponents=NAMED_OPPONENTS)
        self.observation_space, self.action_space = _spaces(self.race.obs_dim)

    @staticmethod
    def _np(x: torch.Tensor) -> np.ndarray:
        return x.detach().cpu().numpy().astype(np.float32, copy=True)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Start a new race (``seed`` reseeds the start placement)."""
        super().reset(seed=seed)
        if seed is not None:
            self.race.generator.manual_seed(seed)
        return self._np(self.race.reset()["policy"][0]), {}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Fly one control step."""
        action = torch.as_tensor(np.asarray(action, dtype=np.float32), device=self.race.device).reshape(1, 4)
        obs, rewards, dones, extras = self.race.step(action)
        truncated = bool(extras["time_outs"][0])
        terminated = bool(dones[0]) and not truncated
        if not bool(dones[0]):
            return self._np(obs["policy"][0]), float(rewards[0]), False, False, {}
        info = {k: float(v[0]) if k == "lap_time" else bool(v[0]) for k, v in self.race.final_outcome.items()}
        return self._np(self.race.final_obs[0]), float(rewards[0]), terminated, truncated, info
