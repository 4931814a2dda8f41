"""The PPO profile: FLOP counts on a hand-made network and the plumbing of one profiled iteration (its timings are
reported by `spiral bench ppo`, never asserted here)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from spiral.config import AIRFRAMES, SimCfg, StageSpec
from spiral.env import RaceSetting
from spiral.selfplay import Pool, PoolOpponents, StageSources, run_stage
from spiral.selfplay.curriculum import published_opponents
from spiral.train import StageStart
from spiral.train.profile import (
    ENV_PHASES,
    _update_parts,
    device_clock,
    linear_layers,
    matmul_seconds,
    profile_iteration,
    timed_methods,
    update_flops_per_sample,
)


def test_update_flops_count_forward_weight_and_input_gradients_but_no_input_gradient_of_a_first_layer():
    """3→4→2 actor and 3→1 critic: 2·12·2 + 2·8·3 + 2·3·2 = 108 FLOPs per sample and epoch."""
    actor = nn.Sequential(nn.Linear(3, 4), nn.ELU(), nn.Linear(4, 2))
    critic = nn.Sequential(nn.Linear(3, 1))
    layers = linear_layers(actor, critic)
    assert layers == [(3, 4), (4, 2), (3, 1)]
    assert update_flops_per_sample(layers, {0, 2}) == 48 + 48 + 12
    wall, cpu = matmul_seconds(layers, {0, 2}, 16, repeats=2)
    assert wall > 0 and cpu >= 0


def test_profiled_iteration_splits_rollout_by_hook_and_update_by_part_and_unwraps_the_env(line2):
    """Every env hook and policy call is timed, the update's parts add up to the whole, clipping is unpatched."""
    stage = StageSpec.model_validate({
        "name": "tiny", "worlds": 8, "iterations": 4, "env": {"obs": {"history_len": 1, "gate_normals": True}},
        "ppo": {"num_steps_per_env": 4, "actor_hidden_dims": [16], "critic_hidden_dims": [16]},
        "selection": {"races": 2}})
    r = profile_iteration(RaceSetting(line2, AIRFRAMES["cf2x"], SimCfg()), stage, iterations=1)
    assert set(r["rollout_parts_s"]) == {*ENV_PHASES, "act", "process_env_step", "compute_returns"}
    assert sum(r["rollout_parts_s"].values()) <= r["rollout_s"]
    parts = set(r["update_parts_share"])
    assert {"forward", "backward", "optimizer", "clip_grad_norm", "update_normalization"} <= parts
    assert sum(r["update_parts_share"].values()) == pytest.approx(1.0)
    assert r["samples_per_iteration"] == 32 and r["mini_batch"] == 32 // stage.ppo.num_mini_batches
    assert r["layers"] == [(r["obs_dim"], 16), (16, 4), (r["obs_dim"], 16), (16, 1)]
    assert r["update_samples_per_s"] == pytest.approx(32 / r["update_s"])
    assert r["update_over_matmul_limit"] == pytest.approx(r["update_s"] / r["matmul_s"])
    assert nn.utils.clip_grad_norm_.__name__ == "clip_grad_norm_"
    assert r["matmul_dtype"] == "torch.float32"


def test_the_matmul_limit_of_a_mixed_precision_update_is_timed_in_bfloat16(line2):
    """The limit is the rate of the products the update really runs: bfloat16 under ``ppo.mixed_precision``."""
    stage = StageSpec.model_validate({
        "name": "tiny", "worlds": 8, "iterations": 4, "env": {"obs": {"history_len": 1}},
        "ppo": {"num_steps_per_env": 4, "actor_hidden_dims": [16], "critic_hidden_dims": [16],
                "mixed_precision": True}, "selection": {"races": 2}})
    r = profile_iteration(RaceSetting(line2, AIRFRAMES["cf2x"], SimCfg()), stage, iterations=1)
    assert r["matmul_dtype"] == "torch.bfloat16"
    assert r["update_over_matmul_limit"] == pytest.approx(r["update_s"] / r["matmul_s"])


TINY_PPO = {"num_steps_per_env": 4, "actor_hidden_dims": [16], "critic_hidden_dims": [16]}


