"""Metrics: Wilson intervals against hand-computed values, lap statistics over successful laps only."""

from __future__ import annotations

import pytest
import torch

from spiral.core.outcome import race_winner
from spiral.env.racing import RaceResults
from spiral.eval.metrics import first_gate_order, lap_statistics, summarize_races, wilson_interval


@pytest.mark.parametrize(("k", "n", "expected"), [
    # p = 0.8, z² = 3.8415: centre (0.8 + 0.19208)/1.38415 = 0.71682, half 1.96·√0.025604/1.38415 = 0.22658
    (8, 10, (0.4902, 0.9433)),
    # p = 0: centre 0.19208/1.38415 = 0.13877, half 1.96·√(3.8415/400)/1.38415 = 0.13877
    (0, 10, (0.0, 0.2775)),
    # p = 1 over 50: centre 1.038415/1.07683 = 0.96433, half 0.038415/1.07683 = 0.03567
    (50, 50, (0.9287, 1.0)),
    (0, 0, (0.0, 1.0)),
])
def test_wilson_interval_matches_hand_computed_values(k, n, expected):
    """Give the 95% Wilson score interval to four decimals for hand-computed cases."""
    lo, hi = wilson_interval(k, n)
    assert lo == pytest.approx(expected[0], abs=1e-4)
    assert hi == pytest.approx(expected[1], abs=1e-4)


def test_lap_statistics_ignore_failed_laps():
    """Average only the lap times of drones that finished, whatever the others' times say."""
    laps = torch.tensor([10.0, 12.0, 0.0, 99.0])
    finished = torch.tensor([True, True, False, False])
    assert lap_statistics(laps, finished) == (pytest.approx(11.0), pytest.approx(1.0))
    assert lap_statistics(laps, torch.zeros(4, dtype=torch.bool)) == (None, None)


def test_race_summary_counts_successes_crashes_and_speed():
    """Count one success, one gate crash and one timeout among three present drones; the absent one is ignored."""
    res = RaceResults(
        finished=torch.tensor([[True, False], [False, False]]),
        crashed=torch.tensor([[False, True], [False, False]]),
        crash_kind=torch.tensor([[0, 4], [0, 0]], dtype=torch.int32),
        lap_time=torch.tensor([[8.0, 0.0], [0.0, 0.0]]),
        gates_passed=torch.tensor([[7, 2], [1, 0]]),
        distance=torch.tensor([[20.0, 3.0], [2.0, 0.0]]),
        present=torch.tensor([[True, True], [True, False]]),
    )
    s = summarize_races(res)
    assert s["drones"] == 3
    assert s["success_ratio"] == pytest.approx(1 / 3)
    assert s["lap_time_mean"] == pytest.approx(8.0)
    assert s["mean_speed"] == pytest.approx(2.5)
    assert s["crashes"] == {"ground": 0, "bounds": 0, "gate": 1, "drone": 0, "timeout": 1}
    assert s["crash_gates"] == {"2": 1}
    assert "drone_contacts" not in s  # results without crash partners (e.g. made by hand) leave it out
    assert summarize_races(res, [0])["success_ratio"] == pytest.approx(0.5)


def hand_results(finished: list[list[bool]]) -> RaceResults:
    f = torch.tensor(finished)
    zeros = torch.zeros(f.shape)
    return RaceResults(finished=f, crashed=~f, crash_kind=torch.where(f, 0, 8).int(), lap_time=zeros + 5.0 * f,
                       gates_passed=zeros.long(), distance=zeros + f * 20.0, present=torch.ones_like(f))


def test_per_race_success_needs_every_counted_drone_home():
    """Four 1v1 races: both home, one contact (both down), one of two home, both home. Per drone 5/8, per race 2/4;
    counting team A's slot only, 3 of 4 races."""
    res = hand_results([[True, True], [False, False], [True, False], [True, True]])
    s = summarize_races(res)
    assert (s["success_ratio"], s["races"], s["race_success_ratio"]) == pytest.approx((5 / 8, 4, 0.5))
    assert s["race_success_ci95"] == pytest.approx(list(wilson_interval(2, 4)))
    assert summarize_races(res, [0])["race_success_ratio"] == pytest.approx(0.75)  # a ratio of integer counts


