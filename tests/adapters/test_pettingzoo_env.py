"""PettingZoo view of one race: the parallel API conformance test, and agents leaving as they crash."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

pytest.importorskip("pettingzoo")

from pettingzoo.test import parallel_api_test

from spiral.env.pettingzoo_env import RaceParallelEnv


def test_parallel_env_passes_the_pettingzoo_api_test(small_env):
    """Pass pettingzoo.test.parallel_api_test without warnings, one agent per drone of a 2v2 race."""
    env = RaceParallelEnv("oval4", scenario="2v2", env_cfg=small_env)
    assert env.possible_agents == ["drone_0", "drone_1", "drone_2", "drone_3"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        parallel_api_test(env, num_cycles=60)
    obs, infos = env.reset(seed=0)
    assert set(obs) == set(infos) == set(env.possible_agents)
    assert obs["drone_0"].shape == env.observation_space("drone_0").shape
    assert obs["drone_0"].dtype == np.float32


def test_a_crashed_drone_leaves_while_the_others_race_on(small_env):
    """Terminate only the drone flown into the ground; keep the hovering one racing."""
    env = RaceParallelEnv("oval4", scenario="1v1", env_cfg=small_env)
    env.reset(seed=1)
    down, hover = np.array([0, 0, -1, 0], np.float32), np.zeros(4, np.float32)
    for _ in range(200):
        _, rewards, terminated, truncated, infos = env.step({a: down if a == "drone_0" else hover
                                                             for a in env.agents})
        if terminated.get("drone_0"):
            break
    assert terminated == {"drone_0": True, "drone_1": False} and truncated == {"drone_0": False, "drone_1": False}
    assert infos["drone_0"]["crashed"] and not infos["drone_0"]["success"]
    assert rewards["drone_0"] < 0  # the collision penalty
    assert env.agents == ["drone_1"]
    _, rewards, *_ = env.step({"drone_1": hover})
    assert set(rewards) == {"drone_1"}
