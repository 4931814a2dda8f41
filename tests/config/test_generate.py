"""Generated tracks: seeded, closed, in the generator's ranges, in bounds, and written as files that load like any."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from spiral.config import load_track
from spiral.config.generate import TrackGenCfg, gate_offsets, generate_track, track_faults, track_yaml

ROOT = Path(__file__).resolve().parents[2]


def test_a_seed_gives_one_track_and_another_seed_another():
    cfg = TrackGenCfg()
    assert generate_track(cfg, 7) == generate_track(cfg, 7)
    assert generate_track(cfg, 7).gates != generate_track(cfg, 8).gates


@pytest.mark.parametrize("gates", [4, 6, 9])
def test_every_generated_track_is_a_closed_circuit_in_its_ranges_and_reloads_unchanged(tmp_path, gates):
    """Twenty seeds: consecutive gates (the last and the first included) within the spacing, turns and climbs in range,
    every frame and the start box inside the arena, the file written loads to the same track."""
    cfg = TrackGenCfg(gates=gates)
    for seed in range(20):
        track = generate_track(cfg, seed)
        assert len(track.gates) == gates and not track_faults(track, cfg)
        c = track.gate_centers()
        spacing = np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1)  # the closing segment included
        assert spacing.min() >= cfg.spacing[0] and spacing.max() <= cfg.spacing[1]
        lo, hi = np.asarray(track.bounds.min), np.asarray(track.bounds.max)
        corners = np.concatenate([track.gate_corners(g) for g in range(gates)])
        assert (corners >= lo).all() and (corners <= hi).all() and corners[:, 2].min() >= cfg.floor
        box = np.asarray(track.start.center), np.asarray(track.start.size) / 2
        assert (box[0] - box[1] >= lo).all() and (box[0] + box[1] <= hi).all()
        path = tmp_path / f"{seed}.yaml"
        path.write_text(track_yaml(track, f"seed {seed}"))
        assert load_track(path) == track


def test_track_faults_name_gates_too_close_a_frame_on_a_segment_and_a_sharp_turn(circuit6):
    """circuit6 is in range; moved by hand, its faults are named."""
    cfg = TrackGenCfg(spacing=(1.0, 5.0), floor=0.1)  # its gate 5 is a diamond 0.1 m above the ground
    assert track_faults(circuit6, cfg) == []
    gates = [g.model_copy() for g in circuit6.gates]
    gates[1] = gates[1].model_copy(update={"position": (-1.4, 0.0, 1.0)})  # 0.5 m from gate 0
    faults = track_faults(circuit6.model_copy(update={"gates": gates}), cfg)
    assert any("gates 0 and 1" in f for f in faults)
    assert any("turn of" in f for f in track_faults(circuit6, cfg.model_copy(update={"max_turn_deg": 60.0})))
    middle = (np.asarray(circuit6.gates[2].position) + np.asarray(circuit6.gates[3].position)) / 2
    gates = [g.model_copy() for g in circuit6.gates]
    gates[5] = gates[5].model_copy(update={"position": tuple(middle)})  # gate 5 on the segment from 2 to 3
    assert any("gate 5: within" in f for f in track_faults(circuit6.model_copy(update={"gates": gates}), cfg))


@pytest.mark.parametrize("name", ["circuit6", "figure8", "oval4", "splits3d"])
def test_the_default_ranges_hold_every_shipped_track(name):
    """Spacing, turns, climbs, each gate's yaw, pitch and roll off the line through it, frames clear of the segments
    they do not join: every shipped track is one the generator could draw (circuit6's diamond gate sits 0.1 m above
    the ground, below the generator's floor)."""
    track = load_track(ROOT / "tracks" / f"{name}.yaml")
    assert track_faults(track, TrackGenCfg(floor=0.1)) == []


def test_a_gate_turned_off_the_line_through_it_is_named_and_a_generated_one_stays_in_range():
    """circuit6's gate 3 passes 40 deg to the side of the line from gate 2 to gate 4 and 22 deg below it; a range
    tighter than that names it. Generated gates lie within the yaw, pitch and roll ranges."""
    circuit6 = load_track(ROOT / "tracks" / "circuit6.yaml")
    yaw, pitch = gate_offsets(circuit6)
    assert yaw[3] == pytest.approx(-40.0, abs=1.0) and pitch[3] == pytest.approx(-22.0, abs=1.0)
    faults = track_faults(circuit6, TrackGenCfg(floor=0.1, yaw_deg=30.0, tilt_deg=30.0, roll_deg=30.0))
    assert "gate 3: yawed 40 deg off the line through it" in faults
    assert "gate 2: pitched 37 deg off the line through it" in faults and "gate 5: rolled 45 deg" in faults
    cfg = TrackGenCfg(yaw_deg=20.0, tilt_deg=10.0, roll_deg=5.0)
    for seed in range(5):
        track = generate_track(cfg, seed)
        yaw, pitch = gate_offsets(track)
        assert np.abs(yaw).max() <= 20.5 and np.abs(pitch).max() <= 10.5
        assert max(abs(g.rpy_deg[0]) for g in track.gates) <= 5.0


def test_most_generated_gates_sit_near_their_line_unless_the_offsets_are_uniform():
    """With the default power 2 a gate's yaw offset is within a third of its range with probability 3**-0.5 (0.58);
    uniform offsets (power 1) put a third of the gates there. 30 six-gate tracks each."""
    def near_share(power: float) -> float:
        cfg = TrackGenCfg(offset_power=power)
        yaws = np.concatenate([gate_offsets(generate_track(cfg, seed))[0] for seed in range(30)])
        return float(np.mean(np.abs(yaws) <= cfg.yaw_deg / 3))

    assert near_share(2.0) > 0.48 and near_share(1.0) < 0.43


def test_impossible_ranges_are_refused_naming_the_field():
    with pytest.raises(ValidationError, match="spacing"):
        TrackGenCfg(spacing=(3.0, 2.0))
    with pytest.raises(ValueError, match="no raceable track of 6 gates"):
        generate_track(TrackGenCfg(spacing=(1.0, 1.05), tries=20), 0)
