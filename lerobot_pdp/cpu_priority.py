"""This process's CPU scheduling policy, which LeRobot's video encoder raises and leaves raised.

LeRobot 0.6 encodes camera frames with SVT-AV1, which raises the encoding thread to real-time ``SCHED_FIFO``
priority 99 where it may (as root, in a container say) and leaves it there: the rest of that process, and every
process it starts afterwards, then competes with the whole machine at real-time priority (a test worker that had
written a video dataset ran its later trainings at SCHED_FIFO 99 beside the other worker, on two cores). Linux only;
elsewhere every function here is a no-op.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from typing import Any

Scheduling = tuple[int, Any]  # (policy, os.sched_param)


def current() -> Scheduling | None:
    """The calling thread's scheduling policy and parameters; None where the OS has no such call."""
    if not hasattr(os, "sched_getscheduler"):
        return None
    return os.sched_getscheduler(0), os.sched_getparam(0)


def restore(saved: Scheduling | None) -> bool:
    """Put the calling thread back to ``saved`` (from :func:`current`); True if it had been changed."""
    if saved is None or current() == saved:
        return False
    os.sched_setscheduler(0, *saved)
    return True


@contextlib.contextmanager
def keep_cpu_scheduling() -> Iterator[None]:
    """Run the block (a video encoding), then undo what it did to the calling thread's scheduling."""
    saved = current()
    try:
        yield
    finally:
        restore(saved)
