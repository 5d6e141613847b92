"""The ``pdp_sim`` robot and ``pdp_waypoints`` teleoperator: in-process, and under a real ``lerobot-record``."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from lerobot.robots.utils import make_robot_from_config
from lerobot.teleoperators.utils import make_teleoperator_from_config

from lerobot_pdp.robots import PDPSimConfig
from lerobot_pdp.robots.hooks import split_environment_state
from lerobot_pdp.robots.pdp_sim import PDPSim
from lerobot_pdp.teleoperators import PDPWaypointsConfig


def _pair(tmp_path: Path, robot_kw: dict | None = None, **teleop_kw):
    robot = make_robot_from_config(PDPSimConfig(calibration_dir=tmp_path, **(robot_kw or {})))
    teleop = make_teleoperator_from_config(PDPWaypointsConfig(calibration_dir=tmp_path, **teleop_kw))
    return robot, teleop


def test_robot_and_teleop_step_with_named_values_and_reset_themselves(tmp_path):
    outcomes = tmp_path / "sub" / "outcomes.jsonl"
    robot, teleop = _pair(tmp_path, {"env": "reach-around", "scene": "0", "outcomes": str(outcomes)}, mode="2")
    try:
        teleop.connect()
        robot.connect()
        assert list(teleop.action_features) == robot.action_names == ["vx", "vy", "vz"]
        obs = robot.get_observation()
        assert list(obs) == list(robot.observation_features) == robot.state_names + robot.env_state_names
        assert all(isinstance(v, float) for v in obs.values())
        steps = 0
        sent: dict[int, list] = {0: [], 1: []}
        while True:
            robot.get_observation()  # after an episode ends, this resets the scene
            if robot.episode == 2:  # two whole episodes done
                break
            action = teleop.get_action()
            assert set(action) == set(robot.action_names)
            sent[robot.episode].append([action[n] for n in robot.action_names])
            assert robot.send_action(action) == action
            steps += 1
            assert steps < 2 * robot.suite.max_episode_steps + 2
    finally:
        robot.disconnect()
        teleop.disconnect()
    lines = [json.loads(s) for s in outcomes.read_text().splitlines()]
    assert [d["episode"] for d in lines] == [0, 1]
    for d in lines:
        assert d["success"] is True and d["collided"] is False and d["mode"] == 2 and d["ended_by"] == "success"
        assert d["actions_per_s"] > 0 and 0 < d["median_gap_s"] <= d["max_gap_s"]  # the loop's pace
        moved = np.linalg.norm(np.diff(np.asarray(sent[d["episode"]], dtype=np.float32), axis=0), axis=1)
        assert d["action_step_median"] == pytest.approx(np.median(moved), abs=1e-5)  # how smoothly it moved
        assert d["action_step_p90"] == pytest.approx(np.percentile(moved, 90), abs=1e-5)
        assert d["action_step_max"] == pytest.approx(moved.max(), abs=1e-5) and moved.max() > 0
    assert sum(d["steps"] for d in lines) == steps


def test_cameras_when_asked_for(tmp_path):
    """Camera frames come as the env renders them, uint8 (H, W, 3), declared as LeRobot camera features."""
    robot, teleop = _pair(tmp_path, {"env": "reach-around", "scene": "3", "camera_names": ["oblique", "top"],
                                     "camera_size": (32, 48)}, mode="0")
    try:
        teleop.connect()
        robot.connect()
        assert robot.observation_features["oblique"] == (32, 48, 3) == robot.observation_features["top"]
        assert len(robot.cameras) == 2
        first = robot.get_observation()
        for _ in range(5):
            robot.send_action(teleop.get_action())
        later = robot.get_observation()
        for cam in ("oblique", "top"):
            assert first[cam].shape == (32, 48, 3) and first[cam].dtype.name == "uint8"
        assert (first["top"] != later["top"]).any()  # the camera sees the agent move
    finally:
        robot.disconnect()
        teleop.disconnect()


def test_an_unfinished_episode_is_logged_as_stopped_on_disconnect(tmp_path):
    outcomes = tmp_path / "o.jsonl"
    robot, teleop = _pair(tmp_path, {"env": "avoiding", "scene": "3", "outcomes": str(outcomes)},
                          waypoints="scene")
    teleop.connect()
    robot.connect()
    for _ in range(3):
        robot.get_observation()
        robot.send_action(teleop.get_action())
    robot.disconnect()
    (line,) = [json.loads(s) for s in outcomes.read_text().splitlines()]
    assert line["steps"] == 3 and line["success"] is False and line["ended_by"] == "stopped"


def test_the_action_step_leaves_the_gripper_command_out(tmp_path):
    """The gripper switches by design: a steady velocity command with the gripper toggling has not moved."""
    outcomes = tmp_path / "o.jsonl"
    robot = make_robot_from_config(PDPSimConfig(env="pick-place", scene="0", outcomes=str(outcomes),
                                                calibration_dir=tmp_path))
    robot.connect()
    robot.get_observation()
    gripper = robot.action_names[robot.suite.segment_on_gripper]
    hold = dict.fromkeys(robot.action_names, 0.1)
    for closed in (0.0, 1.0, 0.0, 1.0):
        robot.send_action({**hold, gripper: closed})
    robot.disconnect()
    (line,) = [json.loads(s) for s in outcomes.read_text().splitlines()]
    assert line["steps"] == 4 and line["action_step_max"] == 0.0


def test_bad_input_gets_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="unknown env 'nope'"):
        make_robot_from_config(PDPSimConfig(env="nope", calibration_dir=tmp_path))
    with pytest.raises(ValueError, match="unknown camera 'side'.*top, front, oblique"):
        make_robot_from_config(PDPSimConfig(env="reach-around", camera_names=["side"], calibration_dir=tmp_path))
    with pytest.raises(ValueError, match="exactly one of"):
        PDPWaypointsConfig()
    with pytest.raises(ValueError, match="exactly one of"):
        PDPWaypointsConfig(mode="1", waypoints="scene")
    for mode in ("-1", " "):  # refused by the config, whatever the env
        with pytest.raises(ValueError, match=f"--teleop.mode={mode.strip()!r} is not a mode; expected a mode id >= 0"):
            PDPWaypointsConfig(mode=mode)
    robot = make_robot_from_config(PDPSimConfig(env="reach-around", calibration_dir=tmp_path))
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps([[0.0, "x"]]))
    far = tmp_path / "far.json"
    far.write_text(json.dumps([[5.0, 5.0, 5.0], [0.0, 0.0, 0.4]]))
    try:
        # lerobot-record makes the robot, then the teleoperator, then the dataset folder: a route the robot's env
        # cannot take is refused when the teleoperator is made, before anything is written (LeRobot's factory
        # re-raises a plugin's error as a ValueError that ends with its message)
        for kw, msg in [({"mode": "99"}, r"reach-around: mode 99 out of range \[0, 7\]"),
                        ({"mode": "sideways"}, "unknown mode 'sideways'"),
                        ({"waypoints": str(tmp_path / "none.json")}, "none.json does not exist"),
                        ({"waypoints": "scene"}, "the scene has no 'waypoints'"),
                        ({"waypoints": str(bad)}, "way-points must be"),
                        ({"waypoints": str(far)}, r"--teleop.waypoints=.*far.json: way-point 0 \[5.0, 5.0, 5.0\] lies "
                                                  r"outside reach-around's workspace")]:
            with pytest.raises(ValueError, match=msg):
                make_teleoperator_from_config(PDPWaypointsConfig(calibration_dir=tmp_path, **kw))
        with pytest.raises(LookupError, match="no pdp_sim robot with id 'other'"):
            make_teleoperator_from_config(PDPWaypointsConfig(calibration_dir=tmp_path, mode="0",
                                                             robot_id="other")).connect()
    finally:
        robot.env.close()


@pytest.mark.parametrize(("args", "message"), [
    ([], "pdp_waypoints needs exactly one of --teleop.waypoints"),
    (["--teleop.mode=1", "--teleop.waypoints=scene"], "pdp_waypoints needs exactly one of --teleop.waypoints"),
    (["--teleop.mode=-1"], "pdp_waypoints: --teleop.mode='-1' is not a mode; expected a mode id >= 0"),
    (["--teleop.mode=1", "--robot.episodes=0"], "pdp_sim: episodes must be >= 1 or None, got 0"),
])
def test_config_errors_reach_the_user_through_lerobot_record_s_parser(args, message):
    """lerobot-record parses its command line with draccus, which replaces a config's ValueError by "Couldn't
    instantiate class ..."; the configs' own reason gets through (LeRobot prints the DecodingError)."""
    import draccus
    from draccus.utils import DecodingError
    from lerobot.scripts.lerobot_record import RecordConfig

    with pytest.raises(DecodingError) as e:
        draccus.parse(config_class=RecordConfig, args=["--robot.type=pdp_sim", "--robot.env=reach-around",
                                                       "--teleop.type=pdp_waypoints", "--dataset.repo_id=local/x",
                                                       "--dataset.single_task=x", *args])
    assert message in str(e.value) and "Couldn't instantiate" not in str(e.value)


