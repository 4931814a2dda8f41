"""A race env whose worlds fly different tracks: each world as it would alone, a track drawn at each training reset,
starts and passage states on the world's own track, evaluation races over several tracks, and the single-track users
that refuse such an env."""

from __future__ import annotations

import pytest
import torch

from spiral.config import EnvCfg, ObsCfg, PassageStartsCfg, SimCfg
from spiral.core.errors import UsageError
from spiral.env import RaceEnv, RaceSetting
from spiral.env.passages import PassageBuffer
from spiral.env.racing import run_races
from tests.env.helpers import CF2X

ROOT_TRACKS = ("circuit6", "oval4", "figure8")


@pytest.fixture(scope="module")
def tracks():
    from spiral.config.load import load_track
    from tests.conftest import ROOT

    return [load_track(ROOT / "tracks" / f"{name}.yaml") for name in ROOT_TRACKS]


def _env(tracks, *, worlds: int, drones: int = 1, training: bool, episode: dict | None = None) -> RaceEnv:
    cfg = EnvCfg(obs=ObsCfg(history_len=2, gate_normals=True), reward={"proximity": 0.1, "closing": 0.5},
                 episode=episode or {"track_start_prob": 0.0})
    setting = RaceSetting(tracks[0], CF2X, SimCfg(), more_tracks=tuple(tracks[1:]))
    return RaceEnv(setting, cfg, world_count=worlds, drones_per_world=drones,
                   learner_slots=tuple(range(drones)), seed=5, training=training)


def _towards_next_gate(env: RaceEnv) -> torch.Tensor:
    """Actions that fly every learner drone at its next gate's centre (and through it)."""
    rel = env.world_tracks.to_gate(env.pos, env.next_gate)[env.learner_idx] / env.cfg.action.pos_scale
    return torch.cat([rel.clamp(-1, 1), torch.zeros(len(rel), 1)], dim=-1)


@pytest.mark.bitwise
def test_worlds_on_different_tracks_step_as_each_would_alone(tracks):
    """Two evaluation worlds, one on circuit6 and one on oval4, from the same states as two one-track envs and with
    the same actions, give the same states, gate passes, rewards and observations, step for step."""
    both = _env(tracks[:2], worlds=2, training=False)
    assert sorted(both.world_tracks.world_track.tolist()) == [0, 1]
    alone = [_env(tracks[i:i + 1], worlds=1, training=False) for i in both.world_tracks.world_track.tolist()]
    for w, env in enumerate(alone):  # the same start: the two-track env's draw on the world's track
        env.pos.copy_(both.pos[w:w + 1])
        env.get_observations()
    both.get_observations()
    passes = 0
    for _ in range(150):
        obs, reward, _, _ = both.step(_towards_next_gate(both))
        for w, env in enumerate(alone):
            obs_1, reward_1, _, _ = env.step(_towards_next_gate(env))
            for mine, theirs in ((both.pos[w], env.pos[0]), (both.vel[w], env.vel[0]), (reward[w], reward_1[0]),
                                 (obs["policy"][w], obs_1["policy"][0])):
                torch.testing.assert_close(mine, theirs, rtol=0, atol=0)
            assert both.gates_passed[w] == env.gates_passed[0] and both.next_gate[w] == env.next_gate[0]
        passes = int(both.gates_passed.min())
    assert passes >= 2  # both worlds flew through gates of their own tracks