def test_a_profiled_self_play_stage_races_a_copy_of_the_pool_and_times_the_opponents_apart(line2, tmp_path):
    """A 1v1 stage with 2v2 worlds mixed in: the hooks of both parts and the pool members' policies are timed (the
    opponents apart from the hook that calls them), the published pool folder is left as it was, and a multi-drone
    stage without the checkpoint it starts from and its opponents is refused."""
    solo = StageSpec.model_validate({"name": "solo", "worlds": 4, "iterations": 1, "env": {"obs": {"history_len": 1}},
                                     "ppo": TINY_PPO, "selection": {"interval": 1, "races": 2}})
    run_stage(RaceSetting(line2, AIRFRAMES["cf2x"], SimCfg()), solo, tmp_path / "solo",
              sources=StageSources(pool_dir=tmp_path / "unused"), progress=False)
    init = tmp_path / "solo" / "best.pt"
    pool = Pool(tmp_path / "pool", log=lambda _: None)
    pool.add(init, stage="solo", iteration=0, evaluation={})
    before = {p.name: p.read_bytes() for p in (tmp_path / "pool").iterdir()}
    duel = StageSpec.model_validate({
        "name": "1v1", "scenario": "1v1", "worlds": 8, "iterations": 4, "env": {"obs": {"history_len": 1}},
        "mix": {"2v2": 0.5}, "ppo": TINY_PPO, "selfplay": {"p_self": 0.5, "promotion": {"races": 2}}})
    (tmp_path / "scratch").mkdir()
    opponents = published_opponents(duel, init, tmp_path / "scratch", pool_dir=tmp_path / "pool").worlds
    r = profile_iteration(RaceSetting(line2, AIRFRAMES["cf2x"], SimCfg()), duel, iterations=1,
                          start=StageStart(init, opponents))
    assert set(r["rollout_parts_s"]) == {*ENV_PHASES, "act", "process_env_step", "compute_returns", "opponents"}
    assert r["rollout_parts_s"]["opponents"] > 0 and r["rollout_parts_s"]["apply_actions"] > 0
    assert sum(r["rollout_parts_s"].values()) <= r["rollout_s"]
    assert r["samples_per_iteration"] == (4 + 2 * 4) * 4  # 4 duels and 4 team races with 2 learner drones each
    assert {p.name: p.read_bytes() for p in (tmp_path / "pool").iterdir()} == before
    assert vars(PoolOpponents)["__call__"].__name__ == "__call__"  # not the timing wrapper
    frozen = duel.model_copy(update={"selfplay": duel.selfplay.model_copy(update={"mode": "frozen"})})
    (tmp_path / "scratch2").mkdir()
    opponents = published_opponents(frozen, init, tmp_path / "scratch2").worlds
    r = profile_iteration(RaceSetting(line2, AIRFRAMES["cf2x"], SimCfg()), frozen, iterations=1,
                          start=StageStart(init, opponents))
    assert r["rollout_parts_s"]["opponents"] > 0
    with pytest.raises(ValueError, match="needs the checkpoint it starts from and its opponents"):
        profile_iteration(RaceSetting(line2, AIRFRAMES["cf2x"], SimCfg()), duel, iterations=1)


def test_on_a_cpu_the_clock_is_perf_counter_and_a_timed_method_reads_the_clock_it_is_given():
    """The CPU clock is ``time.perf_counter`` itself (nothing waits, the figures as before); a timed method is timed
    by the clock it is given, read once before and once after each call."""
    assert device_clock("cpu") is time.perf_counter and device_clock(torch.device("cpu")) is time.perf_counter

    class Thing:
        def double(self, x):
            return 2 * x

    ticks, totals = iter([1.0, 3.5, 10.0, 10.25]), {"double": 0.0}
    with timed_methods(Thing, ("double",), totals, clock=lambda: next(ticks)):
        assert Thing().double(2) == 4 and Thing().double(3) == 6
    assert totals["double"] == pytest.approx(2.75)


def test_a_trace_without_kernel_times_is_split_by_processor_time_even_when_the_gpus_share_is_asked_for():
    """Without the GPU's kernel times in a trace (a CPU run, or CUDA without its profiling library) the update's
    parts are the processor times, never all zero."""
    x = torch.randn(64, 64)
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as trace:
        torch.mm(x, x)
    parts = _update_parts(trace)
    assert parts["forward"] > 0 and _update_parts(trace, on_device=True) == pytest.approx(parts)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_on_a_gpu_the_clock_waits_for_the_queued_work():
    """A CUDA clock is not perf_counter and reads the time after the products queued before it have finished."""
    clock = device_clock("cuda:0")
    assert clock is not time.perf_counter
    x = torch.randn(2048, 2048, device="cuda:0")
    t0 = clock()
    y = x @ x
    t1 = clock()
    assert t1 > t0 and torch.cuda.current_stream().query()  # nothing left queued when the clock was read
    assert y.shape == (2048, 2048)


