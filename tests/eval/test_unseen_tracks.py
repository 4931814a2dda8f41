"""The unseen-tracks section: the shipped policy raced on tracks, its lap against each track's reference, the table."""

from __future__ import annotations

from pathlib import Path

import pytest

from spiral.config import AIRFRAMES
from spiral.config.pipeline import UnseenTracksCfg
from spiral.eval.unseen_tracks import SCENARIOS, race_unseen_tracks, unseen_tracks_markdown

ROOT = Path(__file__).resolve().parents[2]


def test_every_track_method_and_scenario_gets_a_row_with_the_tracks_reference_lap(circuit6):
    """The shipped policy on circuit6 (its own track) in 2 one-lap races per scenario: one row per scenario, success
    in [0, 1], the race time over the laps as the mean lap and, as the race is flown by the drone at most as fast as
    the point mass, a mean lap no faster than the reference."""
    cfg = UnseenTracksCfg(races=2, laps=1)
    rows = race_unseen_tracks([("file", circuit6)], {"spiral": ROOT / "checkpoints" / "full" / "spiral.pt"}, cfg,
                              AIRFRAMES["cf2x"], log=lambda _: None)
    assert [r["scenario"] for r in rows] == list(SCENARIOS)
    solo = rows[0]
    assert solo["success"] == pytest.approx(1.0)
    assert solo["reference_lap_s"] < solo["mean_lap_s"] < 2 * solo["reference_lap_s"]
    for row in rows:
        assert 0.0 <= row["success"] <= 1.0
        assert row["reference_lap_s"] == pytest.approx(solo["reference_lap_s"])


def test_the_section_tables_each_method_by_track_with_laps_as_multiples_of_the_reference():
    rows = [{"track": "t", "kind": "held out", "reference_lap_s": 2.0, "method": "spiral", "scenario": s,
             "success": ok, "mean_lap_s": lap, "first_lap_s": None, "flying_lap_s": None}
            for s, ok, lap in (("solo", 1.0, 3.0), ("1v1", 0.5, 3.2), ("2v2", 0.0, None))]
    text = unseen_tracks_markdown(rows, UnseenTracksCfg(races=2, laps=3), "spiral run p.yaml")
    assert "**PPO Selfplay (SPIRAL)**" in text and "3 laps" in text
    assert "| t | held out | 2.00 | 1.00 / 0.50 / 0.00 | 3.00 (1.50×) | – |" in text
