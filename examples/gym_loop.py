"""Fly spiral's gymnasium environment in a plain loop with random actions, as any gymnasium user would.

    python examples/gym_loop.py

``gymnasium.make_vec`` gives one batched env (N drones stepped together, same-step autoreset);
``gymnasium.make`` gives a single-drone env for tools that expect a plain ``gymnasium.Env``.
"""

from __future__ import annotations

import gymnasium
import numpy as np

import spiral.env  # noqa: F401  (registers spiral/Race-v0)


def vector_loop(steps: int = 200) -> None:
    """8 drones on the shipped oval, random actions; episodes restart by themselves."""
    envs = gymnasium.make_vec("spiral/Race-v0", num_envs=8, track="oval4", seed=0,
                              env_cfg={"obs": {"history_len": 4}})
    print(f"vector env: {envs.num_envs} drones, observation {envs.single_observation_space.shape}, "
          f"action {envs.single_action_space}, autoreset {envs.metadata['autoreset_mode'].value}")
    envs.reset(seed=0)
    envs.action_space.seed(0)
    returns, finished = np.zeros(envs.num_envs), []
    for _ in range(steps):
        _, rewards, terminated, truncated, infos = envs.step(envs.action_space.sample())
        returns += rewards
        for i in np.flatnonzero(terminated | truncated):
            # obs[i] already starts the next race; infos["final_obs"][i] is where the last one ended.
            finished.append((returns[i], bool(infos["final_info"]["crashed"][i])))
            returns[i] = 0.0
    crashes = sum(c for _, c in finished)
    print(f"{steps} steps: {len(finished)} episodes ended ({crashes} crashes), "
          f"mean return {np.mean([r for r, _ in finished]) if finished else float('nan'):.2f}")
    envs.close()


def single_episode() -> None:
    """One episode of the single-drone env."""
    env = gymnasium.make("spiral/Race-v0", track="oval4", env_cfg={"obs": {"history_len": 4}})
    env.reset(seed=0)
    env.action_space.seed(0)
    total, steps, done = 0.0, 0, False
    while not done:
        _, reward, terminated, truncated, info = env.step(env.action_space.sample())
        total, steps, done = total + reward, steps + 1, terminated or truncated
    print(f"single env: episode of {steps} steps, return {total:.2f}, {info}")
    env.close()


if __name__ == "__main__":
    vector_loop()
    single_episode()
