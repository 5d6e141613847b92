"""An error PDP raises on purpose ends LeRobot's commands with its message, not under a traceback; every other error
(a library's, a bug's) keeps Python's traceback, and LEROBOT_PDP_TRACEBACK=1 keeps it for all."""

import os
import subprocess
import sys

import pytest
from conftest import lerobot_cli

from lerobot_pdp.cli_errors import raised_by_pdp


def _error_of(call):
    try:
        call()
    except Exception as e:  # noqa: BLE001 - the error under test, whatever it is
        return e, e.__traceback__
    raise AssertionError("no error")


def test_only_errors_pdp_raises_on_purpose_are_told_apart():
    from lerobot_pdp.checkpoint_files import read_config_json
    from lerobot_pdp.demonstration import episode_index

    assert raised_by_pdp(*_error_of(lambda: episode_index(0.9)))  # `raise TypeError(...)` in PDP's code
    assert not raised_by_pdp(*_error_of(lambda: read_config_json("/nonexistent/config.json")))  # pathlib's
    assert not raised_by_pdp(*_error_of(lambda: episode_index.__wrapped__))  # an AttributeError: never a message
    assert not raised_by_pdp(*_error_of(lambda: int("x")))  # raised outside PDP's code


def test_lerobot_train_ends_with_pdps_message(synthetic_meta, tmp_path):
    """A real ``lerobot-train`` whose --policy.trace_dims point past the state: PDP's message as the last line, exit
    status 1, no traceback; with LEROBOT_PDP_TRACEBACK=1 the traceback too."""
    args = [lerobot_cli("lerobot-train"), "--policy.type=pdp", "--policy.trace_dims=[0,9]", "--policy.push_to_hub=false",
            "--dataset.repo_id=local/synthetic", f"--dataset.root={synthetic_meta.root}", "--steps=1",
            "--batch_size=2", "--num_workers=0", "--wandb.enable=false", f"--output_dir={tmp_path / 'run'}"]
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(args, capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 1, proc.stderr[-3000:]
    assert "lerobot-train: error: trace_dims [0, 9] must be a non-empty list of indices into 'observation.state' of " \
           "shape (2,)" in proc.stderr, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and "LEROBOT_PDP_TRACEBACK=1 shows the traceback" in proc.stderr
    proc = subprocess.run(args, capture_output=True, text=True, timeout=300, env={**env, "LEROBOT_PDP_TRACEBACK": "1"})
    assert proc.returncode == 1 and "Traceback" in proc.stderr and "ValueError: trace_dims [0, 9]" in proc.stderr


@pytest.mark.parametrize(("script", "hooked"), [("lerobot-eval", True), ("lerobot-pdp", False), ("python", False)])
def test_only_lerobots_commands_get_the_hook(script, hooked):
    """LeRobot's commands import the plugin first; lerobot-pdp prints its errors itself, and a Python session or a
    user's script keeps Python's excepthook."""
    code = (f"import sys; sys.argv[0] = {script!r}; import lerobot_policy_pdp; "
            "print(getattr(sys.excepthook, 'pdp_errors', False))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.stdout.strip().splitlines()[-1] == str(hooked), proc.stderr[-2000:]
