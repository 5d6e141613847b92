"""A clean console: without FFmpeg's shared libraries, LeRobot's "torchcodec cannot be loaded" warning (torchcodec's
error with one traceback per FFmpeg version) is reported in one line, once; any other torchcodec failure in full."""

from __future__ import annotations

import importlib
import logging
import re

import pytest

from lerobot_pdp import console

FALLBACK = re.compile(r"falling back to 'pyav'", re.IGNORECASE)


def _torchcodec_loads() -> bool:
    try:
        importlib.import_module("torchcodec")
        return True
    except Exception:  # not installed, or installed without FFmpeg (the case this module is about)
        return False


def _assert_clean(proc) -> None:
    out = proc.stdout + proc.stderr
    assert "Traceback" not in out, proc.stderr[-4000:]
    fallback = [line for line in out.splitlines() if FALLBACK.search(line)]
    if _torchcodec_loads():
        assert not fallback, fallback
    else:  # the fallback is still said, in exactly one line
        assert len(fallback) == 1, proc.stderr[-4000:]


def test_lerobot_train_help_prints_no_torchcodec_traceback():
    """LeRobot's plugin discovery imports lerobot_policy_pdp before parsing the config (whose dataset default
    probes torchcodec): the path of lerobot-train, lerobot-eval, lerobot-record and lerobot-rollout."""
    from conftest import lerobot_cli, run_cli

    _assert_clean(run_cli([lerobot_cli("lerobot-train"), "--help"], timeout=300))


def test_lerobot_pdp_make_dataset_prints_no_torchcodec_traceback(tmp_path):
    """lerobot-pdp's own commands (LeRobotDataset.create probes torchcodec)."""
    from conftest import lerobot_cli, run_cli

    proc = run_cli([lerobot_cli("lerobot-pdp"), "make-dataset", "--env", "reach-around", "--episodes-per-mode", "1",
                    "--out", str(tmp_path / "data")], timeout=300)
    assert (tmp_path / "data" / "meta" / "info.json").is_file()
    _assert_clean(proc)


def test_a_python_user_of_the_policy_gets_the_one_line_report(synthetic_dataset):
    """`from lerobot_pdp import PDPPolicy` in a script, then a LeRobotDataset (which probes torchcodec)."""
    import subprocess
    import sys

    code = ("from lerobot_pdp import PDPPolicy\n"
            "from lerobot.datasets.lerobot_dataset import LeRobotDataset\n"
            f"LeRobotDataset('local/x', root={str(synthetic_dataset)!r})\n")
    _assert_clean(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300))


# ---- the filter itself, on LeRobot's message as torchcodec 0.11 / LeRobot 0.6 write it ----------------------

def _block(version: int, cause: str) -> str:
    return (f"FFmpeg version {version}:\nTraceback (most recent call last):\n"
            '  File "torch/_ops.py", line 1503, in load_library\n    ctypes.CDLL(path)\n'
            f"{cause}\n\nThe above exception was the direct cause of the following exception:\n\n"
            "Traceback (most recent call last):\n"
            f"OSError: Could not load this library: torchcodec/libtorchcodec_core{version}.so\n")


def _message(causes: dict[int, str]) -> str:
    error = ("Could not load libtorchcodec. Likely causes:\n  1. FFmpeg is not properly installed ...\n"
             "\n[start of libtorchcodec loading traceback]\n"
             + "\n".join(_block(v, c) for v, c in causes.items())
             + "[end of libtorchcodec loading traceback].")
    return (f"{error}\n'torchcodec' is installed but cannot be loaded (see the error above). "
            "Falling back to 'pyav' as a default decoder.")


NO_FFMPEG = {v: f"OSError: libavutil.so.{52 + v}: cannot open shared object file: No such file or directory"
             for v in (8, 7, 6, 5, 4)}


def _record(msg: str) -> logging.LogRecord:
    return logging.LogRecord(console.LOGGER_NAME, logging.WARNING, "import_utils.py", 80, msg, (), None)


def test_missing_ffmpeg_is_one_line_once():
    f = console.TorchcodecFallbackFilter()
    first = _record(_message(NO_FFMPEG))
    assert f.filter(first)
    line = first.getMessage()
    assert "\n" not in line and "Traceback" not in line and FALLBACK.search(line)
    assert "libavutil.so.60" in line and "libavutil.so.56" in line
    assert not f.filter(_record(_message(NO_FFMPEG)))  # LeRobot asks again for each dataset config: said once


def test_other_torchcodec_failures_are_kept_in_full():
    """FFmpeg 6 present but torchcodec built for another PyTorch: a real error, shown as LeRobot logs it."""
    causes = {**NO_FFMPEG, 6: "OSError: torchcodec/libtorchcodec_core6.so: undefined symbol: _ZN3c104cuda9SetDevice"}
    f = console.TorchcodecFallbackFilter()
    for msg in (_message(causes), "Could not load libtorchcodec: something else\n" + console.MARKER):
        rec = _record(msg)
        assert f.filter(rec) and rec.getMessage() == msg
    assert console.missing_ffmpeg_libraries(_message(causes)) is None


def test_unrelated_records_pass_untouched():
    f = console.TorchcodecFallbackFilter()
    rec = _record("Detected %s version: %s")
    rec.args = ("torch", "2.11")
    assert f.filter(rec) and rec.getMessage() == "Detected torch version: 2.11"


def test_real_message_from_this_machine():
    """LeRobot's own message here, when torchcodec cannot load for want of FFmpeg."""
    if _torchcodec_loads():
        pytest.skip("torchcodec loads here")
    from lerobot.utils import import_utils

    logger = logging.getLogger(console.LOGGER_NAME)
    seen: list[logging.LogRecord] = []

    class Catch(logging.Handler):
        def emit(self, record):
            seen.append(record)

    handler, saved = Catch(), logger.filters
    logger.addHandler(handler)
    logger.filters = [console.TorchcodecFallbackFilter()]  # a fresh one: the plugin's may have reported already
    try:
        assert import_utils.get_safe_default_video_backend() == "pyav"
        assert import_utils.get_safe_default_video_backend() == "pyav"
    finally:
        logger.removeHandler(handler)
        logger.filters = saved
    if not importlib.util.find_spec("torchcodec"):
        return  # LeRobot's own one-line "not available" message
    assert len(seen) == 1 and "\n" not in seen[0].getMessage(), [r.getMessage()[:300] for r in seen]


def test_latents_print_at_a_readable_precision():
    """Logs and CLI lines show a latent rounded (files keep it whole): one phase latent keeps its nesting."""
    import numpy as np
    import torch

    from lerobot_pdp.console import latent_text

    assert latent_text(torch.tensor([[1.3870640993118286, -0.8325331807136536]])) == "[[1.3871, -0.8325]]"
    assert latent_text(np.array([0.1, 2])) == "[0.1, 2.0]"
    assert latent_text([1e6, -3.00004]) == "[1000000.0, -3.0]"
    assert latent_text(torch.tensor([[1e30, -2.5e7]])) == "[[1e+30, -25000000.0]]"  # float32's 1e30 is 1.00000002e30
    assert latent_text(None) == "None"  # a steering request back to the default latent
