"""Whole files or nothing: every file and folder the package writes goes through here.

Runs get cut off (a machine is shut down, a disk fills, a user presses Ctrl-C); a resumed benchmark or a loading
policy must never read a truncated file as a finished one. Files are written next to their target and
renamed into place (``os.replace`` is atomic within one filesystem); folders are built in a staging
folder next to theirs and moved in when complete.
"""

from __future__ import annotations

import glob
import os
import shutil
import socket
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any


def write_file_atomic(path: str | Path, write: Callable[[Path], None]) -> None:
    """``write(tmp)`` writes the whole file at a temporary path, which then replaces ``path``.

    The temporary name keeps ``path``'s suffix (``np.save`` appends ``.npy`` otherwise); after a failed
    write no stray temporary file is left either.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_figure_atomic(fig: Any, path: str | Path, **savefig: Any) -> None:
    """Save a matplotlib figure whole or not at all, in the format its suffix names (PNG without one: the
    temporary name's ``.tmp`` is no format)."""
    fmt = Path(path).suffix[1:] or "png"
    write_file_atomic(path, lambda tmp: fig.savefig(tmp, format=fmt, **savefig))


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write a whole text file or none."""
    write_file_atomic(path, lambda tmp: tmp.write_text(text))


@contextmanager
def staging_dir(next_to: str | Path, prefix: str = ".staging-") -> Iterator[Path]:
    """A fresh folder beside ``next_to`` (same filesystem, so it or its contents can be renamed into place),
    with the permissions of a folder made by ``mkdir``, removed with whatever is left in it when the block ends,
    also on error."""
    parent = Path(next_to).parent
    parent.mkdir(parents=True, exist_ok=True)
    _sweep_stale(parent, prefix)
    # the writer named in the folder's name (host, pid): a later one can tell it was killed and sweep it
    tmp = Path(tempfile.mkdtemp(prefix=f"{prefix}{_host()}-{os.getpid()}-", dir=parent))
    try:
        probe = tmp / ".mode"  # mkdtemp's folder is its owner's alone (0700); one moved into place must not be
        probe.mkdir()
        tmp.chmod(probe.stat().st_mode & 0o7777)  # a plain mkdir's mode: 0777 less the umask
        probe.rmdir()
        yield tmp
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _host() -> str:
    return "".join(c for c in socket.gethostname() if c.isalnum())[:32] or "host"


def _sweep_stale(parent: Path, prefix: str) -> None:
    """Remove the staging folders ``prefix`` left in ``parent`` by writers of this host that no longer run (a
    process killed while writing: its ``finally`` never ran). Another host's (a shared file system) are left."""
    mine = f"{prefix}{_host()}-"
    for old in parent.glob(f"{glob.escape(mine)}*"):
        pid = old.name[len(mine):].split("-", 1)[0]
        if not pid.isdigit() or not old.is_dir():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            shutil.rmtree(old, ignore_errors=True)
        except PermissionError:  # alive, another user's
            pass


def move_into_place(staged: Path, out: Path) -> None:
    """Rename the finished ``staged`` folder to ``out``, which was checked not to exist: one created meanwhile
    (another program, a second run) is named instead of the rename's errno."""
    try:
        os.replace(staged, out)
    except OSError as e:
        if out.exists():
            raise FileExistsError(f"{out} was created while this was being written; nothing was written there: "
                                  "give a new folder") from e
        raise
