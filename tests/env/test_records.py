"""Each drone's race record: ended by a crash or a finish, started afresh by a restart of its world."""

from __future__ import annotations

import pytest
import torch

from spiral.env.records import RaceRecords


def test_a_crash_and_a_finish_end_only_their_drones_races_with_the_kind_and_the_time():
    """Of three racing drones, drone 0 crashes into a gate (kind 2) and drone 2 finishes at 4.5 s: both leave the
    race with their kind and time, drone 1 races on."""
    rec = RaceRecords(3, torch.device("cpu"))
    rec.end(torch.tensor([True, False, False]), torch.tensor([2, 0, 0], dtype=torch.int32),
            torch.tensor([False, False, True]), torch.tensor([1.0, 2.0, 4.5]))
    assert rec.crashed.tolist() == [True, False, False] and rec.finished.tolist() == [False, False, True]
    assert rec.crash_kind.tolist() == [2, 0, 0] and rec.lap_time.tolist() == pytest.approx([0.0, 0.0, 4.5])
    assert rec.racing().tolist() == [False, True, False]


def test_a_restart_clears_the_restarted_drones_races_and_keeps_the_others():
    """Drones 0 and 1 restart (drone 1 now absent); drone 2 keeps its finish, its time and its reward sums."""
    rec = RaceRecords(3, torch.device("cpu"))
    rec.end(torch.tensor([True, False, False]), torch.tensor([8, 0, 0], dtype=torch.int32),
            torch.tensor([False, False, True]), torch.tensor([0.0, 0.0, 4.5]))
    for sums in rec.term_sums.values():
        sums += 1.0
    rec.restart(torch.tensor([True, True, False]), absent=torch.tensor([False, True, False]))
    assert rec.crashed.tolist() == [False, False, False] and rec.crash_kind.tolist() == [0, 0, 0]
    assert rec.finished.tolist() == [False, False, True] and rec.lap_time.tolist() == pytest.approx([0.0, 0.0, 4.5])
    assert rec.absent.tolist() == [False, True, False] and rec.racing().tolist() == [True, False, False]
    assert all(sums.tolist() == pytest.approx([0.0, 0.0, 1.0]) for sums in rec.term_sums.values())