def test_a_training_reset_draws_each_world_a_track_of_the_set_and_starts_it_there(tracks):
    """48 training worlds of two drones on three tracks: the worlds share the tracks out, the simulator races the
    env's choice, box starts sit in the world's track's start box, track starts head for a gate of that track, and
    the worlds that reset draw their tracks again."""
    env = _env(tracks, worlds=48, drones=2, training=True, episode={"track_start_prob": 0.5})
    first = env.world_tracks.world_track.clone()
    assert set(first.tolist()) == {0, 1, 2}
    drone_track = first.repeat_interleave(2)
    assert env.world_tracks.simulator_tracks.tolist() == first.tolist()
    counts = torch.tensor([len(t.gates) for t in tracks])
    assert env.world_tracks.gate_count.tolist() == counts[drone_track].tolist()
    assert env.world_tracks.race_passes.tolist() == (counts[drone_track] + 1).tolist()
    assert (env.next_gate.long() < env.world_tracks.gate_count).all()
    box = (env.next_gate == 0) & (env.vel.norm(dim=-1) == 0)  # exact: box starts are at rest
    for drone in box.nonzero().flatten().tolist():
        start = tracks[int(drone_track[drone])].start
        lo = torch.tensor(start.center) - torch.tensor(start.size) / 2
        assert ((env.pos[drone] >= lo - 1e-6) & (env.pos[drone] <= lo + torch.tensor(start.size) + 1e-6)).all()
    for _ in range(120):
        env.step(torch.rand(env.num_envs, 4) * 2 - 1)
    assert (env.world_tracks.world_track != first).any()
    assert env.world_tracks.simulator_tracks.tolist() == env.world_tracks.world_track.tolist()
    assert (env.next_gate.long() < env.world_tracks.gate_count).all()


def test_passage_states_of_several_tracks_start_worlds_behind_gates_of_their_own_track():
    """Tracks of 4 and 2 gates (rows 0–3 and 4–5 of a padded layout of 8): states recorded at every gate are drawn
    only for worlds of that gate's track, each world's drones behind different gates, heading for the next gate of
    their track; a world of three drones on the 2-gate track gets none."""
    buf = PassageBuffer(8, 4, device=torch.device("cpu"), gate_count=torch.tensor([4, 2]))
    for row in (0, 1, 2, 3, 4, 5):
        buf.record(torch.full((3,), row), torch.full((3, 3), float(row)), torch.zeros(3, 3), torch.zeros(3))
    world_tracks = torch.tensor([0, 1] * 32)
    pos, _, _, gate, ok = buf.sample(64, 2, torch.Generator().manual_seed(1), pos_noise=0.0, vel_noise=0.0,
                                     world_tracks=world_tracks)
    assert ok.all()
    count = torch.tensor([4, 2])[world_tracks][:, None]
    before = (gate - 1) % count
    row = world_tracks[:, None] * 4 + before
    torch.testing.assert_close(pos[..., 0], row.float())  # each start is a state of its gate of its track
    assert (before[:, 0] != before[:, 1]).all()
    _, _, _, _, ok = buf.sample(4, 3, torch.Generator().manual_seed(1), pos_noise=0.0, vel_noise=0.0,
                                world_tracks=torch.tensor([0, 1, 0, 1]))
    assert ok.tolist() == [True, False, True, False]


