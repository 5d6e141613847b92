"""How many CPU threads torch uses in a process that runs PDP.

Torch starts one OpenMP thread per core, and its threads spin at every operator's barrier. A PDP step is
thousands of small operators, so when anything else wants those cores (LeRobot's loader workers, a second
training, an evaluation beside it) each barrier waits for a descheduled thread. On the 2-core machine, one
thread made ``lerobot-train`` 2.3x faster alone and 3.2x faster beside a second training, and a fit 1.9x
faster beside it (docs/performance.md, "Threads"). PDP therefore takes half the cores it may run on (at
least one) unless told otherwise, so two jobs side by side never oversubscribe them.
"""

from __future__ import annotations

import logging
import os

import torch

log = logging.getLogger(__name__)

# Environment variables through which a user (or a parent process) has already chosen the thread count.
USER_THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS")


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity, which containers and ``taskset`` narrow)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        return os.cpu_count() or 1


def auto_threads() -> int:
    """Half the usable cores, at least one."""
    return max(1, usable_cores() // 2)


def choose_cpu_threads(cpu_threads: int | None) -> int | None:
    """The torch thread count PDP sets for ``PDPConfig.cpu_threads``, or None to leave torch's own.

    ``n >= 1``: n threads. ``0``: torch's own setting. ``None`` (auto): :func:`auto_threads`, never more
    than the process already uses; left alone when ``OMP_NUM_THREADS`` / ``MKL_NUM_THREADS`` is set (an
    explicit choice wins)."""
    if cpu_threads is not None:
        return cpu_threads or None
    if any(os.environ.get(v) for v in USER_THREAD_VARS):
        return None
    return min(auto_threads(), torch.get_num_threads())


def apply_cpu_threads(cpu_threads: int | None) -> None:
    """Set torch's intra-op threads as :func:`choose_cpu_threads` says; log the change once."""
    n = choose_cpu_threads(cpu_threads)
    before = torch.get_num_threads()
    if n is None or n == before:
        return
    torch.set_num_threads(n)
    how = "PDPConfig.cpu_threads" if cpu_threads is not None else "auto: half the usable cores"
    log.info("PDP: torch now uses %d CPU thread(s) instead of %d (%s; --policy.cpu_threads=N to choose, "
             "0 keeps torch's default)", n, before, how)
