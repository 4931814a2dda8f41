"""Starting Warp's runtime once per process, without its warning about a missing CUDA driver.

Warp's native initialisation always probes for the CUDA driver and, on a machine without one, prints a warning on
the process's standard error (``fd 2``) that every CPU run and every worker process would repeat. spiral checks a
requested CUDA device itself (:func:`spiral.core.device.check_device` says in one line that CUDA is not available), so
that line is dropped here; anything else Warp prints while it starts is passed on.
"""

from __future__ import annotations

import os
import sys
import tempfile

import warp as wp

__all__ = ["CUDA_DRIVER_WARNING", "init_warp"]

CUDA_DRIVER_WARNING = "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver"
"""Start of the line Warp prints when it finds no CUDA driver."""


def init_warp() -> None:
    """Initialise Warp (a no-op once done), passing on what it prints on standard error but the CUDA-driver line."""
    if wp._src.context.runtime is not None:
        return
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as captured:
        os.dup2(captured.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        captured.seek(0)
        text = captured.read().decode(errors="replace")
    kept = [line for line in text.splitlines(keepends=True) if not line.startswith(CUDA_DRIVER_WARNING)]
    if kept:
        sys.stderr.write("".join(kept))
        sys.stderr.flush()
