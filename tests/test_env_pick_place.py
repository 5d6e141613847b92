"""PickPlace-v0 with real MuJoCo physics: experts, classifier, scenes 0-3, grasp / release, scene errors."""

from __future__ import annotations

import json
import os

import gymnasium as gym
import numpy as np
import pytest

from lerobot_pdp.envs import NOVEL, SceneError, get_suite_env, load_scene
from lerobot_pdp.envs import pick_place as pp

SCENE1_MODE = 0 * 8 + 3  # reach over-tight / carry left-wide
SCENE2_MODE = 7 * 8 + 4  # reach under-wide / carry right-tight


def rollout(env: pp.PickPlaceEnv, expert, seed: int) -> tuple[dict, int, np.ndarray]:
    obs, info = env.reset(seed=seed)
    expert.reset(obs)
    states = [obs["agent_pos"]]
    for t in range(env._max_episode_steps):
        obs, _, term, trunc, info = env.step(expert(obs))
        states.append(obs["agent_pos"])
        if term or trunc:
            return info, t + 1, np.asarray(states)
    raise AssertionError("episode neither terminated nor truncated")


def started(env: pp.PickPlaceEnv, mode: int, seed: int) -> tuple[pp.PickPlaceExpert, dict]:
    """A fresh expert for ``mode`` and the env reset with the same seed: (expert, first observation)."""
    expert = pp.make_expert(mode, np.random.default_rng(seed))
    obs, _ = env.reset(seed=seed)
    expert.reset(obs)
    return expert, obs


def successful_modes(scene: int, seed: int = 0) -> list[int]:
    env = pp.PickPlaceEnv(scene=scene)
    return [m for m in range(64)
            if rollout(env, pp.make_expert(m, np.random.default_rng(seed + m)), seed)[0]["is_success"]]


def test_scene0_every_mode_succeeds_and_is_classified():
    env = pp.PickPlaceEnv(scene=0)
    for m in range(64):
        info, steps, states = rollout(env, pp.make_expert(m, np.random.default_rng(m)), seed=m)
        assert info["is_success"] and not info["collided"], (m, info)
        assert info["mode"] == m, (pp.MODE_NAMES[m], info["mode"])
        assert pp.classify_mode(states) == m
        assert info["min_clearance"] > 0.01
        assert steps < pp.MAX_EPISODE_STEPS


def test_expert_jitter_varies_within_mode():
    env = pp.PickPlaceEnv()
    runs = [rollout(env, pp.make_expert(21, np.random.default_rng(s)), seed=s) for s in range(3)]
    assert all(r[0]["is_success"] and r[0]["mode"] == 21 for r in runs)
    assert len({r[1] for r in runs}) > 1 or not np.allclose(runs[0][2][:50], runs[1][2][:50])


def test_expert_gripper_command_is_always_explicit_and_segments_into_reach_and_carry():
    """The gripper command is always -1 or +1 (0.0 sits on the open/closed threshold and taught learned
    policies to chatter at the start), so gripper segmentation finds exactly reach and carry (the release is
    the final frame, too short to be a phase of its own)."""
    from lerobot_pdp.behavior import gripper_segments

    env = pp.PickPlaceEnv()
    for seed in range(3):
        expert, obs = started(env, 5, seed)
        actions = []
        for _ in range(env._max_episode_steps):
            actions.append(expert(obs))
            obs, _, term, trunc, info = env.step(actions[-1])
            if term or trunc:
                break
        actions = np.asarray(actions)
        assert info["is_success"] and set(np.unique(actions[:, 3]).tolist()) == {-1.0, 1.0}
        assert actions[-1, 3] == -1.0 and (actions[-2, 3] == 1.0)  # released on the final frame
        (r0, r1), (c0, c1) = gripper_segments(actions, 3, 0.0)
        assert r0 == 0 and r1 > 20 and c1 - c0 > 20 and c1 == len(actions)


@pytest.mark.parametrize("scene, mode", [(1, SCENE1_MODE), (2, SCENE2_MODE)])
def test_scenes_1_2_leave_exactly_one_training_mode(scene, mode):
    assert successful_modes(scene) == [mode]


def test_scene3_blocks_all_training_modes_and_shipped_route_succeeds():
    assert successful_modes(3) == []
    waypoints = load_scene(3, "pick_place").waypoints
    env = pp.PickPlaceEnv(scene=3)
    for seed in range(3):
        expert = pp.expert_from_waypoints(json.loads(json.dumps(waypoints)), np.random.default_rng(seed))
        info, _, _ = rollout(env, expert, seed)
        assert info["is_success"], info
        assert info["mode"] == -1 and info["mode_name"] == NOVEL


