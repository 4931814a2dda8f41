"""Starts from recorded gate-passage states: the buffer, the draws, the clearance test and the stage's schedule."""

from __future__ import annotations

import pytest
import torch

from spiral.config import AIRFRAMES, EnvCfg, ObsCfg, PassageStartsCfg, SimCfg
from spiral.env import RaceEnv, RaceSetting
from spiral.env.passages import PassageBuffer, clear_of_gates, passage_share

CF2X = AIRFRAMES["cf2x"]


def test_each_gate_keeps_its_newest_states_up_to_its_capacity():
    """Record five passages of gate 1 (three in one step) and one of gate 0 into rings of three: gate 1 keeps its
    newest three, gate 0 its one; drones that passed no gate (−1) leave no state."""
    buf = PassageBuffer(2, 3, device=torch.device("cpu"))
    pos = torch.arange(12.0).view(4, 3)
    buf.record(torch.tensor([1, -1, 1, 0]), pos, -pos, torch.arange(4.0))
    buf.record(torch.tensor([1, 1, 1, -1]), pos + 100, -pos, torch.arange(4.0) + 10)
    assert buf.count.tolist() == [1, 3] and buf.head.tolist() == [1, 2]
    assert sorted(buf.yaw[1].tolist()) == pytest.approx([10.0, 11.0, 12.0])
    assert buf.yaw[0, 0].item() == pytest.approx(3.0)


def test_drawn_starts_are_recorded_states_behind_different_gates_heading_for_the_next():
    """Without noise, draw for 64 worlds of three drones only states recorded at the drawn gate, each world's drones
    behind three different gates, each heading for the gate after; a world needs recorded states for its gates."""
    buf = PassageBuffer(4, 8, device=torch.device("cpu"))
    for g in range(3):  # gate 3 gets no states yet
        n = 5
        buf.record(torch.full((n,), g), torch.rand(n, 3) + 10 * g, torch.rand(n, 3), torch.full((n,), float(g)))
    gen = torch.Generator().manual_seed(0)
    pos, _, yaw, gate, ok = buf.sample(64, 3, gen, pos_noise=0.0, vel_noise=0.0)
    g = (gate - 1) % 4
    assert (g.sort(dim=1).values.diff(dim=1) > 0).all()
    assert torch.equal(ok, (g != 3).all(dim=1))  # exact: booleans
    assert ok.any()
    for w in ok.nonzero().flatten().tolist():  # every drawn state is one the buffer holds for that gate
        for d in range(3):
            held = buf.pos[g[w, d], : buf.count[g[w, d]]]
            assert torch.isclose(held, pos[w, d], rtol=1e-6, atol=1e-9).all(dim=1).any()
            assert yaw[w, d].item() == pytest.approx(g[w, d].item())
    assert not buf.sample(4, 5, gen, pos_noise=0.0, vel_noise=0.0)[-1].any()  # more drones than gates


def test_clearance_rejects_starts_on_a_gate_frame_or_out_of_bounds(oval2):
    """Call the opening's centre clear, a point on a gate's bar or inside the arena's margin not."""
    gate = torch.tensor(oval2.gate_centers()[0], dtype=torch.float32)
    half = oval2.gate_opening(0) / 2 + oval2.gate_bar(0) / 2
    points = torch.stack([gate, gate + torch.tensor([0.0, half, 0.0]), gate + torch.tensor([0.0, 0.0, -half]),
                          torch.tensor([0.0, 0.0, 0.02]), torch.tensor([-1.2, -1.0, 1.0])])
    assert clear_of_gates(points, oval2, CF2X.radius).tolist() == [True, False, False, False, True]


@pytest.mark.parametrize(("fraction", "share"), [(0.0, 0.9), (0.25, 0.7), (0.5, 0.5), (1.0, 0.1), (1.5, 0.1)])
def test_the_share_of_passage_starts_follows_the_stage_linearly(fraction, share):
    """Move the share of passage starts from 0.9 at the stage's start to 0.1 at its end (box starts the rest)."""
    assert passage_share(PassageStartsCfg(share_start=0.9, share_end=0.1), fraction) == pytest.approx(share)


