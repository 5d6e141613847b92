"""ReachAround-v0: real MuJoCo physics, 8 expert modes, scene feasibility, classifier, info and API."""

from __future__ import annotations

import importlib
import warnings

import gymnasium as gym
import numpy as np
import pytest

from lerobot_pdp.envs import NOVEL, get_suite_env, load_scene
from lerobot_pdp.envs import reach_around as ra
from lerobot_pdp.envs.recording import run_expert_episode

SUITE = get_suite_env("reach-around")


def run_expert(scene, mode=None, waypoints=None, seed=0):
    """Roll out the mode's expert (or a way-point expert); returns (last info, states, n_steps)."""
    return run_expert_episode(SUITE, scene, mode, waypoints, seed)


def test_suite_entry():
    assert SUITE.gym_id == "lerobot_pdp/ReachAround-v0" and SUITE.lerobot_env_type == "pdp_reach_around"
    assert SUITE.n_modes == 8 and SUITE.trace_dims == (0, 1, 2)
    assert SUITE.task_string(3) == "mode 3: left-wide"
    assert set(SUITE.mode_names) == {f"{s}-{w}" for s in ("left", "right", "over", "under") for w in ("tight", "wide")}


def test_spaces_and_layout():
    env = gym.make(ra.GYM_ID)
    assert env.action_space.shape == (3,) and env.action_space.low.min() == -1 and env.action_space.high.max() == 1
    obs, info = env.reset(seed=0)
    assert obs["agent_pos"].shape == (6,) and obs["agent_pos"].dtype == np.float32
    np.testing.assert_allclose(obs["agent_pos"][:3], ra.START, atol=0.0051)
    np.testing.assert_allclose(obs["environment_state"], [*ra.GOAL, *ra.OBSTACLE_CENTER])
    assert info == {"is_success": False, "collided": False, "min_clearance": pytest.approx(0.245, abs=0.01)}
    assert env.unwrapped.task_description and env.get_wrapper_attr("_max_episode_steps") == SUITE.max_episode_steps
    # environment_state does not change with the scene: a scene-0 policy must run in every scene
    env1 = gym.make(ra.GYM_ID, scene=1)
    np.testing.assert_array_equal(env1.reset(seed=0)[0]["environment_state"], obs["environment_state"])


@pytest.mark.parametrize("mode", range(8))
def test_scene0_every_mode_succeeds_and_is_classified(mode):
    for seed in range(3):
        info, states, n = run_expert(0, mode, seed=seed)
        assert info["is_success"] and not info["collided"], (ra.MODE_NAMES[mode], seed, info)
        assert info["min_clearance"] > 0.01
        assert info["mode"] == mode and info["mode_name"] == ra.MODE_NAMES[mode]
        assert SUITE.classify_mode(states) == mode
        assert 60 <= n <= 150  # short episodes keep CPU training/eval fast


def test_expert_jitter_gives_variety_and_is_seeded():
    _, a, _ = run_expert(0, 3, seed=1)
    _, b, _ = run_expert(0, 3, seed=1)
    _, c, _ = run_expert(0, 3, seed=2)
    np.testing.assert_array_equal(a, b)
    assert len(a) != len(c) or not np.allclose(a, c)


@pytest.mark.parametrize("scene,feasible", [(1, "over-tight"), (2, "left-wide")])
def test_scene_leaves_exactly_one_training_mode(scene, feasible):
    ok = []
    for mode in range(8):
        info, _, _ = run_expert(scene, mode, seed=0)
        if info["is_success"]:
            ok.append(ra.MODE_NAMES[mode])
        else:
            assert info["collided"] and info["min_clearance"] < 0
    assert ok == [feasible]
    for seed in (1, 2):
        assert run_expert(scene, ra.MODE_NAMES.index(feasible), seed=seed)[0]["is_success"]


def test_scene3_blocks_all_modes_and_shipped_route_succeeds():
    for mode in range(8):
        info, _, _ = run_expert(3, mode, seed=0)
        assert not info["is_success"] and info["collided"], ra.MODE_NAMES[mode]
    wps = load_scene(3, "reach_around").waypoints
    for seed in range(3):
        info, states, _ = run_expert(3, waypoints=wps, seed=seed)
        assert info["is_success"] and info["min_clearance"] > 0.01
        assert SUITE.classify_mode(states) == NOVEL and info["mode"] == -1 and info["mode_name"] == NOVEL


