"""gymnasium adapters: registration, vector and single env, same-step autoreset, opponents, tracks."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode, VectorEnv

import spiral.env  # noqa: F401  (registers spiral/Race-v0)
from spiral.adapters import RaceSingleEnv, RaceVectorEnv
from spiral.config import AIRFRAMES, SimCfg, load_track
from spiral.env import RaceEnv, RaceSetting
from spiral.env.factory import SHIPPED_TRACKS, resolve_track

DOWN = np.array([0.0, 0.0, -1.0, 0.0], dtype=np.float32)
"""Relative action: aim 2 m below the drone, so it hits the ground within a second."""


def test_make_vec_returns_one_batched_vector_env(small_env):
    """Return a RaceVectorEnv of N drones with single and batched Box spaces and same-step autoreset."""
    envs = gymnasium.make_vec("spiral/Race-v0", num_envs=3, track="oval4", env_cfg=small_env)
    assert isinstance(envs, VectorEnv) and isinstance(envs, RaceVectorEnv)
    dim = envs.race.obs_dim
    assert envs.num_envs == 3 and envs.race.world_count == 3
    assert envs.single_observation_space.shape == (dim,) and envs.single_observation_space.dtype == np.float32
    assert envs.observation_space.shape == (3, dim)
    assert envs.single_action_space.shape == (4,) and envs.action_space.shape == (3, 4)
    assert envs.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    obs, infos = envs.reset(seed=0)
    assert obs.shape == (3, dim) and obs.dtype == np.float32 and infos == {}
    obs, rew, term, trunc, _ = envs.step(envs.action_space.sample())
    assert obs.shape == (3, dim) and rew.shape == term.shape == trunc.shape == (3,)


@pytest.mark.filterwarnings("ignore:.*Box observation space.*infinity")  # positions, velocities are unbounded
def test_make_returns_a_single_env_that_passes_check_env(small_env):
    """Pass gymnasium's env checker (seeded resets, determinism, spaces, fresh arrays)."""
    env = gymnasium.make("spiral/Race-v0", track="oval4", env_cfg=small_env)
    assert isinstance(env.unwrapped, RaceSingleEnv)
    check_env(env.unwrapped)
    obs, _ = env.reset(seed=5)
    assert obs in env.observation_space


def test_final_obs_is_the_last_observation_before_the_reset(small_env):
    """Put the crash-step observation of a non-resetting race in infos['final_obs'], the new race in obs."""
    envs = RaceVectorEnv(1, track="oval4", env_cfg=small_env, seed=3)
    ref = RaceEnv(RaceSetting(load_track(SHIPPED_TRACKS / "oval4.yaml"), AIRFRAMES["cf2x"], SimCfg()), small_env,
                  world_count=1, drones_per_world=1, seed=3, training=False)
    first, _ = envs.reset()
    np.testing.assert_allclose(first[0], ref.reset()["policy"][0].numpy(), atol=1e-6)
    for _ in range(200):
        obs, _, term, trunc, infos = envs.step(DOWN[None])
        ref_obs, _, ref_done, _ = ref.step(torch.from_numpy(DOWN[None]))
        if term[0] or trunc[0]:
            break
    assert term[0] and not trunc[0] and bool(ref_done[0])
    assert infos["_final_obs"].tolist() == [True]
    np.testing.assert_allclose(infos["final_obs"][0], ref_obs["policy"][0].numpy(), atol=1e-6)
    assert infos["final_info"]["crashed"][0] and not infos["final_info"]["success"][0]
    assert np.isnan(infos["final_info"]["lap_time"][0])
    assert abs(obs[0, 2] - first[0, 2]) < 0.5  # back at start height, not on the ground


def test_time_limit_truncates_instead_of_terminating(small_env):
    """Report the episode time limit as truncated, not terminated, in the single env."""
    cfg = small_env.model_copy(update={"episode": small_env.episode.model_copy(update={"time_limit_s": 0.25})})
    env = RaceSingleEnv(track="oval4", env_cfg=cfg)
    env.reset(seed=0)
    results = [env.step(np.zeros(4, dtype=np.float32)) for _ in range(env.race.max_episode_length)]
    assert [r[3] for r in results] == [False] * (len(results) - 1) + [True]
    assert not any(r[2] for r in results)
    info = results[-1][4]
    assert (info["success"], info["crashed"], np.isnan(info["lap_time"])) == (False, False, True)


def test_torch_arrays_stay_tensors_on_the_env_device(small_env):
    """Return torch tensors for array_type='torch' and accept torch actions."""
    envs = gymnasium.make_vec("spiral/Race-v0", num_envs=4, scenario="2v2", array_type="torch", env_cfg=small_env)
    assert envs.race.world_count == 2
    obs, _ = envs.reset(seed=1)
    obs, rew, term, trunc, _ = envs.step(torch.zeros(4, 4))
    assert isinstance(obs, torch.Tensor) and obs.device == envs.device and obs.dtype == torch.float32
    assert rew.shape == (4,) and term.dtype == trunc.dtype == torch.bool


def test_checkpoint_opponent_flies_the_opponent_slot(policy_checkpoint):
    """Fly the opponent slot of a 1v1 race with a checkpoint's policy, using the checkpoint's env layout."""
    envs = RaceVectorEnv(2, track="oval4", scenario="1v1", opponent=policy_checkpoint)
    race = envs.race
    assert race.obs_builder.layout() == race.opponent_policy.obs_layout
    envs.reset(seed=0)
    envs.step(np.zeros((2, 4), dtype=np.float32))
    assert race.opponent_idx.tolist() == [1, 3] and not race.records.absent[race.opponent_idx].any()
    assert race.last_action[race.opponent_idx].abs().sum() > 0


def test_se_ibr_opponent_is_the_planner(small_env):
    """Drive the opponent slot with the SE-IBR planner when opponent='se-ibr'."""
    from spiral.baselines import PlannerPolicy

    env = RaceSingleEnv(track="oval4", scenario="1v1", opponent="SE-IBR", env_cfg=small_env)
    assert isinstance(env.race.opponent_policy, PlannerPolicy)
    assert not env.race.records.absent[1]


def test_opponent_without_an_opponent_slot_is_refused():
    """Refuse an opponent in a solo race, naming the argument."""
    with pytest.raises(ValueError, match="opponent"):
        RaceSingleEnv(track="oval4", scenario="solo", opponent="se-ibr")


def test_tracks_resolve_by_name_or_path_and_unknown_names_list_the_shipped_ones():
    """Load a shipped track by name or path; name the shipped tracks for an unknown one."""
    assert resolve_track("circuit6") == load_track(SHIPPED_TRACKS / "circuit6.yaml")
    assert resolve_track(SHIPPED_TRACKS / "oval4.yaml").name == "oval4"
    with pytest.raises(FileNotFoundError, match="oval4"):
        resolve_track("no-such-track")
