"""Compiler options of the simulator's Warp modules (each kernel module applies them with ``wp.set_module_options``)."""

from __future__ import annotations

import warp as wp

__all__ = ["MODULE_OPTIONS"]

MODULE_OPTIONS: dict[str, object] = {
    "cpu_compiler_flags": (wp.config.cpu_compiler_flags or "-march=native")
    + " -freciprocal-math -fno-signed-zeros -fapprox-func",
}
"""Warp's default CPU flags plus floating-point relaxations that make the controller faster (the compiler may turn
divisions, e.g. by a norm, into products with approximate reciprocals). They move results at the rounding level: the
renormalised identity quaternion comes out one float32 step below 1, and the kernels stay within the numpy
reference's rounding bound (``tests/sim/test_reference.py``). Not ``-mreassociate``: it gained nothing measurable
and took the rotor thrusts past that bound (1.12 of it). Not ``-ffast-math``: its finite-math assumption lets the
compiler drop the finite-value health check (``dynamics.all_finite``), so a NaN would go unflagged; these flags keep
NaN and infinity semantics (``tests/sim/test_world.py`` injects NaN and ±inf to check)."""
