"""Head to head from both sides: swapped start slots, results reordered by method, winners by method."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from spiral.config import SeparationCfg
from spiral.core.outcome import race_winner
from spiral.core.scenario import TEAMS
from spiral.env.racing import RaceResults, concat_results
from spiral.eval.evaluate import FlightOverride, RaceSet, cross_play, evaluate_methods, load_method, race_policies

SHIPPED = Path(__file__).resolve().parents[2] / "checkpoints" / "full"
SPIRAL_1V1, NOSELFPLAY_1V1 = SHIPPED / "1v1" / "best.pt", SHIPPED / "1v1-noselfplay" / "best.pt"
"""The shipped 1v1 policies: drones that finish laps, so races have winners."""


def two_v_two() -> RaceResults:
    """One 2v2 race by hand: slot 2 finishes first, slot 1 crashes into slot 3, slot 0 times out."""
    return RaceResults(
        finished=torch.tensor([[False, False, True, True]]),
        crashed=torch.tensor([[False, True, False, False]]),
        crash_kind=torch.tensor([[0, 8, 0, 0]], dtype=torch.int32),
        lap_time=torch.tensor([[0.0, 0.0, 4.0, 4.5]]),
        gates_passed=torch.tensor([[3, 2, 7, 7]]),
        distance=torch.tensor([[9.0, 5.0, 20.0, 21.0]]),
        present=torch.ones(1, 4, dtype=torch.bool),
        crash_time=torch.tensor([[0.0, 1.5, 0.0, 0.0]]),
        crash_partner=torch.tensor([[-1, 3, -1, -1]]),
        team=torch.tensor([0, 0, 1, 1]),
        split_time=torch.arange(8.0).view(1, 4, 2),
    )


def test_swapping_the_teams_slots_moves_each_drone_and_renames_its_contact_partner():
    """Slots 2, 3 become 0, 1: the winner is now on team 0 and slot 1's contact with slot 3 reads slot 3 -> 1."""
    res = two_v_two()
    swapped = res.permuted([2, 3, 0, 1])
    torch.testing.assert_close(swapped.lap_time, torch.tensor([[4.0, 4.5, 0.0, 0.0]], dtype=swapped.lap_time.dtype))
    assert swapped.crash_partner.tolist() == [[-1, -1, -1, 1]]
    assert swapped.team.tolist() == [0, 0, 1, 1]
    torch.testing.assert_close(swapped.split_time[0, 0], res.split_time[0, 2])  # a permuted copy
    assert race_winner(res.finished, res.lap_time, TEAMS["2v2"]).tolist() == [1]
    assert race_winner(swapped.finished, swapped.lap_time, TEAMS["2v2"]).tolist() == [0]
    back = swapped.permuted([2, 3, 0, 1])
    for name in ("finished", "crashed", "crash_kind", "lap_time", "crash_partner", "split_time"):
        torch.testing.assert_close(getattr(back, name), getattr(res, name), msg=name)  # permuted back
    with pytest.raises(ValueError, match="permutation"):
        res.permuted([0, 0, 1, 2])


def test_concatenated_results_list_the_races_one_after_another():
    """Join two result sets race by race; mismatched teams are refused."""
    res = two_v_two()
    joined = concat_results([res, res.permuted([2, 3, 0, 1])])
    assert joined.finished.shape == (2, 4) and joined.split_time.shape == (2, 4, 2)
    assert race_winner(joined.finished, joined.lap_time, TEAMS["2v2"]).tolist() == [1, 0]
    other = two_v_two()
    other.team = torch.tensor([0, 1, 0, 1])
    with pytest.raises(ValueError, match="different teams"):
        concat_results([res, other])


@pytest.mark.bitwise
def test_both_sides_race_each_placement_again_with_the_methods_swapped(circuit6):
    """The first half is the team-A protocol; the second half is the swapped race with the method back on team A."""
    spiral, baseline = load_method(SPIRAL_1V1), load_method(NOSELFPLAY_1V1)
    races = RaceSet(circuit6, "1v1", 4, 5)
    one_side, first = cross_play(spiral, baseline, races, sides="a")
    both, winners = cross_play(spiral, baseline, races, sides="both")
    swapped, won = race_policies(races, baseline, spiral)
    assert bool(both.finished.any())  # real laps: the comparisons below are not of zeros
    assert torch.equal(both.lap_time[:4], one_side.lap_time) and torch.equal(winners[:4], first)
    assert torch.equal(both.lap_time[4:], swapped.lap_time.flip(1))
    assert torch.equal(both.gates_passed[4:], swapped.gates_passed.flip(1))
    assert torch.equal(winners[4:], torch.where(won >= 0, 1 - won, won))
    with pytest.raises(ValueError, match="sides"):
        cross_play(spiral, baseline, RaceSet(circuit6, "1v1", 1, 0), sides="b")


def test_a_policy_against_itself_from_both_sides_wins_exactly_as_often_as_it_loses(circuit6):
    """Each placement raced twice by the same two drones, swapped: every win of one side is a loss of the other, and
    the lead at the first gate is one side's in one race of each pair."""
    data = evaluate_methods(RaceSet(circuit6, "1v1", 4, 2), {"me": SPIRAL_1V1}, against=("me", SPIRAL_1V1))
    entry = data["methods"]["me"]
    assert (data["sides"], data["races"], entry["drones"]) == ("both", 8, 8)
    assert entry["win_rate"] > 0 and entry["win_rate"] == pytest.approx(entry["loss_rate"])  # equal counts
    by_side = entry["win_rate_by_side"]
    assert (by_side["a"] + by_side["b"]) / 2 == pytest.approx(entry["win_rate"])
    assert entry["success_ratio"] == pytest.approx(entry["opponent"]["success_ratio"])  # equal counts
    # the drone first through the first gate leads on one side of each pair
    assert entry["first_gate"]["led"] == pytest.approx(0.5)  # a ratio of integer counts


@pytest.mark.bitwise
def test_a_one_team_filter_stays_with_its_method_when_the_sides_are_swapped(circuit6):
    """The method's drones carry the filter in both halves: team A's slots first, team B's in the swapped races.
    Seed 6's placements bring the drones close enough for the filter to act (the laps differ with it on either team)."""
    spiral, baseline = load_method(SPIRAL_1V1), load_method(NOSELFPLAY_1V1)
    on_a = FlightOverride(separation=SeparationCfg(distance=0.25, horizon_s=0.4, gain=1.5), separation_team="a")
    assert on_a.swapped().separation_team == "b" and on_a.swapped().swapped() == on_a
    races = RaceSet(circuit6, "1v1", 4, 6)
    both, _ = cross_play(spiral, baseline, races, sides="both", flight=on_a)
    first, _ = race_policies(races, spiral, baseline, flight=on_a)
    swapped, _ = race_policies(races, baseline, spiral, flight=on_a.swapped())
    unswapped, _ = race_policies(races, baseline, spiral, flight=on_a)  # the filter on the baseline
    assert bool(both.finished.any()) and not torch.equal(swapped.lap_time, unswapped.lap_time)
    assert torch.equal(both.lap_time[:4], first.lap_time)
    assert torch.equal(both.lap_time[4:], swapped.lap_time.flip(1))
    assert on_a.to_json()["separation_team"] == "a"