def test_split_environment_state_by_name():
    feats = {"observation.state": {"dtype": "float32", "shape": (4,), "names": ["a", "b", "g1", "g2"]},
             "action": {"dtype": "float32", "shape": (1,), "names": ["u"]}}
    out = split_environment_state(feats, ["a", "b"], ["g1", "g2"])
    assert out["observation.state"] == {"dtype": "float32", "shape": (2,), "names": ["a", "b"]}
    assert out["observation.environment_state"] == {"dtype": "float32", "shape": (2,), "names": ["g1", "g2"]}
    assert out["action"] == feats["action"]
    assert split_environment_state(feats, ["a"], ["g1"]) is feats  # other names: another robot's, untouched


# ----------------------------------------------- lerobot-record's episodes and their mode labels, in this process

ROBOT_LOG = "lerobot_pdp.robots.pdp_sim"


@pytest.fixture(scope="module")
def two_demos(tmp_path_factory) -> Path:
    """Two reach-around demonstrations (modes 1 and 2; task strings "mode <id>: <name>") as make-dataset writes them."""
    from lerobot_pdp.envs.recording import make_dataset

    return make_dataset("reach-around", tmp_path_factory.mktemp("demos") / "ds", scene=0, episodes_per_mode=1,
                        modes=[1, 2], progress=False)