def scripted(env: RaceEnv):
    """Fly each drone through the centre of its next gate and 0.6 m past it."""
    def act(obs):
        gate = env.next_gate.long()
        target = env.world_tracks.gate_center[gate] + 0.6 * env.world_tracks.gate_forward[gate]
        rel = (target - env.pos) / env.cfg.action.pos_scale
        return torch.cat([rel.clamp(-1, 1), torch.zeros(env.drone_count, 1)], dim=-1)
    return act


def test_a_training_env_starts_worlds_from_the_passages_its_drones_flew(line2):
    """Fly a training env until its drones passed both gates, then reset with every world started from passage
    states: starts off the box, clear of the gates, at states the buffer recorded (no noise), heading on."""
    cfg = EnvCfg(obs=ObsCfg(history_len=1), episode={"track_start_prob": 0.0, "passage_starts": {
        "share_start": 1.0, "share_end": 1.0, "pos_noise": 0.0, "vel_noise": 0.0}})
    env = RaceEnv(RaceSetting(line2, CF2X, SimCfg()), cfg, world_count=4, drones_per_world=1, seed=0)
    assert env.passages.share == pytest.approx(1.0) and bool(env.passages.buffer.count.eq(0).all())
    policy = scripted(env)
    for _ in range(400):
        env.step(policy(None))
        if bool((env.passages.buffer.count > 0).all()):
            break
    assert (env.passages.buffer.count > 0).all()
    env.reset()
    recorded = env.passages.buffer.pos[:, : int(env.passages.buffer.count.min())]
    starts = env.pos.clone()
    assert clear_of_gates(starts, line2, CF2X.radius).all()
    for p in starts:
        assert ((recorded - p).norm(dim=-1) < 1e-6).any()
    assert not env.contested.any() and env.vel.norm(dim=-1).gt(0.5).all()


def test_the_curriculum_shares_of_passage_track_and_box_starts_at_three_points_of_a_stage(oval2):
    """full.yaml's schedule (passage share 0.5 → 0.2, track starts 0.3 of the rest) on a training env whose buffer
    holds clear states past both gates: at the stage's start, middle and end, the 1v1 worlds start from passages, the
    track and the box in shares 50 / 15 / 35, 35 / 19.5 / 45.5 and 20 / 24 / 56 % (within a few points for 4096
    worlds)."""
    cfg = EnvCfg(obs=ObsCfg(history_len=1), episode={"track_start_prob": 0.3, "passage_starts": {
        "share_start": 0.5, "share_end": 0.2, "pos_noise": 0.0, "vel_noise": 0.0}})
    env = RaceEnv(RaceSetting(oval2, CF2X, SimCfg()), cfg, world_count=4096, drones_per_world=2,
                  learner_slots=[0, 1], seed=0)
    centers = torch.tensor(oval2.gate_centers(), dtype=torch.float32)
    rot = torch.tensor(oval2.gate_rotations(), dtype=torch.float32)
    for g in range(len(oval2.gates)):  # states 0.3 m past each gate's centre at 2 m/s: clear, and told apart by speed
        env.passages.buffer.record(torch.full((8,), g), (centers[g] + 0.3 * rot[g][:, 0]).expand(8, 3),
                                   2.0 * rot[g][:, 0].expand(8, 3), torch.zeros(8))
    for fraction, passages, box in [(0.0, 0.5, 0.35), (0.5, 0.35, 0.455), (1.0, 0.2, 0.56)]:
        env.set_training_progress(fraction)
        env.reset()
        from_passage = (env.vel.norm(dim=-1) - 2.0).abs().lt(1e-4).view(4096, 2).all(dim=1)
        from_box = env.contested  # per world
        assert not (from_passage & from_box).any()
        assert from_passage.float().mean().item() == pytest.approx(passages, abs=0.03)
        assert from_box.float().mean().item() == pytest.approx(box, abs=0.03)
        assert (~from_passage & ~from_box).float().mean().item() == pytest.approx(1 - passages - box, abs=0.03)
