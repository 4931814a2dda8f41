"""Racing metrics on hand-made gate-passage sequences: overtakes, lead changes, winners from behind, lap times."""

from __future__ import annotations

import pytest
import torch

from spiral.env.racing import RaceResults
from spiral.eval.metrics import summarize_races
from spiral.eval.racecraft import lap_times, lead_changes, order_changes, passage_leaders, won_from_behind

ALL = torch.ones(1, 2, dtype=torch.bool)


def splits(*drones: list[float]) -> torch.Tensor:
    """One race's passage times, a list per drone (0: not made)."""
    return torch.tensor([list(d) for d in drones])[None]


def test_every_swap_of_two_drones_between_passages_is_an_overtake():
    """Count three overtakes when two drones swap places at every passage after the first."""
    t = splits([1.0, 2.0, 3.0, 4.0], [1.1, 1.9, 3.2, 3.9])
    assert order_changes(t, ALL).tolist() == [3]
    assert lead_changes(t, ALL).tolist() == [3]


def test_a_level_passage_leaves_the_order_as_it_was_before_it():
    """Count no overtake for ahead, level, ahead and one for ahead, level, behind."""
    assert order_changes(splits([1.0, 2.0, 3.0], [1.5, 2.0, 3.5]), ALL).tolist() == [0]
    assert order_changes(splits([1.0, 2.0, 3.0], [1.5, 2.0, 2.5]), ALL).tolist() == [1]
    assert passage_leaders(splits([1.0, 2.0, 3.0], [1.5, 2.0, 2.5]), ALL).tolist() == [[0, -1, 1]]
    assert lead_changes(splits([1.0, 2.0, 3.0], [1.5, 2.0, 2.5]), ALL).tolist() == [1]


def test_a_crash_is_not_an_overtake_and_an_absent_slot_races_nobody():
    """Count the pass made before drone 0 crashed, not its dropping out; ignore a slot that did not race."""
    t = splits([1.0, 2.0, 0.0, 0.0], [1.5, 1.8, 3.0, 4.0], [0.5, 0.6, 0.7, 0.8])
    present = torch.tensor([[True, True, False]])
    assert order_changes(t, present).tolist() == [1]
    assert passage_leaders(t, present).tolist() == [[0, 1, 1, 1]]
    assert lead_changes(t, present).tolist() == [1]


def test_overtakes_count_each_pair_of_a_pack():
    """Count two overtakes when the last of three drones passes both others between two passages."""
    t = splits([1.0, 2.0], [1.1, 2.1], [1.2, 1.9])
    assert order_changes(t, torch.ones(1, 3, dtype=torch.bool)).tolist() == [2]
    assert lead_changes(t, torch.ones(1, 3, dtype=torch.bool)).tolist() == [1]


def test_lap_times_split_the_first_lap_from_the_start_and_the_flying_laps():
    """Time two laps of three gates: the first from the start to the first gate's second passage, the second between
    the two lap ends; a drone that crashed in lap 2 has lap 1 only."""
    t = splits([0.5, 1.0, 1.5, 2.25, 2.75, 3.25, 4.0], [0.6, 1.1, 1.6, 2.5, 3.0, 0.0, 0.0])
    laps = lap_times(t, 2)
    torch.testing.assert_close(laps, torch.tensor([[[2.25, 1.75], [2.5, 0.0]]]))
    with pytest.raises(ValueError, match="laps × gates"):
        lap_times(t, 4)


def hand_race(split_time: torch.Tensor, lap_time: list[float], team: list[int], *, laps: int) -> RaceResults:
    w, d, _ = split_time.shape
    finished = torch.tensor(lap_time)[None] > 0
    return RaceResults(finished=finished, crashed=~finished, crash_kind=torch.where(finished, 0, 8).int(),
                       lap_time=torch.tensor(lap_time)[None], gates_passed=(split_time > 0).sum(-1),
                       distance=torch.ones(w, d), present=torch.ones(w, d, dtype=torch.bool), team=torch.tensor(team),
                       split_time=split_time, laps=laps)


def test_a_team_that_trailed_at_the_first_gate_and_won_won_from_behind():
    """Mark a 1v1 race won by the drone second through the first gate as won from behind, and a 2v2 race whose first
    drone home is of the team that led there as not."""
    duel = hand_race(splits([1.0, 2.0, 3.0], [1.2, 1.9, 2.8]), [3.0, 2.8], [0, 1], laps=1)
    assert won_from_behind(duel, duel.team).tolist() == [1]
    team = hand_race(splits([1.0, 2.0, 3.0], [1.2, 1.9, 2.9], [1.1, 2.1, 2.7], [1.3, 2.3, 0.0]), [3.0, 2.9, 2.7, 0.0],
                     [0, 1, 0, 1], laps=1)
    assert won_from_behind(team, team.team).tolist() == [0]
    nobody = hand_race(splits([1.0, 0.0, 0.0], [1.2, 0.0, 0.0]), [0.0, 0.0], [0, 1], laps=1)
    assert won_from_behind(nobody, nobody.team).tolist() == [-1]


def test_the_race_summary_reports_the_racing_metrics_and_contacts_per_lap():
    """Summarise a two-lap duel of two gates: one overtake, one lead change, won from behind, a first lap and a
    flying lap per drone, no contacts; a drone–drone crash in a second duel counts per lap flown."""
    duel = hand_race(splits([0.5, 1.0, 1.5, 2.0, 2.6], [0.6, 1.1, 1.4, 1.9, 2.5]), [2.6, 2.5], [0, 1], laps=2)
    racing = summarize_races(duel)["racing"]
    assert racing["laps"] == 2 and racing["won_from_behind"] == pytest.approx(1.0)
    assert racing["overtakes_per_race"] == pytest.approx(1.0) and racing["lead_changes_per_race"] == pytest.approx(1.0)
    assert racing["first_lap"] == pytest.approx((1.5 + 1.4) / 2)
    assert racing["flying_lap"] == pytest.approx((1.1 + 1.1) / 2)
    assert racing["drone_contacts_per_lap"] == pytest.approx(0.0)
    crash = hand_race(splits([0.5, 1.0, 0.0, 0.0, 0.0], [0.6, 1.1, 1.4, 1.9, 2.5]), [0.0, 2.5], [0, 1], laps=2)
    crash.crash_kind[0, 0] = 8  # drone–drone
    assert summarize_races(crash, [0])["racing"]["drone_contacts_per_lap"] == pytest.approx(1.0)