def _record_one(root: Path, tmp_path: Path, resume: bool, robot_kw: dict | None = None, cut_after: int | None = None,
                **teleop_kw) -> PDPSim:
    """One episode recorded into a real dataset at ``root`` as ``lerobot-record`` (``--resume=true`` with ``resume``)
    records it: robot, teleoperator, dataset, connect, the record loop inside pdp_sim's hook, save_episode, finalize,
    disconnect. ``cut_after``: the operator ends the episode after that many steps. Returns the robot."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_pdp.envs.recording import _dataset_features
    from lerobot_pdp.robots.record_hooks import _wrap_record_loop

    robot, teleop = _pair(tmp_path, {"env": "reach-around", **(robot_kw or {})}, **teleop_kw)
    dataset = (LeRobotDataset.resume("local/ds", root=root) if resume else
               LeRobotDataset.create("local/ds", robot.suite.fps, features=_dataset_features(robot.env), root=root,
                                     use_videos=False))
    teleop.connect()
    robot.connect()

    def record_loop(robot, events, dataset=None, **kw):
        steps = 0
        while not events["exit_early"] and steps != cut_after:
            obs = robot.get_observation()
            action = robot.send_action(teleop.get_action())
            dataset.add_frame({"observation.state": np.array([obs[k] for k in robot.state_keys], np.float32),
                               "observation.environment_state": np.array([obs[k] for k in robot.env_state_keys],
                                                                         np.float32),
                               "action": np.array([action[k] for k in robot.action_keys], np.float32), "task": "x"})
            steps += 1
            assert steps <= robot.suite.max_episode_steps

    try:
        _wrap_record_loop(record_loop)(robot=robot, events={"exit_early": False}, dataset=dataset,
                                       fps=robot.suite.fps, single_task=None)
        dataset.save_episode()
    finally:
        dataset.finalize()
        robot.disconnect()
        teleop.disconnect()
    return robot


@pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="Linux scheduling calls")
def test_the_record_loop_runs_at_the_priority_the_video_encoder_took(tmp_path):
    """LeRobot's AV1 encoder leaves lerobot-record at real-time priority after an episode with cameras (as root):
    pdp_sim's next record loop runs at the priority the process had when the robot was made."""
    from lerobot_pdp.robots import record_hooks

    robot = make_robot_from_config(PDPSimConfig(calibration_dir=tmp_path))
    record_hooks.install()  # as the robot does inside lerobot-record (nothing to wrap here: it is not running)
    seen = []
    loop = record_hooks._wrap_record_loop(lambda robot, events, **kw: seen.append(os.sched_getscheduler(0)))
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))  # what the encoder does to its thread
    except PermissionError:
        pytest.skip("not allowed to raise this process's priority (not root): the encoder could not either")
    try:
        loop(robot=robot, events={"exit_early": False})
    finally:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        if robot.is_connected:
            robot.disconnect()
    assert seen == [os.SCHED_OTHER]


