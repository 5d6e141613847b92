"""One writer per output folder: a second ``benchmark`` or ``search-curves`` into the same ``--out`` is refused
at once, naming the process that holds it.

Two runs writing one folder race on its caches and progress files (one deletes a partial training the
other is resuming) and fail late with an error about a file, not about the other run. The lock is an
``fcntl.flock`` on ``OUT/.lock``: the kernel drops it when its holder exits, also when killed, so there is
no stale lock to clean up. Hand-written rather than ``filelock`` because the refusal has to name the
holder, and the holder's identity lives in the lock file itself.
"""

from __future__ import annotations

import fcntl
import json
import os
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

LOCK_NAME = ".lock"


class FolderBusyError(RuntimeError):
    """Another live process writes into the folder."""


@contextmanager
def hold_folder(folder: str | Path, what: str) -> Iterator[Path]:
    """Hold ``folder`` (created if missing) for writing while the block runs; ``what`` says what writes it
    (``"benchmark"``), for the message another process gets. Raises ``FolderBusyError`` naming the holder's
    pid, command and start time when another process holds it. The lock is released when the block ends."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK_NAME
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise FolderBusyError(f"{folder} is being written by another process ({_describe(fd)}); wait for it "
                                  f"to finish or stop it, or give another --out") from None
        holder = {"pid": os.getpid(), "what": what, "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
                  "since": time.strftime("%Y-%m-%d %H:%M:%S")}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(holder).encode(), 0)
        try:
            yield folder
        finally:
            os.ftruncate(fd, 0)  # the file stays (a lock is on the inode); emptied, it names no one
    finally:
        os.close(fd)  # releases the flock


def _describe(fd: int) -> str:
    """The holder as its lock file names it (it writes itself in just after taking the lock)."""
    for _ in range(20):
        raw = os.pread(fd, 4096, 0)
        if raw:
            try:
                h = json.loads(raw)
                return f"pid {h['pid']}, {h['what']} since {h['since']}: {h['command']}"
            except (ValueError, KeyError, TypeError):
                return f"its lock file {LOCK_NAME} is unreadable"
        time.sleep(0.05)
    return "it has not named itself yet"