def test_a_training_env_of_several_tracks_draws_passage_starts_on_each_worlds_track(tracks):
    """With passage starts from the first step on, a two-track training env keeps flying: every drone always heads
    for a gate of its world's track and the buffer fills rows of both tracks only."""
    env = _env(tracks[:2], worlds=32, training=True,
               episode={"track_start_prob": 0.3, "passage_starts": PassageStartsCfg(share_start=1.0, share_end=1.0)})
    for _ in range(200):
        env.step(_towards_next_gate(env))
        assert (env.next_gate.long() < env.world_tracks.gate_count).all()
    filled = (env.passages.buffer.count > 0).nonzero().flatten()
    g = env.world_tracks.geometry.max_gates
    assert (filled // g == 0).any() and (filled // g == 1).any()
    assert ((filled % g) < torch.tensor([len(t.gates) for t in tracks[:2]])[filled // g]).all()


def test_evaluation_races_each_world_on_its_track_when_the_tracks_share_a_lap_count(tracks):
    """An evaluation env of two tracks races world w on track (w + k) mod 2: the drones fly their own track's gates;
    tracks of different lap counts are refused by the races, and the SE-IBR planner and absolute action targets,
    which need one arena, refuse an env of several tracks."""
    from spiral.baselines.se_ibr import SEIBRPlanner

    env = _env(tracks[:2], worlds=4, training=False)
    results = run_races(env, lambda obs: _towards_next_gate(env))
    assert env.world_tracks.world_track.tolist() in ([0, 1, 0, 1], [1, 0, 1, 0])
    assert (results.gates_passed > 0).all()
    mixed = RaceEnv(RaceSetting(tracks[0], CF2X, SimCfg(), more_tracks=(tracks[1].with_laps(2),)), EnvCfg(),
                    world_count=2, drones_per_world=1, training=False)
    with pytest.raises(UsageError, match="different lap counts"):
        run_races(mixed, lambda obs: _towards_next_gate(mixed))
    with pytest.raises(UsageError, match="the SE-IBR planner needs every world on one track"):
        SEIBRPlanner(env)
    with pytest.raises(UsageError, match=r"action\.mode absolute"):
        RaceEnv(RaceSetting(tracks[0], CF2X, SimCfg(), more_tracks=(tracks[1],)), EnvCfg(action={"mode": "absolute"}),
                world_count=2, drones_per_world=1, training=False)


def test_evaluation_races_of_fewer_worlds_than_tracks_race_every_track_in_turn_and_replay_with_the_generator(tracks):
    """Two worlds, three tracks: each race puts the worlds on consecutive tracks from a drawn one, so that over races
    every track is raced (not the first two only); a race from the same generator state races the same tracks (a
    paired comparison of two policies races both on the same tracks)."""
    env = _env(tracks, worlds=2, training=False)
    raced, firsts = set(), set()
    for _ in range(8):
        state = env.generator.get_state()
        env.reset()  # what each race (run_races) starts with
        drawn = env.world_tracks.world_track.tolist()
        assert drawn[1] == (drawn[0] + 1) % 3
        assert env.world_tracks.gate_count.tolist() == [len(tracks[t].gates) for t in drawn]
        raced.update(drawn)
        firsts.add(drawn[0])
        env.generator.set_state(state)
        env.reset()
        assert env.world_tracks.world_track.tolist() == drawn
    assert raced == {0, 1, 2} and len(firsts) > 1


def test_hard_tracks_draw_a_track_the_learner_fails_more_often_in_proportion_to_its_failure_rate(tracks):
    """Of two tracks, the learner finished 100 of 100 episodes on the first and none of 100 on the second: with every
    draw weighted by failure rate nearly all draws are the second track; with half of them, about 0.5 · 0.5 +
    0.5 · 0.99; without the option, half."""
    share = {}
    for weighted in (1.0, 0.5, None):
        episode = {"track_start_prob": 0.0, **({"hard_tracks": {"share": weighted}} if weighted else {})}
        env = _env(tracks[:2], worlds=4, training=True, episode=episode)
        env.world_tracks.ended.fill_(100.0)
        env.world_tracks.finished.copy_(torch.tensor([100.0, 0.0]))
        share[weighted] = env.world_tracks.draw(4000, env.generator).float().mean().item()
    assert share[1.0] > 0.97
    assert share[0.5] == pytest.approx(0.25 + 0.5 * (1 - 1 / 102) / (1 / 102 + 101 / 102), abs=0.03)
    assert share[None] == pytest.approx(0.5, abs=0.03)


def test_ended_learner_episodes_are_counted_on_their_worlds_track_and_decay_every_iteration(tracks):
    """Flying at the next gate on circuit6 and oval4, the learner's ended episodes are counted on the track their
    world raced (the counts add up to the dones); an iteration's progress call scales them by the decay."""
    env = _env(tracks[:2], worlds=8, training=True, episode={"track_start_prob": 0.0, "hard_tracks": {"decay": 0.5}})
    dones = torch.zeros(2)
    for _ in range(400):
        ended = env.world_tracks.world_track.clone()
        _, _, done, _ = env.step(_towards_next_gate(env))
        dones.index_add_(0, ended, done.float())
    assert dones.sum() > 8 and env.world_tracks.ended.tolist() == pytest.approx(dones.tolist())
    assert (env.world_tracks.finished <= env.world_tracks.ended).all() and env.world_tracks.finished.sum() > 0
    before = env.world_tracks.ended.clone()
    env.set_training_progress(0.5)
    torch.testing.assert_close(env.world_tracks.ended, before * 0.5)