@pytest.mark.parametrize("label_file", [True, False])
def test_a_resumed_recording_extends_the_mode_labels(two_demos, tmp_path, label_file):
    """--resume=true: the new episode is numbered after the dataset's (env episode and outcome line too), the
    label file keeps the earlier episodes' labels (from the file when it has one, else from their task strings)
    and adds the new one."""
    import shutil

    from lerobot_pdp.episodes import read_episodes, read_mode_labels, write_mode_labels

    root, outcomes = tmp_path / "ds", tmp_path / "o.jsonl"
    shutil.copytree(two_demos, root)
    if label_file:  # labels other than the task strings' (1, 2): the file's are the ones kept
        write_mode_labels(root, {0: 5, 1: 6}, {5: "kept"})
    robot = _record_one(root, tmp_path, resume=True, robot_kw={"outcomes": str(outcomes)}, mode="3")
    (line,) = [json.loads(x) for x in outcomes.read_text().splitlines()]
    assert robot.episode == 2 and line["episode"] == 2 and line["mode"] == 3 and line["success"]
    names = robot.suite.mode_names
    if label_file:
        assert read_mode_labels(root) == ({0: 5, 1: 6, 2: 3}, {5: "kept", 3: names[3]})
    else:
        assert read_mode_labels(root) == ({0: 1, 1: 2, 2: 3}, {1: names[1], 2: names[2], 3: names[3]})
    assert read_episodes(root, [])[2]["task"] == f"mode 3: {names[3]}"


def test_a_resumed_recording_of_an_unlabelled_episode_removes_the_stale_label_file(two_demos, tmp_path, caplog):
    """A resumed episode with no training mode (cut after 3 steps): no label file can cover every episode, so the
    old one (episodes 0 and 1 only, which training would refuse) is removed, with a warning that says so."""
    import logging
    import shutil

    from lerobot_pdp.episodes import read_episodes, write_mode_labels

    root = tmp_path / "ds"
    shutil.copytree(two_demos, root)
    write_mode_labels(root, {0: 1, 1: 2})
    with caplog.at_level(logging.INFO, logger=ROBOT_LOG):
        robot = _record_one(root, tmp_path, resume=True, cut_after=3, mode="3")
    assert robot.recorded_labels == ["novel"]
    assert not (root / "meta" / "mode_labels.json").exists()
    (warning,) = [r.getMessage() for r in caplog.records if r.name == ROBOT_LOG and r.levelname == "WARNING"]
    assert ("episodes [2] have no training mode (labels ['novel']), episodes [0, 1] have one" in warning
            and "removed" in warning and "mode_labels.json" in warning)
    assert [e.get("mode") for e in read_episodes(root, []).values()] == [None] * 3  # training reads the tasks


def test_one_demonstration_of_a_new_route_logs_no_warning(tmp_path, caplog):
    """deploy.md's one-demonstration recording (the scene's own way-points, a route of no training mode): no
    label file, and an info line, not a warning (nothing is wrong)."""
    import logging

    root = tmp_path / "demo"
    with caplog.at_level(logging.INFO, logger=ROBOT_LOG):
        robot = _record_one(root, tmp_path, resume=False, robot_kw={"scene": "3"}, waypoints="scene")
    assert robot.recorded_labels == ["novel"] and not (root / "meta" / "mode_labels.json").exists()
    logged = [(r.levelname, r.getMessage()) for r in caplog.records if r.name == ROBOT_LOG]
    assert ("INFO", "pdp_sim: no meta/mode_labels.json: no episode has a training mode (1 episodes, labels ['novel'])") \
        in logged and "WARNING" not in dict(logged)


def _record_cmd(tmp: Path, root: Path, episodes: int, *extra: str) -> list[str]:
    """A ``lerobot-record`` command line: pdp_sim in reach-around, driven by pdp_waypoints, into ``root``."""
    from conftest import lerobot_cli

    return [lerobot_cli("lerobot-record"), "--robot.type=pdp_sim", "--robot.env=reach-around",
            f"--robot.calibration_dir={tmp / 'cal'}", "--teleop.type=pdp_waypoints",
            f"--teleop.calibration_dir={tmp / 'cal'}", "--dataset.repo_id=local/pdp_sim_rec", f"--dataset.root={root}",
            f"--dataset.num_episodes={episodes}", "--dataset.fps=50", "--dataset.episode_time_s=30",
            "--dataset.reset_time_s=0.5", "--dataset.video=false", "--dataset.push_to_hub=false", "--play_sounds=false",
            "--display_data=false", *extra]


