"""Helpers of the simulator tests: the devices a test runs on."""

from __future__ import annotations

import pytest
import warp as wp

import spiral.sim  # noqa: F401  (starts Warp quietly, before it is asked about CUDA)

ON_CUDA = pytest.param("cuda:0", marks=[pytest.mark.gpu,
                                        pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a CUDA device")])
"""The first GPU as a parameter: marked ``gpu`` and skipped without one (Warp's CUDA, which the simulator runs on;
a CPU-only torch build does not hide it)."""
DEVICES = ["cpu", ON_CUDA]
"""The devices a simulator test runs on: the CPU always, the first GPU where there is one."""