def test_waypoint_dict_format_matches_flat_format():
    flat = [[0.0, -0.31, 0.53], [0.0, -0.19, 0.53], [0.0, 0.0, 0.4], [-0.25, 0.19, 0.4], [-0.25, 0.31, 0.4],
            [0.0, 0.5, 0.4]]
    nested = {"reach": flat[:2], "carry": flat[3:5]}
    env = pp.PickPlaceEnv()
    for wps in (flat, nested, np.asarray(flat)):
        info, _, _ = rollout(env, pp.expert_from_waypoints(wps, np.random.default_rng(0)), seed=0)
        assert info["is_success"] and info["mode"] == SCENE1_MODE
    with pytest.raises(ValueError, match="grasp point"):
        pp.expert_from_waypoints([[0.0, 0.3, 0.4], [0.0, 0.5, 0.4]], np.random.default_rng(0))
    with pytest.raises(ValueError, match="release point"):
        pp.expert_from_waypoints([[0.0, 0.0, 0.4], [0.0, 0.3, 0.4]], np.random.default_rng(0))
    with pytest.raises(ValueError, match="unknown key"):
        pp.expert_from_waypoints({"reach": [], "lift": []}, np.random.default_rng(0))


def _drive_open(env: pp.PickPlaceEnv, aim: np.ndarray) -> None:
    """Move the end effector to ``aim`` (within 2 mm) with the gripper open."""
    for _ in range(200):
        err = aim - env.ee_pos
        env.step(np.append(np.clip(err * 10, -1, 1), -1.0))
        if np.linalg.norm(err) < 0.002:
            return
    raise AssertionError(f"end effector did not reach {aim}: at {env.ee_pos}")


def test_grasp_moves_object_only_while_closed():
    env = pp.PickPlaceEnv()
    env.reset(seed=0)
    # Closing the gripper far from the object grasps nothing; the object stays put.
    env.step(np.array([0.0, 0.0, 0.0, 1.0]))
    assert env._gripper_closed and not env.grasped
    env.step(np.array([0.0, 0.0, 0.0, -1.0]))
    # Drive straight to the object (the straight line is blocked by obstacle A: remove it for this test).
    env = pp.PickPlaceEnv(scene={"remove": ["obstacle_a", "obstacle_b"]})
    env.reset(seed=0)
    _drive_open(env, pp.OBJECT)
    obs, _, _, _, info = env.step(np.array([0.0, 0.0, 0.0, 1.0]))
    assert env.grasped and info["phase"] == "carry" and obs["agent_pos"][3] == 1.0
    for _ in range(20):
        env.step(np.array([0.5, 0.3, 0.2, 1.0]))
    assert np.linalg.norm(env.object_pos - pp.OBJECT) > 0.1  # moved with the end effector
    assert np.linalg.norm(env.object_pos - env.ee_pos) < 2e-3  # held at the gripper's centre
    env.step(np.array([0.0, 0.0, 0.0, -1.0]))
    assert not env.grasped
    for _ in range(5):
        env.step(np.zeros(4))
    released = env.object_pos.copy()
    for _ in range(20):
        obs, *_ = env.step(np.array([-0.5, 0.0, 0.0, -1.0]))
    assert np.allclose(env.object_pos, released, atol=1e-3)  # stays where released
    assert np.allclose(obs["environment_state"][:3], released, atol=1e-3)
    assert np.linalg.norm(env.ee_pos - released) > 0.08  # the end effector moved away alone


def test_off_centre_grasp_centres_the_object():
    """Closing 2.5 cm beside the object (inside the grasp radius) pulls it to the gripper's centre."""
    env = pp.PickPlaceEnv(scene={"remove": ["obstacle_a", "obstacle_b"]})
    env.reset(seed=0)
    aim = pp.OBJECT + np.array([0.025, 0.0, 0.0])
    _drive_open(env, aim)
    assert 0.02 < np.linalg.norm(env.object_pos - env.ee_pos) < pp.GRASP_RADIUS
    env.step(np.array([0.0, 0.0, 0.0, 1.0]))
    assert env.grasped
    for _ in range(5):
        env.step(np.array([0.0, 0.0, 0.0, 1.0]))
    assert np.linalg.norm(env.object_pos - env.ee_pos) < 3e-3
    # A grasp outside the radius still takes nothing.
    env = pp.PickPlaceEnv(scene={"remove": ["obstacle_a", "obstacle_b"]})
    env.reset(seed=0)
    aim = pp.OBJECT + np.array([0.035, 0.0, 0.0])
    _drive_open(env, aim)
    env.step(np.array([0.0, 0.0, 0.0, 1.0]))
    assert not env.grasped


def test_collision_of_carried_object_terminates():
    env = pp.PickPlaceEnv()
    expert = pp.make_expert(8, np.random.default_rng(0))
    obs, _ = env.reset(seed=0)
    expert.reset(obs)
    while not env.grasped:
        obs, *_ = env.step(expert(obs))
    # Now push the held object straight into obstacle B.
    for _ in range(100):
        err = pp.OBSTACLE_B - env.object_pos
        obs, _, term, _, info = env.step(np.append(np.clip(err * 10, -1, 1), 1.0))
        if term:
            break
    assert term and info["collided"] and not info["is_success"] and info["min_clearance"] < 0
    assert "mode" in info


@pytest.mark.parametrize("point", [pp.OBJECT, pp.TARGET, pp.START])
def test_barrier_covering_start_object_or_target_is_a_scene_error(point):
    scene = {"barriers": [{"shape": "box", "pos": list(point), "half_size": [0.05, 0.05, 0.05]}]}
    with pytest.raises(SceneError, match="covers the"):
        pp.PickPlaceEnv(scene=scene)


