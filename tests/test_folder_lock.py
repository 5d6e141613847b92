"""One writer per output folder: a second run into a held ``--out`` is refused at once, naming the holder."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from lerobot_pdp.folder_lock import LOCK_NAME, FolderBusyError, hold_folder

LERO_PDP = str(Path(sys.executable).with_name("lerobot-pdp"))
HOLD = ("import sys, time\nfrom lerobot_pdp.folder_lock import hold_folder\n"
        "with hold_folder(sys.argv[1], 'benchmark'):\n    print('held', flush=True)\n    time.sleep(120)\n")


def holder(folder: Path) -> subprocess.Popen:
    """Another process holding ``folder`` (as a running benchmark does), ready when it says so."""
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_writer_is_refused_naming_the_holder(tmp_path):
    out = tmp_path / "run"
    proc = holder(out)
    try:
        with pytest.raises(FolderBusyError, match=rf"{out} is being written by another process \(pid {proc.pid}, "
                                                  r"benchmark since .*\); .*give another --out"):
            with hold_folder(out, "search-curves"):
                pass
        # the CLI refuses before generating data or training anything, in one line with the holder's pid
        r = subprocess.run([LERO_PDP, "benchmark", "--env", "reach-around", "--quick", "--no-figures",
                            "--out", str(out)], capture_output=True, text=True, timeout=300,
                           env={**os.environ, "OMP_NUM_THREADS": "1"})
        assert r.returncode == 2 and f"pid {proc.pid}" in r.stderr and "Traceback" not in r.stderr, r.stderr
        assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME], "nothing written beside the holder's run"
    finally:
        proc.kill()
        proc.wait()


def test_a_killed_holder_leaves_no_stale_lock(tmp_path):
    out = tmp_path / "run"
    proc = holder(out)
    assert json.loads((out / LOCK_NAME).read_text())["pid"] == proc.pid
    os.kill(proc.pid, signal.SIGKILL)  # as a machine shut down or `kill -9`: no cleanup runs
    proc.wait()
    with hold_folder(out, "benchmark"):  # the kernel dropped its lock: the folder is free again
        assert json.loads((out / LOCK_NAME).read_text())["pid"] == os.getpid()
    assert (out / LOCK_NAME).read_text() == ""  # released: it names no one
    with hold_folder(out, "benchmark"), pytest.raises(FolderBusyError, match=f"pid {os.getpid()}"):
        with hold_folder(out, "benchmark"):  # a second hold in the same process is refused too
            pass
