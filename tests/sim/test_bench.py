"""Benchmark plumbing on tiny sizes (the figures themselves come from `spiral bench sim`, not from tests)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import warp as wp

from spiral.core.errors import UsageError
from spiral.sim.bench import (
    BenchExtras,
    _restorer,
    default_world_counts,
    format_bench_table,
    format_kernel_table,
    kernel_profile,
    run_build_comparison,
    run_sim_bench,
    run_sim_bench_two_process,
    time_world,
)


def test_bench_rows_and_table(kernels, gate_track):
    """Report one row per world count and layout, with moving drones and a numpy figure from the same run."""
    result = run_sim_bench([2, 3], drones=(1, 2), steps=4, repeats=1, track=gate_track)
    rows = result["results"]
    assert [(r["worlds"], r["drones"]) for r in rows] == [(2, 1), (2, 2), (3, 1), (3, 2)]
    for r in rows:
        assert abs(r["drone_substeps_per_s"] - 5 * r["drone_ctrl_steps_per_s"]) <= 3
        assert r["numpy_drone_ctrl_steps_per_s"] > 0 and r["numpy_steps"] == 4
        # rates are rounded to whole steps per second: at tiny sizes that moves their ratio by up to ~1%
        assert r["speedup_vs_numpy"] == pytest.approx(r["drone_ctrl_steps_per_s"] / r["numpy_drone_ctrl_steps_per_s"],
                                                      rel=0.01, abs=0.01)
        assert r["mean_speed_m_s"] > 0.1
    assert result["settings"]["substeps"] == 5 and result["settings"]["freeze_crashed"] is False
    assert result["device"] == "cpu" and result["machine"]["cores"] >= 1
    assert "| 3 | 2 |" in format_bench_table(result)


def test_two_process_row_sums_both_processes():
    """Run two worker interpreters together and report an aggregate no larger than their sum."""
    two = run_sim_bench_two_process(2, 2, steps=3, repeats=1)
    each = two["per_process_drone_ctrl_steps_per_s"]
    assert two["processes"] == 2 and len(each) == 2 and min(each) > 0
    assert 0 < two["aggregate_drone_ctrl_steps_per_s"] <= sum(each) + 1


def test_threaded_row_steps_the_worlds_on_the_threads_asked_for(kernels, gate_track):
    """Time Warp alone with the worlds on two threads and print it under the table."""
    row = time_world(3, 2, steps=3, repeats=1, cpu_threads=2, track=gate_track)
    assert row["cpu_threads"] == 2 and (row["worlds"], row["drones"]) == (3, 2)
    assert row["drone_ctrl_steps_per_s"] > 0 and row["mean_speed_m_s"] > 0.1
    result = run_sim_bench([2], drones=(1,), steps=3, repeats=1, track=gate_track)
    table = format_bench_table(result | {"threaded": row})
    assert "on 2 threads, 3 worlds × 2 drones" in table and "threads" not in format_bench_table(result)


def test_the_cpu_extras_are_on_by_default_on_a_cpu_and_off_and_refused_on_a_gpu():
    """A CPU run adds two processes, both builds and two threads unless told not to; a GPU run adds none, refuses
    each when asked for by its option, in one message, before building anything; a GPU's rows go up to 65536
    worlds."""
    assert BenchExtras.for_device("cpu") == BenchExtras(two_process=True, builds=True, threads=2)
    assert BenchExtras.for_device("cpu", two_process=False, builds=False, threads=1) == BenchExtras()
    assert BenchExtras.for_device("cuda:0") == BenchExtras()
    assert BenchExtras.for_device("cuda:0", two_process=False, builds=False, threads=1) == BenchExtras()
    with pytest.raises(UsageError, match=r"^--two-process, --threads 2: the simulator runs on the GPU on cuda:1"):
        BenchExtras.for_device("cuda:1", two_process=True, threads=2)
    with pytest.raises(UsageError, match=r"^--builds: .*use --device cpu$"):
        run_sim_bench([1], device="cuda:0", extras=BenchExtras(builds=True))
    assert default_world_counts("cpu") == (1, 64, 1024, 4096, 16384)
    assert default_world_counts("cuda:0") == (1, 64, 1024, 4096, 16384, 65536)


def test_crazyflow_peer_script_runs_spiral_half(tmp_path):
    """Run spiral's half of benchmarks/crazyflow_peer.py at a tiny size (crazyflow itself is never installed here)."""
    root = Path(__file__).resolve().parents[2]
    out = tmp_path / "peer.json"
    subprocess.run([sys.executable, str(root / "benchmarks" / "crazyflow_peer.py"), "--only", "spiral", "--worlds", "2",
                    "--drones", "2", "--steps", "3", "--repeats", "1", "--spiral-threads", "2", "--json", str(out)],
                   check=True, capture_output=True, text=True, cwd=root)
    result = json.loads(out.read_text())
    (row,) = result["results"]
    assert row["sim"] == "spiral" and (row["worlds"], row["drones"], row["steps"]) == (2, 2, 3)
    assert row["cpu_threads"] == 2
    assert row["drone_ctrl_steps_per_s"] > 0 and row["drone_substeps_per_s"] > 0
    assert row["settings"]["physics_hz"] == 240 and row["settings"]["ctrl_hz"] == 48