def test_success_interval_takes_the_race_as_the_unit():
    """Drones that crash in pairs carry the information of one race, not two: 40 1v1 races, 10 with a contact,
    give p = 0.75 with SE² = Σ(k_r − 2p)²/(2R)² = (30·0.25 + 10·2.25)/6400, i.e. an effective 40 races (Wilson over
    40), where counting 80 independent drones would be narrower. One drone per race is Wilson over the races."""
    paired = hand_results([[True, True]] * 30 + [[False, False]] * 10)
    lo, hi = summarize_races(paired)["success_ci95"]
    assert (lo, hi) == pytest.approx(wilson_interval(30, 40))
    assert hi - lo > wilson_interval(60, 80)[1] - wilson_interval(60, 80)[0]
    solo = hand_results([[True]] * 45 + [[False]] * 5)
    assert summarize_races(solo)["success_ci95"] == pytest.approx(list(wilson_interval(45, 50)))


def test_success_interval_of_independent_looking_drones_is_capped_at_the_drone_count():
    """One of two drones home in every race: no spread between races, the interval is Wilson's over the drones."""
    res = hand_results([[True, False]] * 20)
    assert summarize_races(res)["success_ci95"] == pytest.approx(list(wilson_interval(20, 40)))
    assert summarize_races(hand_results([[True, True]] * 20))["success_ci95"] == pytest.approx(
        list(wilson_interval(20, 20)))


def test_action_beyond_range_is_a_share_of_the_counted_drones_racing_steps():
    """Two drones, 10 and 30 racing steps, beyond the range on x in 5 and 15 of them and on yaw in 10 and 0: shares
    20/40 and 10/40 over both; counting the first drone only, 5/10 and 10/10. Results without the counts omit it."""
    res = hand_results([[True, False]])
    res.racing_steps = torch.tensor([[10, 30]])
    res.beyond_steps = torch.tensor([[[5, 0, 0, 10], [15, 0, 0, 0]]])
    both, first = (summarize_races(res, slots)["action_beyond_range"] for slots in (None, [0]))
    assert both == pytest.approx({"x": 0.5, "y": 0.0, "z": 0.0, "yaw": 0.25})  # ratios of integer counts
    assert first == pytest.approx({"x": 0.5, "y": 0.0, "z": 0.0, "yaw": 1.0})
    assert "action_beyond_range" not in summarize_races(hand_results([[True, False]]))


def test_first_gate_order_says_how_often_the_team_first_through_the_first_gate_won():
    """Five 2v2 races (teams [0, 2] and [1, 3]), first-gate times by hand: A's second drone leads and A wins; B leads
    and wins; B leads and A wins from behind; A leads, then both teams crash (no winner); nobody reaches the gate.
    A led 2 of 5; of the 2 races A led it won 1, of the 2 B led 1; of the 3 decided races with a gate leader the
    leader won 2."""
    split = torch.zeros(5, 4, 7)
    split[:, :, 0] = torch.tensor([[0.6, 0.5, 0.4, 0.7], [0.6, 0.5, 0.0, 0.7], [0.6, 0.4, 0.9, 0.5],
                                   [0.3, 0.5, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    finished = torch.tensor([[False, False, True, True], [False, True, False, False], [True, False, False, True],
                             [False, False, False, False], [False, False, False, False]])
    lap = torch.tensor([[0.0, 0.0, 4.0, 4.2], [0.0, 4.1, 0.0, 0.0], [4.0, 0.0, 0.0, 4.3], [0.0] * 4, [0.0] * 4])
    res = hand_results(finished.tolist())
    res.split_time = split
    teams = ([0, 2], [1, 3])
    winners = race_winner(finished, lap, teams)
    assert winners.tolist() == [0, 1, 0, -1, -1]
    order = first_gate_order(res, winners, teams)
    assert order == pytest.approx({"led": 2 / 5, "leader_won": 2 / 3, "won_when_led": 1 / 2, "won_when_behind": 1 / 2})
    nobody = first_gate_order(res, torch.full((5,), -1), teams)
    assert nobody["leader_won"] is None and nobody["won_when_led"] == pytest.approx(0.0)  # a ratio of counts
