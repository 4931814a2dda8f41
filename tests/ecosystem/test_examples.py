"""The scripts in examples/ run as written (in this process, to skip a second import of torch and Warp)."""

from __future__ import annotations

import re
import runpy
import sys
import tempfile
from pathlib import Path

import pytest
import torch

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.fixture
def script_env(monkeypatch, tmp_path):
    """Run a script with no arguments, its temporary files under tmp_path, and torch's thread count restored."""
    monkeypatch.setattr(sys, "argv", ["example"])
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    threads = torch.get_num_threads()
    yield tmp_path
    torch.set_num_threads(threads)


def test_train_custom_track_trains_saves_and_races(script_env, capsys):
    """Train 5 iterations on the Python-defined track, write best.pt and race 16 worlds."""
    runpy.run_path(str(EXAMPLES / "train_custom_track.py"), run_name="__main__")
    out = capsys.readouterr().out
    assert "trained 5 iterations, 2560 env steps" in out
    assert list(script_env.glob("spiral-example-*/best.pt"))
    success = float(re.search(r"success (\d\.\d\d)", out).group(1))
    assert 0.0 <= success <= 1.0


def test_gym_loop_steps_the_vector_and_the_single_env(script_env, capsys):
    """Step 8 drones for 200 steps and fly one single-env episode to its end."""
    runpy.run_path(str(EXAMPLES / "gym_loop.py"), run_name="__main__")
    out = capsys.readouterr().out
    # 12 ego + 2 presence + 25 extras (the default layout's) + 4 history entries of 16
    assert "vector env: 8 drones, observation (103,)" in out and "autoreset SameStep" in out
    assert re.search(r"200 steps: \d+ episodes ended", out)
    assert re.search(r"single env: episode of \d+ steps", out)


def test_separation_probe_races_a_policy_with_each_filter_setting(script_env, policy_checkpoint, monkeypatch, capsys):
    """Self-match with no filter and with one, then cross-play against itself: one line per setting."""
    track = str(EXAMPLES.parent / "tracks" / "circuit6.yaml")
    base = ["separation_probe.py", str(policy_checkpoint), "2v2", "--track", track, "--runs", "4", "--seed", "3"]
    monkeypatch.setattr(sys, "argv", [*base, "--filter", "none", "--filter", "0.25,0.4,1.5"])
    runpy.run_path(str(EXAMPLES / "separation_probe.py"), run_name="__main__")
    lines = capsys.readouterr().out.strip().splitlines()[-2:]
    assert [line.split(":")[0].strip() for line in lines] == ["none", "0.25,0.4,1.5"]
    assert all(0.0 <= float(re.search(r"success (\d\.\d+)", line).group(1)) <= 1.0 for line in lines)
    monkeypatch.setattr(sys, "argv", [*base, "--against", str(policy_checkpoint), "--filter", "0.3,0.2,1.0"])
    runpy.run_path(str(EXAMPLES / "separation_probe.py"), run_name="__main__")
    line = capsys.readouterr().out.strip().splitlines()[-1]
    shares = [float(x) for x in re.search(r"win (\S+) loss (\S+) draw (\S+)", line).groups()]
    assert line.startswith("0.3,0.2,1.0") and abs(sum(shares) - 1.0) < 2e-3


def test_crossplay_leads_accounts_for_every_lost_lead(script_env, policy_checkpoint, monkeypatch, capsys):
    """A policy raced against itself: rates sum to one, and each team's lost leads are at most its leads."""
    track = str(EXAMPLES.parent / "tracks" / "circuit6.yaml")
    monkeypatch.setattr(sys, "argv", ["crossplay_leads.py", str(policy_checkpoint), str(policy_checkpoint), "1v1",
                                      "--track", track, "--runs", "4", "--seed", "3", "--passage", "0"])
    runpy.run_path(str(EXAMPLES / "crossplay_leads.py"), run_name="__main__")
    lines = capsys.readouterr().out.strip().splitlines()[-5:]
    shares = [float(x) for x in re.search(r"win (\S+) loss (\S+) draw (\S+)", lines[0]).groups()]
    assert abs(sum(shares) - 1.0) < 2e-3
    for line in (lines[1], lines[3]):
        leads, lost, by_crash = (int(x) for x in re.search(r"in (\d+), loses (\d+) of them, (\d+) with", line).groups())
        assert 0 <= by_crash <= lost <= leads <= 4
    assert all(re.search(r"crashes of 4 drones", line) for line in (lines[2], lines[4]))
