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
    assert "vector env: 8 drones, observation (78,)" in out and "autoreset SameStep" in out
    assert re.search(r"200 steps: \d+ episodes ended", out)
    assert re.search(r"single env: episode of \d+ steps", out)
