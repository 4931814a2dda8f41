"""The env's sync-free path (the default off a CPU): training steps that never read a value back from the device."""

from __future__ import annotations

import torch

from spiral.config import ObsCfg
from spiral.core.host_syncs import HostSyncCounter
from spiral.env.race_env import restart_worlds
from tests.env.helpers import make_env


def test_a_training_step_with_every_optional_term_makes_no_host_sync(circuit6):
    """Every reward term, track and passage starts and start cuts on: 2v2 steps with resets read nothing back
    on the sync-free path."""
    reward = {"proximity": 1.0, "closing": 1.0, "win": 1.0}
    episode = {"track_start_prob": 0.3, "start_cut_prob": 0.5, "start_cut_s": 0.1,
               "passage_starts": {"share_start": 0.5}}
    env = make_env(circuit6, worlds=8, drones=4, learners=(0, 1), obs=ObsCfg(history_len=3),
                   reward=reward, episode=episode)
    env.sync_free = True
    generator, ended = torch.Generator().manual_seed(0), 0
    with HostSyncCounter() as syncs:
        for _ in range(40):
            _, _, dones, _ = env.step(torch.rand(env.num_envs, 4, generator=generator) * 2 - 1)
            ended += dones.sum()
    assert syncs.total == 0, syncs.sites.most_common(5)
    assert ended > 0


def test_a_sync_free_reset_starts_the_ended_worlds_afresh_and_leaves_the_others(circuit6):
    """A reset of every world's draw kept where the mask is set: the running worlds keep their state to the bit, the
    ended ones start in the box, and nothing is read back from the device."""
    env = make_env(circuit6, worlds=6, drones=2, learners=(0, 1))
    env.sync_free = True
    for _ in range(5):
        env.step(torch.zeros(env.num_envs, 4))
    ended = torch.tensor([True, False, False, True, False, True])
    rows = ended.repeat_interleave(2)
    before = env.pos.clone(), env.vel.clone(), env.episode_length_buf.clone()
    with HostSyncCounter() as syncs:
        restart_worlds(env, ended, every_world=True)
    assert syncs.total == 0
    torch.testing.assert_close(env.pos[~rows], before[0][~rows])  # rows the reset leaves alone keep their state
    torch.testing.assert_close(env.vel[~rows], before[1][~rows])
    lo, size = env.track_geometry.box
    assert ((env.pos[rows] >= lo) & (env.pos[rows] <= lo + size)).all()
    assert (env.vel[rows] == 0).all() and (env.next_gate[rows] == 0).all()