def _cli_env(tmp: Path) -> dict[str, str]:
    return {"HF_LEROBOT_HOME": str(tmp / "home"), "DISPLAY": "", "WAYLAND_DISPLAY": ""}


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, Path]:
    """Two reach-around mode-1 demos recorded by a real ``lerobot-record`` with pdp_sim + pdp_waypoints."""
    from conftest import run_cli

    tmp = tmp_path_factory.mktemp("record")
    root, outcomes = tmp / "ds", tmp / "outcomes.jsonl"
    run_cli(_record_cmd(tmp, root, 2, "--robot.scene=0", f"--robot.outcomes={outcomes}", "--teleop.mode=1"),
            timeout=300, env=_cli_env(tmp))
    return root, outcomes


@pytest.mark.slow
def test_lerobot_record_writes_a_make_dataset_shaped_dataset(recorded, tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    from lerobot_pdp.envs.recording import make_dataset
    from lerobot_pdp.episodes import read_episodes, read_mode_labels

    root, outcomes = recorded
    ref = make_dataset("reach-around", tmp_path / "ref", scene=0, episodes_per_mode=1, modes=[1], progress=False)
    got, want = LeRobotDatasetMetadata("local/a", root=root), LeRobotDatasetMetadata("local/b", root=ref)
    assert got.features == want.features  # same keys, dtypes, shapes and names
    assert got.fps == want.fps and got.total_episodes == 2
    assert list(got.tasks.index) == list(want.tasks.index) == ["mode 1: over-wide"]
    assert read_mode_labels(root) == ({0: 1, 1: 1}, {1: "over-wide"})
    lines = [json.loads(s) for s in outcomes.read_text().splitlines()]
    assert len(lines) == 2 and all(d["success"] and not d["collided"] and d["mode"] == 1 for d in lines)
    # each recorded episode is exactly one env episode: it ends on the step that reached the goal
    eps = read_episodes(root, ["observation.state", "action"])
    assert [len(e["action"]) for e in eps.values()] == [d["steps"] for d in lines]
    assert all(e["mode"] == 1 for e in eps.values())


@pytest.mark.slow
def test_pdp_trains_on_the_recorded_dataset_with_lerobot_train(recorded, tmp_path):
    from conftest import train_tiny_pdp

    root, _ = recorded
    ckpt = train_tiny_pdp(root, tmp_path / "train", steps=3)
    cfg = json.loads((ckpt / "config.json").read_text())
    assert cfg["type"] == "pdp" and (ckpt / "model.safetensors").is_file()


@pytest.mark.slow
def test_lerobot_record_resume_extends_the_recording_and_its_mode_labels(recorded, tmp_path):
    """``lerobot-record --resume=true`` (it needs deepdiff, which the install brings): the new episodes follow
    the dataset's, in pdp_sim's log and outcome lines too, and the label file labels every episode."""
    import shutil

    from conftest import run_cli

    from lerobot_pdp.episodes import read_episodes, read_mode_labels

    root, outcomes = tmp_path / "ds", tmp_path / "o.jsonl"
    shutil.copytree(recorded[0], root)
    proc = run_cli(_record_cmd(tmp_path, root, 1, "--robot.scene=0", f"--robot.outcomes={outcomes}", "--teleop.mode=2",
                               "--resume=true"), timeout=300, env=_cli_env(tmp_path))
    (line,) = [json.loads(x) for x in outcomes.read_text().splitlines()]
    assert line["episode"] == 2 and line["mode"] == 2 and line["success"]
    assert "pdp_sim episode 2:" in proc.stderr and "no meta/mode_labels.json" not in proc.stderr
    assert read_mode_labels(root) == ({0: 1, 1: 1, 2: 2}, {1: "over-wide", 2: "left-tight"})
    assert read_episodes(root, [])[2]["task"] == "mode 2: left-tight"


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["99", "-1"])
def test_lerobot_record_refuses_a_mode_the_env_lacks_before_writing(tmp_path, mode):
    """A --teleop.mode out of the env's range is refused before lerobot-record makes the dataset folder, so the
    corrected command can run with the same --dataset.root."""
    import subprocess

    root = tmp_path / "ds"
    proc = subprocess.run(_record_cmd(tmp_path, root, 1, f"--teleop.mode={mode}"), capture_output=True, text=True,
                          timeout=300, env={**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1",
                                            **_cli_env(tmp_path)})
    assert proc.returncode != 0
    expected = ("reach-around: mode 99 out of range [0, 7]" if mode == "99" else
                "pdp_waypoints: --teleop.mode='-1' is not a mode; expected a mode id >= 0")
    assert expected in proc.stderr, proc.stderr[-3000:]
    assert not root.exists()