def test_scene_errors_and_cylinders():
    with pytest.raises(SceneError, match="unknown obstacle"):
        pp.PickPlaceEnv(scene={"remove": ["obstacle_c"]})
    with pytest.raises(SceneError, match="already used"):
        pp.PickPlaceEnv(scene={"barriers": [{"shape": "box", "name": "obstacle_a", "pos": [0.4, 0, 0.4],
                                             "half_size": [0.01, 0.01, 0.01]}]})
    env = pp.PickPlaceEnv(scene={"barriers": [{"shape": "cylinder", "pos": [0.4, 0.0], "radius": 0.03,
                                               "half_height": 0.1}]})
    assert env.model.geom(f"barrier_{0}").pos[2] == pytest.approx(pp.WORKING_Z)


def test_registration_and_lerobot_observation_layout():
    suite = get_suite_env("pick-place")
    assert suite.gym_id == pp.GYM_ID and suite.n_modes == 64 and suite.segment_on_gripper == 3
    assert suite.mode_names[SCENE1_MODE] == "reach over-tight / carry left-wide"
    assert suite.classify_mode(np.zeros((5, 4))) == NOVEL
    env = gym.make(pp.GYM_ID, scene=1)
    obs, info = env.reset(seed=0)
    assert obs["agent_pos"].shape == (4,) and obs["environment_state"].shape == (12,)
    assert obs["agent_pos"].dtype == np.float32
    assert env.unwrapped.task_description and env.unwrapped._max_episode_steps == pp.MAX_EPISODE_STEPS
    assert set(info) >= {"is_success", "collided", "min_clearance", "phase"}
    env.close()


def test_expert_brakes_onto_the_object_without_creeping():
    """The expert closes a few steps after coming within 3 cm, not after a long slow creep: a creep at
    0.5-2 mm/step (18 steps with the old gentle brake) taught learned policies to stall short and close."""
    env = pp.PickPlaceEnv()
    for seed in range(3):
        expert, obs = started(env, 21, seed)
        gaps = []
        for _ in range(env._max_episode_steps):
            action = expert(obs)
            gaps.append(float(np.linalg.norm(env.object_pos - env.ee_pos)))
            if action[3] > 0:
                break
            obs, *_ = env.step(action)
        else:
            raise AssertionError(f"seed {seed}: the expert never closed the gripper")
        within_3cm = next(i for i, g in enumerate(gaps) if g < 0.03)
        assert len(gaps) - 1 - within_3cm <= 8, (seed, len(gaps) - 1 - within_3cm)
        assert gaps[-1] < 0.006  # and still closes on the object


def test_rendering_without_an_opengl_context_says_how_to_get_one():
    """On a machine without a display and without MUJOCO_GL (lerobot-eval records videos through render()), the
    error names the environment variable to set, not MuJoCo's "OpenGL platform library" message alone."""
    import os
    import subprocess
    import sys

    code = ("import gymnasium as gym\nfrom lerobot_pdp.envs import pick_place as pp\n"
            "env = gym.make(pp.GYM_ID, scene=0, render_mode='rgb_array')\nenv.reset(seed=0)\n"
            "try:\n    env.render()\nexcept RuntimeError as e:\n    print('refused:', e)\nelse:\n    print('rendered')\n")
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "DISPLAY", "WAYLAND_DISPLAY", "PYOPENGL_PLATFORM")}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout.strip().splitlines()[-1]
    # a machine with a GL context (a desktop) renders; a headless one gets the advice
    assert out == "rendered" or ("set MUJOCO_GL=egl (or osmesa)" in out and out.startswith("refused: pick-place")), out


def test_a_machine_without_a_display_renders_with_egl_unless_told_otherwise():
    """MuJoCo's default backend (GLFW) needs a display: without one, importing the envs chooses EGL where it is
    installed (pick-place's videos in lerobot-eval, its cameras), before MuJoCo is imported; a MUJOCO_GL the user
    set is kept."""
    import ctypes.util
    import subprocess
    import sys

    code = ("import os, lerobot_pdp.envs, gymnasium as gym; print(os.environ.get('MUJOCO_GL')); "
            "e = gym.make('lerobot_pdp/PickPlace-v0', render_mode='rgb_array'); e.reset(seed=0); "
            "print(e.render().shape); e.close()")
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "DISPLAY", "WAYLAND_DISPLAY")}
    if not ctypes.util.find_library("EGL"):
        pytest.skip("no EGL library on this machine: MuJoCo's default is left alone")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0 and out.stdout.split() == ["egl", "(240,", "320,", "3)"], out.stderr[-2000:]
    out = subprocess.run([sys.executable, "-c", "import os, lerobot_pdp.envs; print(os.environ['MUJOCO_GL'])"],
                         capture_output=True, text=True, timeout=120, env={**env, "MUJOCO_GL": "osmesa"})
    assert out.stdout.strip() == "osmesa", out.stderr[-2000:]
