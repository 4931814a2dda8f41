"""The unseen-tracks section: the shipped policy raced on tracks, its lap against each track's reference, the table."""

from __future__ import annotations

from pathlib import Path

import pytest

from spiral.config import AIRFRAMES
from spiral.config.pipeline import UnseenTracksCfg
from spiral.eval.unseen_tracks import SCENARIOS, UnseenRaces, race_unseen_tracks, unseen_tracks_markdown

ROOT = Path(__file__).resolve().parents[2]


def test_the_section_tables_each_method_by_track_with_laps_as_multiples_of_the_reference():
    rows = [{"track": "t", "kind": "held out", "reference_lap_s": 2.0, "method": "spiral", "scenario": s,
             "success": ok, "mean_lap_s": lap, "first_lap_s": None, "flying_lap_s": None}
            for s, ok, lap in (("solo", 1.0, 3.0), ("1v1", 0.5, 3.2), ("2v2", 0.0, None))]
    text = unseen_tracks_markdown(UnseenRaces(rows), UnseenTracksCfg(races=2, laps=3), "spiral run p.yaml")
    assert "**PPO Selfplay (SPIRAL)**" in text and "3 laps" in text
    assert "| t | held out | 2.00 | 1.00 / 0.50 / 0.00 | 3.00 (1.50×) | – | – |" in text
    assert "Over 1 track: mean success solo 1.00 (lowest 1.00), 1v1 0.50 (lowest 0.50), 2v2 0.00 (lowest 0.00); " \
           "slowest mean lap 1.60× the reference." in text


def test_the_section_sets_a_laps_against_the_specialists_and_tables_the_duels_with_their_means():
    """A specialist's solo lap divides the method's on that track; the duels give win / loss and both teams' success
    per track and scenario, and the mean win rate over the tracks."""
    def row(track, method, lap):
        return [{"track": track, "kind": "file", "reference_lap_s": 2.0, "method": method, "scenario": s,
                 "success": 1.0, "mean_lap_s": lap, "first_lap_s": None, "flying_lap_s": None} for s in SCENARIOS]

    def duel(track, scenario, win):
        return {"track": track, "kind": "file", "method": "spiral", "against": "noselfplay", "scenario": scenario,
                "races": 4, "win_rate": win, "loss_rate": 1 - win, "success": 1.0, "opponent_success": 0.75}

    rows = [*row("a", "spiral", 3.3), *row("b", "spiral", 3.0), *row("a", "specialist", 3.0)]
    duels = [duel("a", "1v1", 0.5), duel("a", "2v2", 1.0), duel("b", "1v1", 0.75), duel("b", "2v2", 0.5)]
    text = unseen_tracks_markdown(UnseenRaces(rows, duels), UnseenTracksCfg(races=2), "spiral run p.yaml")
    assert "| a | file | 2.00 | 1.00 / 1.00 / 1.00 | 3.30 (1.65×) | 3.30 (1.65×) | 1.10× |" in text
    assert "| b | file | 2.00 | 1.00 / 1.00 / 1.00 | 3.00 (1.50×) | 3.00 (1.50×) | – |" in text
    assert "**specialist**" in text
    assert "| a | file | PPO No Selfplay | 0.50 / 0.50 | 1.00 / 0.75 | 1.00 / 0.00 | 1.00 / 0.75 |" in text
    assert "Against PPO No Selfplay: mean win rate 1v1 0.62, 2v2 0.75." in text


def test_every_method_races_each_scenario_the_first_duels_the_others_and_a_specialist_races_its_track(circuit6):
    """Two methods and circuit6's specialist (the same policy as the first method) in one-lap races on circuit6: a row
    per method and scenario with success in [0, 1] and the track's reference lap, a solo lap no faster than the point
    mass; two duel rows (1v1, 2v2) of twice the placements; the specialist's races are the first method's."""
    full = ROOT / "checkpoints" / "full"
    methods = {"spiral": full / "spiral.pt", "noselfplay": full / "ppo-noselfplay.pt"}
    races = race_unseen_tracks([("file", circuit6)], methods, UnseenTracksCfg(races=1, laps=1), AIRFRAMES["cf2x"],
                               specialists={"circuit6": full / "spiral.pt"}, log=lambda _: None)
    by = {(r["method"], r["scenario"]): r for r in races.self_matches}
    assert sorted(by) == sorted((m, s) for m in ("spiral", "noselfplay", "specialist") for s in SCENARIOS)
    solo = by[("spiral", "solo")]
    assert solo["success"] == pytest.approx(1.0)
    assert solo["reference_lap_s"] < solo["mean_lap_s"] < 2 * solo["reference_lap_s"]
    for row in races.self_matches:
        assert 0.0 <= row["success"] <= 1.0
        assert row["reference_lap_s"] == pytest.approx(solo["reference_lap_s"])
    for scenario in SCENARIOS:
        assert by[("specialist", scenario)]["success"] == pytest.approx(by[("spiral", scenario)]["success"])
    assert [(d["scenario"], d["against"], d["races"]) for d in races.duels] == [("1v1", "noselfplay", 2),
                                                                               ("2v2", "noselfplay", 2)]
    assert all(0.0 <= d["win_rate"] + d["loss_rate"] <= 1.0 for d in races.duels)
