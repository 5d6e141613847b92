"""An error PDP raises on purpose ends LeRobot's commands with its message, not under a traceback; every other error
(a library's, a bug's) keeps Python's traceback, and LEROBOT_PDP_TRACEBACK=1 keeps it for all."""

import os
import subprocess
import sys

import pytest
from conftest import lerobot_cli

from lerobot_pdp.cli_errors import _hook, dataset_message, layout_message, pdp_message, raised_by_pdp


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


def test_pdps_message_wrapped_by_lerobot_is_told_alone_and_named_once(capsys, monkeypatch, tmp_path):
    """LeRobot's robot factory catches PDP's error and raises its own ("Error creating robot with config
    PDPSimConfig(<every field>): ..."): PDP's message is printed alone. A message that names the command already
    is not prefixed with it twice."""
    from lerobot.robots.utils import make_robot_from_config

    from lerobot_pdp.robots.config_pdp_sim import PDPSimConfig

    error, tb = _error_of(lambda: make_robot_from_config(PDPSimConfig(env="avoiding", camera_names=["oblique"],
                                                                      calibration_dir=tmp_path)))
    assert not raised_by_pdp(error, tb) and "Error creating robot with config PDPSimConfig(" in str(error)
    assert str(pdp_message(error, tb)) == "avoiding: unknown camera 'oblique'; valid cameras: top"
    assert pdp_message(*_error_of(lambda: int("x"))) is None
    monkeypatch.setattr("sys.argv", ["/venv/bin/lerobot-record"])
    shown = []
    _hook(lambda *a: shown.append(a))(type(error), error, tb)
    assert not shown and capsys.readouterr().err.startswith(
        "lerobot-record: error: avoiding: unknown camera 'oblique'; valid cameras: top\n(ValueError from lerobot_pdp")
    from lerobot_pdp.checkpoint_files import check_checkpoint_source

    (tmp_path / "config.json").write_text("{}")
    (tmp_path / "model.safetensors").write_bytes(b"")
    monkeypatch.setattr("sys.argv", ["/venv/bin/lerobot-eval"])
    named = _error_of(lambda: check_checkpoint_source(tmp_path))  # names the command: lerobot-eval would fail next
    assert str(named[0]).startswith("lerobot-eval: ")
    _hook(lambda *a: shown.append(a))(FileNotFoundError, *named)
    assert not shown and capsys.readouterr().err.startswith(f"lerobot-eval: error: {tmp_path} lacks LeRobot's "
                                                            "processor files")



def test_a_start_up_fit_stopped_by_a_signal_ends_in_one_line(capsys, monkeypatch):
    """steering.start_up_fit's KeyboardInterrupt (Ctrl-C / SIGTERM during the fit) is said in one line; any other
    KeyboardInterrupt keeps Python's own handling."""
    monkeypatch.setattr("sys.argv", ["/venv/bin/lerobot-rollout"])
    stopped = KeyboardInterrupt("SIGTERM during the start-up fit to demo episode 0, 3.2 s in: stopped before ...")
    stopped.said_by_pdp = True
    shown = []
    _hook(lambda *a: shown.append(a))(KeyboardInterrupt, stopped, None)
    assert not shown and capsys.readouterr().err == f"lerobot-rollout: stopped: {stopped}\n"
    _hook(lambda *a: shown.append(a))(KeyboardInterrupt, KeyboardInterrupt(), None)
    assert len(shown) == 1

def test_a_folder_in_lerobots_training_layout_is_pointed_to_its_checkpoint(tmp_path, capsys, monkeypatch):
    """``--policy.path=.../checkpoints/last``: LeRobot's config loader says "config.json not found in" it (with a
    traceback); the hook says it once, with the pretrained_model folder below it that holds the checkpoint."""
    from lerobot.configs.policies import PreTrainedConfig

    last = tmp_path / "checkpoints" / "last"
    (last / "pretrained_model").mkdir(parents=True)
    (last / "pretrained_model" / "config.json").write_text("{}")
    error, tb = _error_of(lambda: PreTrainedConfig.from_pretrained(str(last)))
    assert layout_message(error) == f"config.json not found in {last}; did you mean {last / 'pretrained_model'}?"
    monkeypatch.setattr("sys.argv", ["/venv/bin/lerobot-eval"])
    shown = []
    _hook(lambda *a: shown.append(a))(type(error), error, tb)
    assert not shown and capsys.readouterr().err == (f"lerobot-eval: error: config.json not found in {last}; did you "
                                                      f"mean {last / 'pretrained_model'}?\n")
    run = _error_of(lambda: PreTrainedConfig.from_pretrained(str(tmp_path)))[0]  # the run's folder: pointed too
    assert str(layout_message(run)).endswith(f"did you mean {last / 'pretrained_model'}?")
    (tmp_path / "empty").mkdir()
    other = _error_of(lambda: PreTrainedConfig.from_pretrained(str(tmp_path / "empty")))[0]  # nothing below
    assert layout_message(other) is None


