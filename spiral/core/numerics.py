"""Which CPU arithmetic a run uses: the same bits on more hosts, or this host's fastest.

``SPIRAL_CPU_TARGET`` chooses it, before ``spiral`` is imported (``import spiral`` applies it):

- ``portable`` (default): the simulator's Warp kernels are built for ``x86-64-v3`` (AVX2, FMA, BMI2: every x86-64
  CPU from 2013-2015 on) with IEEE arithmetic only (:mod:`spiral.sim.options`): the simulator gives the same bits on
  every such host, AVX2 or AVX-512, Intel or AMD. Torch picks its CPU kernels by the host (vector width and maker),
  so training on another CPU model is another draw.
- ``avx2``: the portable simulator, and torch's CPU kernels held to their AVX2 code paths (:data:`TORCH_AVX2_ENV`):
  training gives the same bits on Intel CPUs with and without AVX-512 too (not on AMD's, where MKL chooses other
  code), at the price of slower PPO updates.
- ``native``: the simulator built for this host with floating-point shortcuts, torch as it dispatches: the same bits
  on this CPU model only.

A host without x86-64-v3 (an older x86-64 CPU, or another architecture) runs its own code under every target. This
module imports neither torch nor Warp; docs/results.md ("Reproducibility") says what each promise covers and costs.
"""

from __future__ import annotations

import functools
import os
import platform
from pathlib import Path

__all__ = ["CPU_TARGETS", "CPU_TARGET_ENV", "TORCH_AVX2_ENV", "apply_cpu_target", "cpu_target",
           "host_runs_x86_64_v3", "portable_build"]

CPU_TARGET_ENV = "SPIRAL_CPU_TARGET"
"""Environment variable that selects the CPU arithmetic: one of :data:`CPU_TARGETS`."""
CPU_TARGETS = ("portable", "avx2", "native")
"""The CPU arithmetic a run can use."""
TORCH_AVX2_ENV = {"MKL_CBWR": "AVX2", "ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2"}
"""What holds torch's CPU kernels to one code path: MKL's conditional numerical reproducibility on its AVX2 branch
(matrix products), ATen's vectorised kernels at AVX2 (reductions, element-wise ops) and oneDNN's at AVX2. Each is read
when its library first computes, so they are set before torch does anything."""
_V3_FLAGS = frozenset({"avx", "avx2", "fma", "bmi1", "bmi2", "f16c", "abm", "movbe"})
"""``/proc/cpuinfo`` flags that make up x86-64-v3 (``abm`` is LZCNT)."""


def cpu_target() -> str:
    """The CPU arithmetic of this process: ``SPIRAL_CPU_TARGET``, ``portable`` when unset or empty.

    Raises:
        ValueError: for a value outside :data:`CPU_TARGETS`.
    """
    target = os.environ.get(CPU_TARGET_ENV) or "portable"
    if target not in CPU_TARGETS:
        raise ValueError(f"{CPU_TARGET_ENV}: expected one of {', '.join(CPU_TARGETS)}, got {target!r}")
    return target


def host_runs_x86_64_v3(cpuinfo: str | None = None) -> bool:
    """Whether this host runs x86-64-v3 code: an x86-64 CPU whose ``/proc/cpuinfo`` flags hold every v3 feature.

    Args:
        cpuinfo: Text of ``/proc/cpuinfo`` (this host's, read once, when ``None``).
    """
    if cpuinfo is None:
        return _this_host_runs_x86_64_v3()
    flags = next((line.split(":", 1)[1].split() for line in cpuinfo.splitlines() if line.startswith("flags")), [])
    return set(flags) >= _V3_FLAGS


@functools.cache
def _this_host_runs_x86_64_v3() -> bool:
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    try:
        return host_runs_x86_64_v3(Path("/proc/cpuinfo").read_text())
    except OSError:
        return False


def portable_build() -> bool:
    """Whether this process builds the portable simulator: ``portable`` or ``avx2`` asked for, on a host that runs
    x86-64-v3."""
    return cpu_target() != "native" and host_runs_x86_64_v3()


def apply_cpu_target() -> dict[str, str]:
    """Set :data:`TORCH_AVX2_ENV` in this process's environment for the ``avx2`` target on an x86-64-v3 host (a
    variable the user set is kept), and return the settings in force. Child processes inherit them."""
    if cpu_target() != "avx2" or not host_runs_x86_64_v3():
        return {}
    for key, value in TORCH_AVX2_ENV.items():
        os.environ.setdefault(key, value)
    return {key: os.environ[key] for key in TORCH_AVX2_ENV}
