"""The suite's subprocess helper: a command that outlives its timeout is killed with every process it started, also
one in a session of its own (as torchrun starts accelerate's ranks), and the failure shows what it had printed and
each process's stack (so a hung multi-process run in CI says where it hung)."""

from __future__ import annotations

import os
import re
import sys
import time

import pytest
from conftest import run_cli

_PARENT = """
import subprocess, sys, time
child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"], start_new_session=True)
print("child", child.pid, flush=True)
time.sleep(120)
"""


def test_a_timed_out_command_is_killed_with_its_children_and_shows_its_output():
    with pytest.raises(AssertionError, match=r"still ran after 3 s") as info:
        run_cli([sys.executable, "-c", _PARENT], timeout=3)
    message = str(info.value)
    assert message.count("Fatal Python error: Aborted") == 2  # the command's stack and its child's
    assert 'File "<string>", line 5' in message and 'File "<string>", line 1' in message  # where each waited
    child = int(re.search(r"^child (\d+)$", message, re.M).group(1))  # what it printed before the timeout
    for _ in range(50):  # SIGKILL is delivered asynchronously; the child is gone (or a zombie) within moments
        try:
            with open(f"/proc/{child}/stat") as f:
                if f.read().split(")")[-1].split()[0] == "Z":
                    break
        except FileNotFoundError:
            break
        time.sleep(0.1)
    else:
        os.kill(child, 9)
        pytest.fail(f"the command's child {child} outlived the timeout")