def test_kernel_profile_times_every_kernel_of_a_control_step_as_often_as_it_runs(kernels, gate_track):
    """One row per kernel of World.step, in launch order, with its launches per control step (the per-substep
    kernels once per substep) and a CPU time; the rows' sum is reported beside the whole step's time."""
    result = kernel_profile(2, 2, launches=2, repeats=1, track=gate_track)
    counts = {r["kernel"]: r["launches_per_step"] for r in result["kernels"]}
    assert counts == {"command_heading": 1, "control_and_integrate": 5, "detect_collisions_and_gate_passes": 5,
                      "apply_contacts": 5, "advance_clocks": 1, "euler_angles": 1}
    assert list(counts)[:2] == ["command_heading", "control_and_integrate"]
    for r in result["kernels"]:
        assert r["cpu_ms_per_step"] == pytest.approx(r["cpu_ms_per_launch"] * r["launches_per_step"])
        assert r["wall_ms_per_launch"] > 0
    assert result["kernels_cpu_ms"] == pytest.approx(sum(r["cpu_ms_per_step"] for r in result["kernels"]))
    assert result["step_wall_ms"] > 0 and result["settings"]["substeps"] == 5
    table = format_kernel_table(result)
    assert all(f"| `{name}` | {count} |" in table for name, count in counts.items())
    assert "2 worlds × 2 drones" in table and "| CPU per launch |" in table
    on_gpu = format_kernel_table(result | {"device": "cuda:0"})  # a GPU's kernels are read off the wall clock
    assert "| wall clock per launch |" in on_gpu
    wall = result["kernels"][1]["wall_ms_per_launch"]
    assert f"| `control_and_integrate` | 5 | {wall:.3f} ms |" in on_gpu


@pytest.mark.bitwise
def test_kernel_profile_restores_the_state_it_times_from_bit_for_bit(make_world):
    """Every repeat of the profile starts from the same state: the restorer puts positions, attitudes, rates,
    integrals and race counters back exactly, crash flags cleared, after steps that moved and crashed drones."""
    world = make_world(world_count=2, drones=2)
    world.reset_all(np.array([[-2.0, 1.4, 1.5], [-2.0, 1.6, 1.5], [-2.0, 1.0, 1.5], [-2.0, 2.0, 1.5]]))
    world.cmd.assign(np.tile(np.array([[1.0, 1.5, 1.5, 0.0]], np.float32), (4, 1)))
    for _ in range(3):
        world.step()
    before = {name: arr.numpy().copy() for name, arr in (*vars(world.state).items(), *vars(world.race).items(),
                                                         ("integral", world.integral)) if isinstance(arr, wp.array)}
    restore = _restorer(world)
    world.cmd.assign(np.tile(np.array([[0.0, 0.0, -5.0, 1.0]], np.float32), (4, 1)))  # into the ground
    for _ in range(40):
        world.step()
    assert world.race.out.numpy().any() and not np.array_equal(world.state.pos.numpy(), before["pos"])
    restore()
    for name, arr in (*vars(world.state).items(), *vars(world.race).items(), ("integral", world.integral)):
        if isinstance(arr, wp.array):
            expected = np.zeros_like(before[name]) if name == "crashed" else before[name]
            assert np.array_equal(arr.numpy(), expected), name


def test_build_comparison_times_the_portable_and_the_native_simulator_each_in_its_own_process():
    """Time both CPU builds (each repeat a fresh process with its SPIRAL_CPU_TARGET) and print their ratio."""
    builds = run_build_comparison(2, 2, steps=3, repeats=1)
    rates = builds["drone_ctrl_steps_per_s"]
    assert set(rates) == {"portable", "native"} and min(rates.values()) > 0
    assert builds["portable_over_native"] == pytest.approx(rates["portable"] / rates["native"], abs=1e-3)
    table = format_bench_table({"device": "cpu", "machine": {"cpu": "x", "cores": 2, "python": "3", "warp": "1",
                                                             "numpy": "2", "load_avg_1min": 0.0}, "results": [],
                                "builds": builds})
    assert f"portable {rates['portable']:,}, native {rates['native']:,} drone-ctrl-steps/s" in table
