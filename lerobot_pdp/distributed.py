"""Multi-process training (``accelerate launch``, ``torchrun``): one rank computes, every rank agrees.

``lerobot-train`` builds the policy on every rank, and PDP's constructor reads the whole dataset and computes
the soft-DTW distance matrix of its behaviors. Uncoordinated, every rank would compute it at the same time
(N times the work on shared cores, all racing to write the same cache file). With these helpers rank 0
computes and caches, the others then read the cache, and all check that they hold the same behavior bank.

Everything here is a no-op without an initialised ``torch.distributed`` process group (``accelerate`` creates
one for multi-process runs only), so single-process use is unchanged.

:func:`release_process_group_at_exit` works around a torch deadlock at the end of a multi-process CPU training.
"""

from __future__ import annotations

import atexit
import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager

import torch

logger = logging.getLogger(__name__)


def world() -> tuple[int, int]:
    """(rank, number of processes) of the default process group; (0, 1) without one."""
    dist = torch.distributed
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


@contextmanager
def main_process_first() -> Iterator[None]:
    """Rank 0 runs the block first; the other ranks wait at a barrier and run it afterwards.

    Rank 0 reaches the barrier also when its block raises, so the others are not left waiting: they run the
    block themselves (and most likely raise the same error).
    """
    rank, size = world()
    if size == 1:
        yield
        return
    if rank != 0:
        torch.distributed.barrier()
    try:
        yield
    finally:
        if rank == 0:
            torch.distributed.barrier()


_HELD_GROUPS: list = []


def release_process_group_at_exit() -> None:
    """Keep a reference to the default process group until the interpreter exits, and drop it there.

    lerobot-train destroys the process group (``accelerator.end_training``) before its DDP-wrapped model is freed,
    so the DDP ``Reducer`` holds the group's last reference. Its Python binding frees it holding the GIL, and
    ``~ProcessGroupGloo`` joins gloo's worker threads, one of which may still be freeing the last collective's
    tensors, which takes the GIL: a rank that had saved its checkpoint never exits (seen: a 2-process CPU
    training, rank 1 stuck there for 20 min; pytorch/pytorch#56297). The group's own Python object releases
    the GIL before destroying it, so freeing the group through this reference, at exit, cannot deadlock.
    """
    dist = torch.distributed
    if not (dist.is_available() and dist.is_initialized()):
        return
    group = dist.distributed_c10d._get_default_group()
    if any(g is group for g in _HELD_GROUPS):
        return
    if not _HELD_GROUPS:
        atexit.register(_HELD_GROUPS.clear)
    _HELD_GROUPS.append(group)


def agree_across_ranks(what: str, digest: str, note: str = "") -> list[str]:
    """Check that every rank holds the same ``what`` (compared by ``digest``); return every rank's ``note``.

    All ranks must call it (a collective). On a mismatch every rank raises the same error, instead of
    training on different data and averaging gradients that do not belong together.
    """
    rank, size = world()
    if size == 1:
        return [note]
    gathered: list[tuple[str, str] | None] = [None] * size
    torch.distributed.all_gather_object(gathered, (digest, note))
    digests = [g[0] for g in gathered if g is not None]
    if len(set(digests)) != 1:
        by_rank = ", ".join(f"rank {r}: {d[:12]}" for r, d in enumerate(digests))
        raise RuntimeError(f"the ranks disagree on {what} ({by_rank}); every rank must read the same dataset "
                           "(same --dataset.root, same files) with the same policy config")
    return [g[1] for g in gathered if g is not None]


def warn_if_cpu_launch_ran_one_process() -> bool:
    """Warn when ``accelerate launch --cpu --num_processes N`` (N > 1) started a single process.

    Without ``--mpirun_hostfile`` accelerate's ``--cpu`` launcher runs the script once, with no process group,
    and says nothing: training then silently uses one process. Its trace is ``MASTER_ADDR`` set (only for
    N > 1) with no world size in the environment. Returns whether it warned.
    """
    env = os.environ
    if (env.get("ACCELERATE_USE_CPU", "").lower() not in ("true", "1") or "MASTER_ADDR" not in env
            or any(k in env for k in ("WORLD_SIZE", "PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "MV2_COMM_WORLD_SIZE"))
            or world()[1] > 1):
        return False
    logger.warning("accelerate launch --cpu started ONE process (it needs --mpirun_hostfile for more); for N "
                   "CPU processes use: accelerate launch --multi_gpu --num_processes N ... lerobot-train "
                   "--policy.device=cpu ...")
    return True
