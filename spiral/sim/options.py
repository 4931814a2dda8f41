"""Compiler options of the simulator's Warp modules (each kernel module applies them with ``wp.set_module_options``).

Two CPU builds, chosen by ``SPIRAL_CPU_TARGET`` (:mod:`spiral.core.numerics`):

- ``portable`` (the default, and the ``avx2`` target's): ``x86-64-v3`` code with IEEE arithmetic only, the same
  machine code and bits on every host that runs it. On a host without x86-64-v3, the host's own code (IEEE all the
  same).
- ``native``: the host's own code (Warp's ``-march=native``) plus floating-point relaxations. ``-freciprocal-math``
  and ``-fapprox-func`` let the compiler turn a division by a square root into an approximate reciprocal square root
  (``vrsqrtss``) and a Newton step, which makes the controller faster; that instruction's bits differ between CPU
  makers, so a ``native`` build's results hold on one CPU model only.

Neither is ``-ffast-math``: its finite-math assumption lets the compiler drop the finite-value health check
(``dynamics.all_finite``), so a NaN would go unflagged (``tests/sim/test_world.py`` injects NaN and ±inf). Both stay
within the numpy reference's rounding bound (``tests/sim/test_reference.py``). ``-fno-signed-zeros`` only folds
expressions such as ``x + 0.0`` when the module is built, the same on every host. Not ``-mreassociate``: it gained
nothing measurable and took the rotor thrusts past the reference's bound.
"""

from __future__ import annotations

import warp as wp

from spiral.core.numerics import cpu_target, host_runs_x86_64_v3

__all__ = ["MODULE_OPTIONS", "PORTABLE_CPU", "cpu_build_flags"]

PORTABLE_CPU = "x86-64-v3"
"""LLVM's name of the portable level (the x86-64 psABI's v3: AVX, AVX2, FMA, BMI1/2, F16C, LZCNT, MOVBE)."""


def cpu_build_flags(target: str) -> str:
    """Warp CPU compiler flags of ``target`` (``native``, else the portable build): the CPU level, Warp's LLVM tuning
    flags and the arithmetic."""
    tuning = [f for f in (wp.config.cpu_compiler_flags or "").split() if not f.startswith("-march=")]
    if target == "native":
        return " ".join(["-march=native", *tuning, "-freciprocal-math", "-fapprox-func", "-fno-signed-zeros"])
    cpu = ["-target-cpu", PORTABLE_CPU] if host_runs_x86_64_v3() else ["-march=native"]
    return " ".join([*cpu, *tuning, "-fno-signed-zeros"])


MODULE_OPTIONS: dict[str, object] = {"cpu_compiler_flags": cpu_build_flags(cpu_target())}
"""The flags of this process's build (``SPIRAL_CPU_TARGET`` read when ``spiral.sim`` is first imported)."""
