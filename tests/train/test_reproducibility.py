"""Digests for comparing runs across machines: stable on one machine, written by ``spiral bench repro``."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from spiral.cli import app
from spiral.train.reproducibility import sim_digest, training_digest

runner = CliRunner()


@pytest.mark.bitwise
def test_digests_repeat_bit_for_bit_on_one_machine():
    """Give the same simulator and training digests twice in one process, and another simulator digest for another
    seed."""
    assert sim_digest(world_count=4, steps=20) == sim_digest(world_count=4, steps=20)
    assert sim_digest(world_count=4, steps=20) != sim_digest(world_count=4, steps=20, seed=1)
    assert training_digest(worlds=8, iterations=2) == training_digest(worlds=8, iterations=2)


def test_bench_repro_prints_and_writes_the_digests_with_the_arithmetic_in_force(tmp_path):
    """Print the CPU, the target and the simulator digest, and write them with the build flags as JSON."""
    out = tmp_path / "repro.json"
    result = runner.invoke(app, ["bench", "repro", "--no-training", "--json", str(out)])
    assert result.exit_code == 0, result.output
    data = json.loads(out.read_text())
    assert len(data["sim"]) == 64 and f"sim      {data['sim']}" in result.output
    assert data["numerics"]["cpu_target"] == "portable" and "training" not in data
    assert "-fno-signed-zeros" in data["numerics"]["sim_cpu_flags"]
