"""The ``pdp_sim`` robot and ``pdp_waypoints`` teleoperator: in-process, and under a real ``lerobot-record``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from lerobot.robots.utils import make_robot_from_config
from lerobot.teleoperators.utils import make_teleoperator_from_config

from lerobot_pdp.robots import PDPSimConfig
from lerobot_pdp.robots.hooks import split_environment_state
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
    robot = make_robot_from_config(PDPSimConfig(env="reach-around", calibration_dir=tmp_path))
    try:
        for kw, err, msg in [({"mode": "99"}, ValueError, "out of range"),
                             ({"mode": "sideways"}, ValueError, "unknown mode 'sideways'"),
                             ({"waypoints": str(tmp_path / "none.json")}, FileNotFoundError, "does not exist"),
                             ({"waypoints": "scene"}, ValueError, "the scene has no 'waypoints'")]:
            teleop = make_teleoperator_from_config(PDPWaypointsConfig(calibration_dir=tmp_path, **kw))
            with pytest.raises(err, match=msg):
                teleop.connect()
        bad = tmp_path / "bad.json"
        bad.write_text(json.dumps([[0.0, "x"]]))
        teleop = make_teleoperator_from_config(PDPWaypointsConfig(calibration_dir=tmp_path, waypoints=str(bad)))
        with pytest.raises(ValueError, match="way-points must be"):
            teleop.connect()
        with pytest.raises(LookupError, match="no pdp_sim robot with id 'other'"):
            make_teleoperator_from_config(PDPWaypointsConfig(calibration_dir=tmp_path, mode="0",
                                                             robot_id="other")).connect()
    finally:
        robot.env.close()


def test_split_environment_state_by_name():
    feats = {"observation.state": {"dtype": "float32", "shape": (4,), "names": ["a", "b", "g1", "g2"]},
             "action": {"dtype": "float32", "shape": (1,), "names": ["u"]}}
    out = split_environment_state(feats, ["a", "b"], ["g1", "g2"])
    assert out["observation.state"] == {"dtype": "float32", "shape": (2,), "names": ["a", "b"]}
    assert out["observation.environment_state"] == {"dtype": "float32", "shape": (2,), "names": ["g1", "g2"]}
    assert out["action"] == feats["action"]
    assert split_environment_state(feats, ["a"], ["g1"]) is feats  # other names: another robot's, untouched


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, Path]:
    """Two reach-around mode-1 demos recorded by a real ``lerobot-record`` with pdp_sim + pdp_waypoints."""
    from conftest import lerobot_cli, run_cli

    tmp = tmp_path_factory.mktemp("record")
    root, outcomes = tmp / "ds", tmp / "outcomes.jsonl"
    run_cli([lerobot_cli("lerobot-record"), "--robot.type=pdp_sim", "--robot.env=reach-around", "--robot.scene=0",
             f"--robot.outcomes={outcomes}", f"--robot.calibration_dir={tmp / 'cal'}",
             "--teleop.type=pdp_waypoints", "--teleop.mode=1", f"--teleop.calibration_dir={tmp / 'cal'}",
             "--dataset.repo_id=local/pdp_sim_rec", f"--dataset.root={root}", "--dataset.num_episodes=2",
             "--dataset.fps=50", "--dataset.episode_time_s=30", "--dataset.reset_time_s=0.5",
             "--dataset.video=false", "--dataset.push_to_hub=false", "--play_sounds=false", "--display_data=false"],
            timeout=300, env={"HF_LEROBOT_HOME": str(tmp / "home"), "DISPLAY": "", "WAYLAND_DISPLAY": ""})
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
    from conftest import lerobot_cli, run_cli

    root, _ = recorded
    out = tmp_path / "train"
    run_cli([lerobot_cli("lerobot-train"), "--policy.type=pdp", "--policy.push_to_hub=false", "--policy.device=cpu",
             "--policy.down_dims=[16,32]", "--dataset.repo_id=local/pdp_sim_rec", f"--dataset.root={root}",
             "--steps=3", "--batch_size=8", "--num_workers=0", "--save_freq=3", "--log_freq=1",
             "--wandb.enable=false", f"--output_dir={out}"], timeout=600)
    ckpt = out / "checkpoints" / "last" / "pretrained_model"
    cfg = json.loads((ckpt / "config.json").read_text())
    assert cfg["type"] == "pdp" and (ckpt / "model.safetensors").is_file()
