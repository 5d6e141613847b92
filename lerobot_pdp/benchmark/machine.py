"""The CPU a record was made on. Timings depend on it, and so do the low-order bits of float results
(BLAS and vectorised kernels differ between CPU vendors and vector widths), which a fit or a training
amplifies: a record names the CPU so that figures from different machines are not taken for one run's."""

from __future__ import annotations

import platform
from functools import cache
from pathlib import Path


@cache
def cpu_model() -> str:
    """The CPU's model name as ``lscpu`` prints it (``/proc/cpuinfo``'s ``model name``); elsewhere
    ``platform.processor()``, else the architecture."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and value.strip():
                return value.strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"
