"""PPO's mini-batches from one gather per update instead of one per mini-batch.

rsl-rl's ``RolloutStorage.mini_batch_generator`` draws one permutation per update and, for each of the
``epochs × mini_batches`` mini-batches, gathers every field of the rollout by index. The permutation is the same in
every epoch, so the same rows are gathered ``epochs`` times. :func:`gather_once` permutes the flattened rollout once
and yields contiguous slices (views) of it: the same rows in the same order, i.e. the same update to the last bit,
with one gather instead of ``epochs × mini_batches``. :class:`GatherOncePPO` is rsl-rl's PPO with a storage that
hands out its mini-batches so; ``PPOCfg.to_rsl_rl`` names it as the algorithm's class.
"""

from __future__ import annotations

from collections.abc import Generator

import torch
from rsl_rl.algorithms import PPO
from rsl_rl.env import VecEnv
from rsl_rl.storage import RolloutStorage
from tensordict import TensorDict

__all__ = ["GatherOncePPO", "GatherOnceStorage", "gather_once"]


def gather_once(storage: RolloutStorage, num_mini_batches: int,
                num_epochs: int = 8) -> Generator[RolloutStorage.Batch, None, None]:
    """Drop-in for ``RolloutStorage.mini_batch_generator`` (feed-forward RL): same permutation, same batches."""
    if storage.training_type != "rl":
        raise ValueError("gather_once serves reinforcement learning storage only")
    size = storage.num_envs * storage.num_transitions_per_env // num_mini_batches
    indices = torch.randperm(num_mini_batches * size, requires_grad=False, device=storage.device)

    def permuted(t: torch.Tensor) -> torch.Tensor:
        return t.flatten(0, 1)[indices]

    observations = permuted(storage.observations)
    actions, values, returns = permuted(storage.actions), permuted(storage.values), permuted(storage.returns)
    old_log_prob, advantages = permuted(storage.actions_log_prob), permuted(storage.advantages)
    old_params = tuple(permuted(p) for p in storage.distribution_params)  # type: ignore[union-attr]
    for _ in range(num_epochs):
        for i in range(num_mini_batches):
            rows = slice(i * size, (i + 1) * size)
            yield RolloutStorage.Batch(
                observations=observations[rows], actions=actions[rows], values=values[rows],
                advantages=advantages[rows], returns=returns[rows], old_actions_log_prob=old_log_prob[rows],
                old_distribution_params=tuple(p[rows] for p in old_params),
            )


class GatherOnceStorage(RolloutStorage):
    """rsl-rl's rollout storage whose mini-batches come from :func:`gather_once`."""

    def mini_batch_generator(self, num_mini_batches: int,
                             num_epochs: int = 8) -> Generator[RolloutStorage.Batch, None, None]:
        return gather_once(self, num_mini_batches, num_epochs)


class GatherOncePPO(PPO):
    """rsl-rl's PPO over a :class:`GatherOnceStorage`: the same updates, one gather of the rollout per update."""

    @staticmethod
    def construct_algorithm(obs: TensorDict, env: VecEnv, cfg: dict, device: str) -> PPO:
        alg = PPO.construct_algorithm(obs, env, cfg, device)
        alg.storage = GatherOnceStorage("rl", env.num_envs, cfg["num_steps_per_env"], obs, [env.num_actions], device)
        return alg