def test_a_run_on_a_dataset_root_that_holds_no_dataset_says_so(synthetic_meta, tmp_path):
    """``--dataset.root`` where no dataset is: LeRobot asks the Hub and ends on a network error; said in one line
    (a real lerobot-train, offline), and nothing is said when the dataset is there."""
    assert dataset_message(["lerobot-train", f"--dataset.root={synthetic_meta.root}"]) is None
    assert dataset_message(["lerobot-train"]) is None
    assert dataset_message(["lerobot-record", f"--dataset.root={tmp_path / 'new'}"]) is None  # where it writes
    args = [lerobot_cli("lerobot-train"), "--policy.type=pdp", "--policy.push_to_hub=false",
            "--dataset.repo_id=local/nowhere", f"--dataset.root={tmp_path / 'nowhere'}", "--steps=1",
            "--wandb.enable=false", f"--output_dir={tmp_path / 'run'}"]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 1, proc.stderr[-3000:]
    assert proc.stderr.rstrip().splitlines()[-1] == (
        f"lerobot-train: error: no LeRobotDataset at --dataset.root={tmp_path / 'nowhere'} (no meta/info.json there), "
        "so LeRobot looked for the --dataset.repo_id on the Hub instead; make the dataset first (lerobot-pdp "
        "make-dataset --out DIR, or lerobot-record) or fix the path"), proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr


def test_a_run_on_episodes_the_dataset_lacks_names_them(synthetic_meta, tmp_path):
    """``--dataset.episodes`` with an episode the local dataset lacks: LeRobot asks the Hub for its files and ends
    offline on ``OfflineModeIsEnabled``; said in one line naming the episodes and the folder (a real lerobot-train)."""
    args = [lerobot_cli("lerobot-train"), "--policy.type=pdp", "--policy.push_to_hub=false",
            "--dataset.repo_id=local/synthetic", f"--dataset.root={synthetic_meta.root}", "--dataset.episodes=[0,99]",
            "--steps=1", "--batch_size=2", "--num_workers=0", "--wandb.enable=false", f"--output_dir={tmp_path / 'run'}"]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 1, proc.stderr[-3000:]
    assert proc.stderr.rstrip().splitlines()[-1] == (
        f"lerobot-train: error: --dataset.episodes lists episode(s) [99] that the dataset at --dataset.root="
        f"{synthetic_meta.root} lacks (it has 40: 0..39), so LeRobot looked for them on the Hub instead; list episodes "
        "it has"), proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr


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


def test_a_mistyped_lerobot_pdp_flag_is_named_with_its_subcommand_and_the_nearest_flag(capsys):
    """argparse names an unknown flag under the top-level usage, which lists no flag of the subcommand: the subcommand
    says it, with its usage, and the flag meant when one is near (a prefix either way, or a close spelling)."""
    from lerobot_pdp.cli import main

    for argv, said in ((["adapt", "ckpt", "--demo", "d", "--out", "o", "--step", "5"],
                        "lerobot-pdp adapt: error: unrecognized arguments: --step 5 (--step: did you mean --steps?)"),
                       (["make-dataset", "--env", "reach-around", "--out", "o", "--episodes=3"],
                        "(--episodes: did you mean --episodes-per-mode?)"),
                       (["steer", "s.json", "--mode", "2", "--checkpoint", "c"],
                        "lerobot-pdp steer: error: unrecognized arguments: --checkpoint c\n")):
        with pytest.raises(SystemExit) as done:
            main(argv)
        err = capsys.readouterr().err
        assert done.value.code == 2 and said in err and f"usage: lerobot-pdp {argv[0]}" in err, err
