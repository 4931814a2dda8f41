"""CLI of the evaluation commands: track bound, race, report."""

from __future__ import annotations

import json

import pytest
from PIL import Image
from typer.testing import CliRunner

from spiral.cli import app

runner = CliRunner()


def test_track_bound_prints_the_lap_time_and_writes_the_trajectory(sprint_yaml, tmp_path):
    """Print the point-mass lap time and write it, the limits and the node trajectory as JSON."""
    out = tmp_path / "bound.json"
    result = runner.invoke(app, ["track", "bound", str(sprint_yaml), "--steps", "8", "--json", str(out)])
    assert result.exit_code == 0, result.output
    data = json.loads(out.read_text())
    assert f"point-mass minimum lap time {data['lap_time']:.3f} s" in result.output
    assert data["gate_sequence"] == [0, 1, 0]
    assert len(data["positions"]) == sum(data["steps"]) + 1
    assert data["limits"]["a_max_level"] == pytest.approx(16.9914, abs=1e-4)


def test_track_bound_rejects_an_unknown_airframe(sprint_yaml):
    """Exit 1 with an `Error:` line naming the unknown airframe."""
    result = runner.invoke(app, ["track", "bound", str(sprint_yaml), "--airframe", "nope"])
    assert result.exit_code == 1
    assert "Error:" in result.output and "'nope'" in result.output


def test_race_command_renders_a_planner_race(sprint_yaml, tmp_path):
    """Write a GIF of a solo SE-IBR race on the 2-second sprint and report its frames."""
    out = tmp_path / "solo.gif"
    result = runner.invoke(app, ["race", "--track", str(sprint_yaml), "--method", "se-ibr", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert f"wrote {out}: 31 frames, 2.00 s of racing" in result.output
    with Image.open(out) as gif:
        assert gif.n_frames == 31


def test_report_without_stages_fails_with_an_error_line(tmp_path):
    """Exit 1 with `Error:` when RUN_DIR holds no training step's manifest."""
    result = runner.invoke(app, ["report", str(tmp_path)])
    assert result.exit_code == 1
    assert "Error:" in result.output and "no training step's manifest" in result.output


@pytest.mark.parametrize(("args", "named"), [(["--separation-team", "c"], "--separation-team"),
                                             (["--separation-team", "a"], "separation_team")],
                         ids=["unknown-team", "team-without-a-filter"])
def test_eval_refuses_a_one_team_filter_it_cannot_fly(sprint_yaml, tiny_checkpoint, args, named):
    """An unknown team, or a team for the filter of a policy trained without one (`--separation keep`): exit 1 with
    an `Error:` line naming the option."""
    result = runner.invoke(app, ["eval", "--track", str(sprint_yaml), "--scenario", "1v1", "--runs", "1",
                                 "--method", f"a={tiny_checkpoint}", *args])
    assert result.exit_code == 1
    assert "Error:" in result.output and named in result.output


def test_eval_starts_the_races_where_asked_and_says_so(sprint_yaml, tiny_checkpoint, tmp_path):
    """`--starts track` races from points along the track and records the change; an unknown kind is refused."""
    out = tmp_path / "eval.json"
    result = runner.invoke(app, ["eval", "--track", str(sprint_yaml), "--runs", "2", "--method",
                                 f"a={tiny_checkpoint}", "--starts", "track", "--json", str(out)])
    assert result.exit_code == 0, result.output
    assert 'changed from training: {"starts": "track"}' in result.output
    assert json.loads(out.read_text())["flight"] == {"starts": "track"}
    refused = runner.invoke(app, ["eval", "--track", str(sprint_yaml), "--runs", "1", "--method",
                                  f"a={tiny_checkpoint}", "--starts", "air"])
    assert refused.exit_code == 1 and "--starts" in refused.output
