"""Which CPU arithmetic a run uses: the same bits on every x86-64 host, or this host's fastest.

``SPIRAL_CPU_TARGET`` chooses it, before ``spiral`` is imported (``import spiral`` applies it):

- ``portable`` (default): the simulator's Warp kernels are built for ``x86-64-v3`` (AVX2, FMA, BMI2: every x86-64
  CPU from 2013-2015 on) with IEEE arithmetic only (:mod:`spiral.sim.options`), and torch's CPU kernels are held to
  their AVX2 code paths (:data:`TORCH_PORTABLE_ENV`), so that every such host, AVX2 or AVX-512, Intel or AMD, runs
  the same machine code and a run gives the same bits. A host without x86-64-v3 (an older x86-64 CPU, or another
  architecture) runs its own code, which gives another draw.
- ``native``: both build for this host and keep its floating-point shortcuts: faster, and the same bits on this CPU
  model only.

This module imports neither torch nor Warp; docs/results.md ("Reproducibility") says what each promise covers.
"""

from __future__ import annotations

import os
import platform
from pathlib import Path

__all__ = ["CPU_TARGETS", "CPU_TARGET_ENV", "TORCH_PORTABLE_ENV", "apply_cpu_target", "cpu_target",
           "host_runs_x86_64_v3", "portable_build"]

CPU_TARGET_ENV = "SPIRAL_CPU_TARGET"
"""Environment variable that selects the CPU arithmetic: one of :data:`CPU_TARGETS`."""
CPU_TARGETS = ("portable", "native")
"""The CPU arithmetic a run can use."""
TORCH_PORTABLE_ENV = {"MKL_CBWR": "AVX2", "ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2"}
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
        cpuinfo: Text of ``/proc/cpuinfo`` (read from the host when ``None``).
    """
    if cpuinfo is None:
        if platform.machine().lower() not in ("x86_64", "amd64"):
            return False
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return False
    flags = next((line.split(":", 1)[1].split() for line in cpuinfo.splitlines() if line.startswith("flags")), [])
    return set(flags) >= _V3_FLAGS


def portable_build() -> bool:
    """Whether this process builds the portable arithmetic: ``portable`` asked for, on a host that runs it."""
    return cpu_target() == "portable" and host_runs_x86_64_v3()


def apply_cpu_target() -> dict[str, str]:
    """Set :data:`TORCH_PORTABLE_ENV` in this process's environment for a portable build (a variable the user set
    is kept), and return the settings in force. Child processes inherit them."""
    if not portable_build():
        return {}
    for key, value in TORCH_PORTABLE_ENV.items():
        os.environ.setdefault(key, value)
    return {key: os.environ[key] for key in TORCH_PORTABLE_ENV}