def test_timed_methods_put_a_classs_own_method_back():
    """Timing a class's method times every instance's calls; afterwards the class has its own method again."""
    class Thing:
        def double(self, x):
            return 2 * x

    original, totals = Thing.double, {"double": 0.0}
    with timed_methods(Thing, ("double",), totals):
        assert Thing().double(2) == 4
    assert totals["double"] > 0 and Thing.double is original


def test_timed_methods_add_up_calls_and_leave_the_object_as_it_was():
    """Two calls are both counted, results pass through, and the class's method is back afterwards."""
    class Thing:
        def double(self, x):
            return 2 * x

    thing, totals = Thing(), {"double": 0.0}
    with timed_methods(thing, ("double",), totals):
        assert thing.double(2) == 4 and thing.double(3) == 6
        assert "double" in vars(thing)
    assert totals["double"] > 0 and "double" not in vars(thing) and thing.double(1) == 2


def _benchmark(name: str):
    """The script ``benchmarks/<name>.py`` as a module."""
    root = Path(__file__).resolve().parents[2]
    spec = importlib.util.spec_from_file_location(name, root / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_time_to_solo_takes_the_first_evaluation_that_meets_both_success_and_lap():
    """A fast but unsafe evaluation and a safe but slow one do not count; the first meeting both does."""
    rows = [{"iteration": 0}, {"iteration": 19, "eval/success": 1.0, "eval/lap_time": 6.0},
            {"iteration": 39, "eval/success": 0.9, "eval/lap_time": 4.0},
            {"iteration": 59, "eval/success": 0.97, "eval/lap_time": 5.2},
            {"iteration": 79, "eval/success": 1.0, "eval/lap_time": 4.8}]
    assert _benchmark("time_to_solo").first_reaching(rows, 0.95, 5.5)["iteration"] == 59
    assert _benchmark("time_to_solo").first_reaching(rows[:3], 0.95, 5.5) is None


def test_time_to_solo_script_runs_the_smoke_pipeline(tmp_path):
    """Train the smoke pipeline's solo stage for one seed and write its row."""
    root = Path(__file__).resolve().parents[2]
    out = tmp_path / "tts.json"
    subprocess.run([sys.executable, str(root / "benchmarks" / "time_to_solo.py"), "pipelines/smoke.yaml",
                    "--seeds", "3", "--json", str(out)], check=True, capture_output=True, text=True, cwd=root)
    (row,) = json.loads(out.read_text())["results"]
    assert row["seed"] == 3 and row["iterations"] == 2 and row["stage_wall_s"] > 0


def test_ppo_update_variants_script_times_every_variant_on_the_smoke_pipeline(tmp_path):
    """Each of the four update variants (precision x mini-batch gather) is timed once per repeat."""
    root = Path(__file__).resolve().parents[2]
    out = tmp_path / "variants.json"
    subprocess.run([sys.executable, str(root / "benchmarks" / "ppo_update_variants.py"), "pipelines/smoke.yaml",
                    "--stage", "solo", "--repeats", "2", "--worlds", "8", "--json", str(out)],
                   check=True, capture_output=True, text=True, cwd=root)
    times = json.loads(out.read_text())["update_s"]
    assert set(times) == {"float32 rsl_rl", "float32 gather_once", "bfloat16 rsl_rl", "bfloat16 gather_once"}
    assert all(len(v) == 2 and min(v) > 0 for v in times.values())


@pytest.mark.bitwise
def test_pool_opponents_script_times_both_implementations_and_finds_the_same_actions(tmp_path):
    """Three members of the published pool, a few worlds: both implementations timed in each repeat, actions equal."""
    root = Path(__file__).resolve().parents[2]
    out = tmp_path / "opponents.json"
    subprocess.run([sys.executable, str(root / "benchmarks" / "pool_opponents.py"), "--members", "3", "--worlds", "16",
                    "--per-world", "2", "--repeats", "2", "--calls", "2", "--json", str(out)],
                   check=True, capture_output=True, text=True, cwd=root)
    r = json.loads(out.read_text())
    assert r["members"] == 3 and r["same_actions"] is True
    assert all(len(v) == 2 and min(v) > 0 for v in r["seconds_per_call"].values())


def test_gpu_check_quick_mode_runs_the_flight_checks_on_the_cpu(tmp_path):
    """`gpu_check.py --device cpu --quick` without its smoke pipeline (the pipeline tests run that one): the flight
    agrees with the saved reference (to the bit where the host should reproduce it), the fast path with plain
    launches, host syncs are counted in all three stages (none on the sync-free path), and rates at both tiny sizes."""
    root = Path(__file__).resolve().parents[2]
    out = tmp_path / "gpu_check.json"
    only = [arg for check in ("agreement", "graph", "host_syncs", "rates") for arg in ("--only", check)]
    proc = subprocess.run([sys.executable, str(root / "benchmarks" / "gpu_check.py"), "--device", "cpu", "--quick",
                           *only, "--json", str(out)], capture_output=True, text=True, cwd=root)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    checks = {c["check"]: c for c in json.loads(out.read_text())["checks"]}
    assert list(checks) == ["agreement", "graph", "host_syncs", "rates"]
    assert [line.split()[0] for line in proc.stdout.splitlines()[:4]] == ["PASS", "PASS", "PASS", "INFO"]
    agreement = checks["agreement"]
    assert agreement["events_equal"] and (agreement["bitwise"] or not agreement["bitwise_expected"])
    assert checks["graph"]["differing_arrays"] == [] and checks["graph"]["drones_out"] > 0
    assert set(checks["host_syncs"]["stages"]) == {"solo", "1v1", "2v2"}
    assert all(s["steps"] == 96 and s["per_step_mean"] > 0 for s in checks["host_syncs"]["stages"].values())
    free = checks["host_syncs"]["sync_free"].values()
    assert all(s["per_step_max"] == 0 and s["ended_episodes"] > 0 for s in free)  # resets included
    assert [r["worlds"] for r in checks["rates"]["rows"]] == [16, 64]
    assert all(r["env_steps_per_s"] > 0 and r["update_samples_per_s"] > 0 for r in checks["rates"]["rows"])


def test_gpu_check_smoke_fails_a_pipeline_that_publishes_no_policy(tmp_path):
    """The smoke check runs a pipeline on the device into folders of its own and passes only if both final policies
    and the report came out: a pipeline of one solo stage trains and reports on the CPU and fails it, publishing
    nothing."""
    root = Path(__file__).resolve().parents[2]
    pipeline = tmp_path / "solo_only.yaml"
    pipeline.write_text(f"kind: pipeline\nname: solo-only\ntrack: {root / 'tracks' / 'oval4.yaml'}\nstages:\n"
                        "  - {name: solo, scenario: solo, worlds: 4, iterations: 1, selection: {interval: 1, races: 2},"
                        " ppo: {num_steps_per_env: 4, actor_hidden_dims: [8], critic_hidden_dims: [8]}}\n"
                        "evaluation: {runs: 2, seed: 0}\n")
    result = _benchmark("gpu_check").smoke("cpu", pipeline=pipeline)
    assert result["status"] == "fail" and result["returncode"] == 0, result["summary"]
    assert result["steps"] >= 1 and set(result["training_devices"].values()) == {"cpu"}
    assert "published []" in result["summary"] and "report written" in result["summary"]


def test_gpu_check_agreement_passes_on_the_saved_reference_and_fails_beyond_its_tolerance(tmp_path):
    """The saved CPU reference is flown again here: same events, within the tolerances, to the bit on a host that
    runs the portable build. A reference with one position moved past the tolerance fails, and one moved by a
    rounding-size step fails only where the bits are expected."""
    gpu_check = _benchmark("gpu_check")
    same = gpu_check.agreement("cpu")
    assert same["status"] == "pass" and same["events_equal"]
    assert same["bitwise"] or not same["bitwise_expected"]
    saved = dict(np.load(gpu_check.REFERENCE))
    for step, fails in ((2e-3, True), (1e-6, same["bitwise_expected"])):
        moved = {**saved, "pos": saved["pos"].copy()}
        moved["pos"][-1, 5, 0] += np.float32(step)
        np.savez(tmp_path / "moved.npz", **moved)
        result = gpu_check.agreement("cpu", reference=tmp_path / "moved.npz")
        assert result["status"] == ("fail" if fails else "pass"), (step, result["summary"])
        moved_by = float(np.float64(moved["pos"][-1, 5, 0]) - saved["pos"][-1, 5, 0])  # the step, rounded to float32
        assert result["max_abs_diff"]["pos"] == pytest.approx(moved_by) and moved_by == pytest.approx(step, rel=0.1)


def test_gpu_check_counts_only_running_out_of_memory_as_a_size_that_does_not_fit():
    """torch's OutOfMemoryError and Warp's failed allocation are out of memory; any other error is not."""
    out_of_memory = _benchmark("gpu_check").out_of_memory
    assert out_of_memory(torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB"))
    assert out_of_memory(RuntimeError("Failed to allocate 1073741824 bytes on device 'cuda:0'"))
    assert not out_of_memory(RuntimeError("mat1 and mat2 shapes cannot be multiplied"))
    assert not out_of_memory(ValueError("out of memory"))
