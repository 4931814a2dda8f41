"""spiral: self-play training of autonomous racing drones."""

from __future__ import annotations

import contextlib

from spiral.core.numerics import apply_cpu_target

__all__ = ["__version__"]

__version__ = "0.2.0"

# Before torch computes anything: torch reads these when each of its libraries first runs. A bad SPIRAL_CPU_TARGET is
# not raised here, on import: spiral.sim raises it when it builds its kernels, and the CLI prints it as an error.
with contextlib.suppress(ValueError):
    apply_cpu_target()
