"""Start placements: single-file starts along the track, and how draw_starts shares the worlds out."""

from __future__ import annotations

import math

import pytest
import torch

import spiral.env.starts as starts_module
from spiral.config import EpisodeCfg
from spiral.env.starts import FILE_GAP, draw_starts, sample_file_starts

CPU = torch.device("cpu")


def file_starts(track, worlds: int, drones: int, *, seed: int = 0, max_speed: float = 1.0):
    generator = torch.Generator().manual_seed(seed)
    return sample_file_starts(track, worlds, drones, generator, max_speed=max_speed, device=CPU)


def along_and_across(track, pos: torch.Tensor, gate: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Distance of each drone from its segment's first gate along the segment, its distance from the segment's
    line, and the segment's length (every world of these tests uses one segment of the same length)."""
    centers = torch.tensor(track.gate_centers(), dtype=torch.float32)
    origin, end = centers[(gate.long() - 1) % len(centers)], centers[gate.long()]
    direction = (end - origin) / (end - origin).norm(dim=-1, keepdim=True)
    rel = pos - origin
    along = (rel * direction).sum(-1)
    across = (rel - along[..., None] * direction).norm(dim=-1)
    return along, across, float((end - origin).norm(dim=-1).max())


@pytest.fixture
def no_jitter(monkeypatch):
    """File starts exactly on the line between the gates."""
    monkeypatch.setattr(starts_module, "FILE_JITTER", 0.0)


def test_a_file_start_puts_two_drones_on_one_stretch_a_gap_apart_in_random_order(line2, no_jitter):
    """line2's stretches are 2.5 m long: the pair heads for one gate, on the line between the gates, 0.4-1 m apart,
    inside its middle 70 %, moving along it no faster than the limit; either drone may lead."""
    pos, vel, yaw, gate = file_starts(line2, 400, 2, max_speed=1.5)
    assert (gate[:, 0] == gate[:, 1]).all()
    along, across, length = along_and_across(line2, pos, gate)
    assert across.max() < 1e-5
    gap = (along[:, 0] - along[:, 1]).abs()
    assert (gap > FILE_GAP[0] - 1e-5).all() and (gap < FILE_GAP[1] + 1e-5).all()
    assert gap.mean() == pytest.approx(sum(FILE_GAP) / 2, abs=0.05)
    assert (along > 0.15 * length - 1e-5).all() and (along < 0.85 * length + 1e-5).all()
    lead_share = (along[:, 0] > along[:, 1]).float().mean()
    assert 0.4 < lead_share < 0.6
    heading = torch.stack([torch.cos(yaw), torch.sin(yaw)], dim=-1)
    speed = vel.norm(dim=-1)
    assert (speed <= 1.5).all() and speed.max() > 1.2 and vel[..., 2].abs().max() < 1e-6
    moving = speed > 1e-3
    assert torch.allclose((vel[..., :2] / speed[..., None].clamp(min=1e-9))[moving], heading[moving], atol=1e-5)


def test_a_file_too_long_for_its_stretch_is_compressed_into_the_middle(line2, no_jitter):
    """Four drones need up to 3 m of gaps; line2's 2.5 m stretch holds 1.75 m in its middle 70 %: the file is
    shortened in proportion and stays inside it."""
    pos, _, _, gate = file_starts(line2, 300, 4)
    along, _, length = along_and_across(line2, pos, gate)
    span = along.amax(dim=1) - along.amin(dim=1)
    assert (span < 0.7 * length + 1e-5).all() and (span > 0.7 * length - 1e-5).float().mean() > 0.5
    assert (along > 0.15 * length - 1e-5).all() and (along < 0.85 * length + 1e-5).all()
    gaps = along.sort(dim=1).values.diff(dim=1)
    assert gaps.min() > FILE_GAP[0] * 1.75 / 3.0 - 1e-5  # each gap >= 0.4 m, shrunk by at most 1.75 / 3


def test_file_start_jitter_is_the_set_spread_around_the_line(line2):
    """With the default jitter each drone sits off the line by about FILE_JITTER per axis."""
    pos, _, _, gate = file_starts(line2, 2000, 2)
    _, across, _ = along_and_across(line2, pos, gate)
    # two of the three axes are across the line: E|across|^2 = 2 sigma^2
    assert (across ** 2).mean().sqrt() == pytest.approx(math.sqrt(2) * starts_module.FILE_JITTER, rel=0.05)


@pytest.mark.parametrize("where", ["track", "file"])
@pytest.mark.bitwise
def test_evaluation_starts_every_world_off_the_box_when_asked_and_ignores_the_training_shares(line2, where):
    """``eval_starts`` track or file: every evaluation world starts off the start box, drawn as the training sampler
    of that kind draws from the same generator state; training starts are unchanged by the option."""
    asked = EpisodeCfg(track_start_prob=0.0, eval_starts=where)
    starts = draw_starts(line2, asked, 64, 2, torch.Generator().manual_seed(3), training=False, device=CPU)
    assert not starts.box.any()
    generator = torch.Generator().manual_seed(3)
    starts_module.sample_box_starts(line2, 64, 2, generator, device=CPU)  # drawn first, as always
    sample = starts_module.sample_track_starts if where == "track" else sample_file_starts
    pos, vel, _, gate = sample(line2, 64, 2, generator, max_speed=asked.track_start_speed, device=CPU)
    assert torch.equal(starts.pos, pos) and torch.equal(starts.vel, vel) and torch.equal(starts.gate, gate.int())
    trained = draw_starts(line2, asked, 64, 2, torch.Generator().manual_seed(3), training=True, device=CPU)
    box = draw_starts(line2, EpisodeCfg(track_start_prob=0.0), 64, 2, torch.Generator().manual_seed(3),
                      training=True, device=CPU)
    assert trained.box.all() and torch.equal(trained.pos, box.pos)


def test_evaluation_draws_on_the_cpu_and_training_on_the_envs_device():
    """A CUDA generator draws other numbers than the CPU's for one seed: evaluation placements are drawn on the CPU
    whatever the env's device, so that a seed means the same races on any device; training draws stay on the device
    (no copy to it at every reset)."""
    from spiral.env.starts import draw_device

    gpu = torch.device("cuda:0")  # a name only: nothing is built on it
    assert draw_device(gpu, training=False) == CPU
    assert draw_device(gpu, training=True) == gpu
    assert draw_device(CPU, training=True) == CPU


@pytest.mark.parametrize("eval_starts", ["box", "track"])
def test_an_evaluation_envs_placements_are_the_cpu_draws_of_its_seed(circuit6, eval_starts):
    """The starts an evaluation env races are what ``draw_starts`` gives for a CPU generator of its seed: the code
    path of an env on any device, whose draws are then moved to it."""
    from tests.env.helpers import make_env

    episode = EpisodeCfg(eval_starts=eval_starts)
    env = make_env(circuit6, worlds=5, drones=2, learners=(0, 1), training=False, episode=episode)
    assert env.generator.device == CPU
    expected = draw_starts(env.track, env.cfg.episode, 5, 2, torch.Generator().manual_seed(3), training=False,
                           device=CPU)
    torch.testing.assert_close(env.pos.view(5, 2, 3), expected.pos, rtol=0, atol=0)
    torch.testing.assert_close(env.vel.view(5, 2, 3), expected.vel, rtol=0, atol=0)


def test_an_unchecked_box_draw_places_what_a_checked_one_does_without_a_host_read(circuit6):
    """Without the check (a draw of the sync-free reset) the box placements are those of the checked draw whenever no
    world got stuck, keep the minimum separation, and no flag is read back."""
    from spiral.core.host_syncs import HostSyncCounter
    from spiral.env.track_tensors import TrackTensors

    geometry = TrackTensors.of(circuit6, CPU)
    checked, _ = starts_module.sample_box_starts(circuit6, 500, 4, torch.Generator().manual_seed(2), device=CPU)
    with HostSyncCounter() as syncs:
        free, yaw = starts_module.sample_box_starts(geometry, 500, 4, torch.Generator().manual_seed(2), device=CPU,
                                                    checked=False)
    assert syncs.total == 0
    torch.testing.assert_close(free, checked, rtol=0, atol=0)
    gaps = torch.cdist(free, free) + torch.eye(4) * 1e3
    assert gaps.min() >= circuit6.start.min_separation
    assert torch.allclose(yaw, torch.full_like(yaw, math.radians(circuit6.start.yaw_deg)))


def test_track_tensors_hold_the_tracks_geometry_and_are_built_once_per_device(circuit6):
    from spiral.env.track_tensors import TrackTensors

    geometry = TrackTensors.of(circuit6, "cpu")
    assert TrackTensors.of(geometry, CPU) is geometry
    torch.testing.assert_close(geometry.gate_centers[0], torch.tensor(circuit6.gate_centers(), dtype=torch.float32))
    lo, size = geometry.box
    torch.testing.assert_close(lo[0] + size[0] / 2, torch.tensor(circuit6.start.center))
    assert geometry.gate_half.shape == geometry.gate_bar.shape == (1, len(circuit6.gates))


def test_track_tensors_of_several_tracks_pad_the_shorter_ones_track_major(circuit6, line2):
    """circuit6 (6 gates) and line2 (2): per-gate arrays of 6 rows per track, line2's padded with its last gate; in
    the flat layout line2's gates are rows 6 and 7."""
    from spiral.env.track_tensors import TrackTensors

    geometry = TrackTensors.of([circuit6, line2], CPU)
    assert geometry.track_count == 2 and geometry.max_gates == 6 and geometry.gate_count.tolist() == [6, 2]
    centers = torch.tensor(line2.gate_centers(), dtype=torch.float32)
    torch.testing.assert_close(geometry.flat_centers[6:8], centers)
    torch.testing.assert_close(geometry.gate_centers[1, 2:], centers[-1].expand(4, 3))
    torch.testing.assert_close(geometry.flat_forward[6:8], torch.tensor(line2.gate_forward(), dtype=torch.float32))
    torch.testing.assert_close(geometry.start_separation, torch.tensor([circuit6.start.min_separation,
                                                                        line2.start.min_separation]))