def test_collision_terminates_with_real_contact():
    env = gym.make(ra.GYM_ID)
    env.reset(seed=0)
    for _ in range(100):
        obs, reward, terminated, truncated, info = env.step(np.array([0.0, 1.0, 0.0]))
        if terminated:
            break
    assert terminated and not truncated and info["collided"] and not info["is_success"] and reward == 0.0
    # the sphere stopped at the box face (y = -0.04), it did not pass through
    assert -0.04 - 0.015 - 0.005 < obs["agent_pos"][1] < -0.04
    assert info["min_clearance"] < 0 and info["mode_name"] == NOVEL
    with pytest.raises(RuntimeError, match="reset"):
        env.unwrapped.step(np.zeros(3))


def test_truncation_at_episode_length():
    env = gym.make(ra.GYM_ID, episode_length=7)
    env.reset(seed=0)
    for t in range(7):
        _, _, terminated, truncated, info = env.step(np.zeros(3))
        assert not terminated and truncated == (t == 6)
    assert "mode" in info


def test_actions_are_velocity_fractions_and_validated():
    env = gym.make(ra.GYM_ID, start_noise=0.0)
    env.reset(seed=0)
    for _ in range(50):
        obs, *_ = env.step(np.array([5.0, 0.0, 0.0]))  # clipped to 1 -> 0.5 m/s
    assert obs["agent_pos"][0] == pytest.approx(0.5, abs=0.03)  # clamped to the workspace edge x = 0.5
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(2))
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([np.nan, 0, 0]))


def test_reset_is_seeded():
    env = gym.make(ra.GYM_ID)
    a = env.reset(seed=5)[0]["agent_pos"]
    b = env.reset(seed=5)[0]["agent_pos"]
    c = env.reset(seed=6)[0]["agent_pos"]
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_render_rgb_array():
    env = gym.make(ra.GYM_ID, render_mode="rgb_array", scene=2)
    env.reset(seed=0)
    env.step(np.array([0.0, 1.0, 0.0]))
    img = env.render()
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3 and img.shape[0] % 2 == 0
    plain = gym.make(ra.GYM_ID)
    plain.reset(seed=0)
    assert plain.render() is None


def test_classifier_on_synthetic_paths():
    def path(x, z):
        return np.array([[0, -0.3, 0.4], [x, -0.1, z], [x, 0.1, z], [0, 0.3, 0.4]])

    assert ra.classify_positions(path(-0.13, 0.41)) == ra.MODE_NAMES.index("left-tight")
    assert ra.classify_positions(path(0.26, 0.39)) == ra.MODE_NAMES.index("right-wide")
    assert ra.classify_positions(path(0.0, 0.15)) == ra.MODE_NAMES.index("under-wide")
    assert ra.classify_positions(path(0.19, 0.59)) == NOVEL  # diagonal
    assert ra.classify_positions(path(0.6, 0.4)) == NOVEL  # too far out
    assert ra.classify_positions(np.array([[0, -0.3, 0.4], [0, -0.1, 0.4]])) == NOVEL  # never crossed
    with pytest.raises(ValueError, match="positions"):
        ra.classify_positions(np.zeros((5, 2)))


def test_bad_mode_and_waypoints():
    with pytest.raises(ValueError, match=r"mode must be an int in \[0, 7\]"):
        ra.make_expert(8, np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"\[x, y, z\]"):
        ra.expert_from_waypoints([[0.0, 0.1]], np.random.default_rng(0))


def test_reimport_does_not_reregister():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        importlib.reload(ra)
    assert ra.GYM_ID in gym.registry


def test_scene3_wall_cannot_be_bypassed_at_the_workspace_edge():
    env = gym.make(ra.GYM_ID, scene=3)
    env.reset(seed=0)
    for t in range(SUITE.max_episode_steps):
        action = np.array([1.0, 0.0, 1.0]) if t < 60 else np.array([0.0, 1.0, 0.0])
        _, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break
    assert info["collided"] and not info["is_success"]
