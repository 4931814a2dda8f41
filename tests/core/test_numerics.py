"""CPU arithmetic: the portable target's choices, the simulator's build flags, torch's kernels, the device check."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from spiral.cli import app
from spiral.core.device import check_device
from spiral.core.numerics import (
    CPU_TARGET_ENV,
    TORCH_AVX2_ENV,
    apply_cpu_target,
    cpu_target,
    host_runs_x86_64_v3,
)
from spiral.sim.options import PORTABLE_CPU, cpu_build_flags
from spiral.sim.runtime import CUDA_DRIVER_WARNING

ROOT = Path(__file__).resolve().parents[2]
runner = CliRunner()
V3 = "fpu sse sse2 ssse3 sse4_1 sse4_2 popcnt avx avx2 fma bmi1 bmi2 f16c abm movbe"
NO_CUDA = not torch.cuda.is_available()


def test_a_host_runs_x86_64_v3_only_with_every_v3_flag():
    """Read x86-64-v3 off hand-made cpuinfo text: all of AVX2, FMA, BMI1/2, F16C, LZCNT and MOVBE, or not v3."""
    assert host_runs_x86_64_v3(f"processor : 0\nflags\t\t: {V3} avx512f\n")
    assert not host_runs_x86_64_v3(f"flags : {V3.replace(' fma', '')}\n")  # e.g. an Ivy Bridge: AVX without FMA
    assert not host_runs_x86_64_v3("processor : 0\n")


def test_the_cpu_target_is_portable_unless_another_is_asked_for(monkeypatch):
    """Read SPIRAL_CPU_TARGET: unset or empty is portable, avx2 and native are themselves, anything else is an error
    naming it."""
    monkeypatch.delenv(CPU_TARGET_ENV, raising=False)
    assert cpu_target() == "portable"
    monkeypatch.setenv(CPU_TARGET_ENV, "")
    assert cpu_target() == "portable"
    for target in ("avx2", "native"):
        monkeypatch.setenv(CPU_TARGET_ENV, target)
        assert cpu_target() == target
    monkeypatch.setenv(CPU_TARGET_ENV, "fast")
    with pytest.raises(ValueError, match="SPIRAL_CPU_TARGET: expected one of portable, avx2, native, got 'fast'"):
        cpu_target()


def test_the_portable_sim_build_is_x86_64_v3_with_ieee_arithmetic_and_avx2_builds_it_too():
    """Build the portable simulator for x86-64-v3 without the relaxations that bring approximate reciprocal square
    roots; build the native one for the host with them."""
    portable, native = cpu_build_flags("portable").split(), cpu_build_flags("native").split()
    assert cpu_build_flags("avx2").split() == portable
    assert "-freciprocal-math" not in portable and "-fapprox-func" not in portable and "-ffast-math" not in portable
    assert {"-march=native", "-freciprocal-math", "-fapprox-func"} <= set(native)
    if host_runs_x86_64_v3():
        assert portable[:2] == ["-target-cpu", PORTABLE_CPU] and "-march=native" not in portable


def test_the_avx2_target_holds_torch_to_its_avx2_kernels_and_keeps_what_the_user_set(monkeypatch):
    """Set MKL's, ATen's and oneDNN's AVX2 code paths for the avx2 target on a v3 host, keeping a variable the user
    set; set nothing for the portable and native targets."""
    for key in TORCH_AVX2_ENV:
        monkeypatch.delenv(key, raising=False)
    for target in ("portable", "native"):
        monkeypatch.setenv(CPU_TARGET_ENV, target)
        assert apply_cpu_target() == {} and not any(key in os.environ for key in TORCH_AVX2_ENV)
    if not host_runs_x86_64_v3():
        pytest.skip("not an x86-64-v3 host: every target runs the host's own code")
    monkeypatch.setenv(CPU_TARGET_ENV, "avx2")
    monkeypatch.setenv("MKL_CBWR", "COMPATIBLE")
    assert apply_cpu_target() == {**TORCH_AVX2_ENV, "MKL_CBWR": "COMPATIBLE"}


@pytest.mark.skipif(not host_runs_x86_64_v3(), reason="not an x86-64-v3 host")
def test_importing_spiral_first_runs_torchs_avx2_kernels_for_the_avx2_target_only():
    """Run torch's AVX2 kernels in a process that imports spiral before torch computes with the avx2 target, and the
    kernels torch picks by itself with the default target."""
    env = {k: v for k, v in os.environ.items() if k not in TORCH_AVX2_ENV and k != CPU_TARGET_ENV}

    def capability(code: str, **extra: str) -> str:
        out = subprocess.run([sys.executable, "-c", code + "print(torch.backends.cpu.get_cpu_capability())"],
                             env={**env, **extra}, capture_output=True, text=True, check=True)
        return out.stdout.strip()

    assert capability("import spiral, torch; ", SPIRAL_CPU_TARGET="avx2") == "AVX2"
    assert capability("import spiral, torch; ") == capability("import torch; ")


def test_check_device_names_a_bad_device_in_one_line():
    """Accept cpu; reject a malformed name, naming it."""
    assert check_device("cpu") == "cpu"
    for bad in ("gpu", "cuda:", "cuda:x", "CPU"):
        with pytest.raises(ValueError, match="expected cpu, cuda or cuda:N") as info:
            check_device(bad)
        assert repr(bad) in str(info.value) and "\n" not in str(info.value)


@pytest.mark.skipif(not NO_CUDA, reason="this machine has CUDA")
def test_a_cuda_device_without_cuda_fails_with_one_line_that_says_so(tmp_path):
    """Fail `spiral eval --device cuda:0` and `spiral run --device cuda` on a machine without CUDA with one `Error:`
    line saying that CUDA is not available, before any checkpoint is read or step runs."""
    with pytest.raises(ValueError, match="CUDA is not available"):
        check_device("cuda:1")
    policy = ROOT / "checkpoints" / "full" / "spiral.pt"
    result = runner.invoke(app, ["eval", "--track", str(ROOT / "tracks" / "circuit6.yaml"), "--method", f"a={policy}",
                                 "--runs", "1", "--device", "cuda:0"])
    assert result.exit_code == 1
    assert result.output.startswith("Error: device cuda:0: CUDA is not available") and result.output.count("\n") == 1
    result = runner.invoke(app, ["run", str(ROOT / "pipelines" / "smoke.yaml"), "--device", "cuda",
                                 "--runs-dir", str(tmp_path)])
    assert result.exit_code == 1 and "Error: device cuda:0: CUDA is not available" in result.output
    assert not any(tmp_path.iterdir())


@pytest.mark.skipif(not NO_CUDA, reason="this machine has CUDA")
def test_a_cpu_run_prints_no_cuda_driver_warning():
    """Import the simulator and step a world in a fresh process on a machine without CUDA: nothing about the CUDA
    driver on standard error."""
    code = ("from spiral.sim import bench; from spiral.config import load_track; "
            "w, t, *_ = bench._make_world(load_track(bench.DEFAULT_TRACK), bench.AIRFRAMES['cf2x'], 2, 2, 'cpu', 0); "
            "w.step(); print('stepped')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "stepped"
    assert CUDA_DRIVER_WARNING not in out.stderr and "CUDA" not in out.stderr


def test_a_bad_cpu_target_is_one_error_line_of_the_cli():
    """Exit 1 with `Error: SPIRAL_CPU_TARGET: ...` when the variable holds an unknown target."""
    env = {**os.environ, CPU_TARGET_ENV: "fast"}
    out = subprocess.run([sys.executable, "-m", "spiral.cli", "validate", str(ROOT / "tracks" / "oval4.yaml")],
                         env=env, capture_output=True, text=True)
    assert out.returncode == 1
    assert out.stderr.strip() == "Error: SPIRAL_CPU_TARGET: expected one of portable, avx2, native, got 'fast'"
