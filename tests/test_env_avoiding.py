"""Avoiding-v0: D3IL-style 24-route obstacle field, scene feasibility, classifier and env API."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from lerobot_pdp.envs import NOVEL, get_suite_env, load_scene
from lerobot_pdp.envs import avoiding as av
from lerobot_pdp.envs.recording import run_expert_episode

SUITE = get_suite_env("avoiding")


def run_expert(scene, mode=None, waypoints=None, seed=0):
    """Roll out the mode's expert (or a way-point expert); returns (last info, states, n_steps)."""
    return run_expert_episode(SUITE, scene, mode, waypoints, seed)


def test_suite_entry_and_layout():
    assert SUITE.n_modes == 24 and SUITE.trace_dims == (0, 1) and SUITE.lerobot_env_type == "pdp_avoiding"
    assert SUITE.mode_names[0] == "L-L-1" and SUITE.mode_names[23] == "R-R-4"
    env = gym.make(av.GYM_ID)
    obs, info = env.reset(seed=0)
    assert env.action_space.shape == (2,)
    assert obs["agent_pos"].shape == (4,) and obs["environment_state"].shape == (13,)
    assert obs["environment_state"][0] == pytest.approx(av.FINISH_Y)
    np.testing.assert_allclose(obs["agent_pos"][:2], av.START, atol=0.0051)
    assert len(env.unwrapped.environment_state_names()) == 13


def test_mode_id_is_g1_12_g2_4_g3():
    for g1 in range(2):
        for g2 in range(3):
            for g3 in range(4):
                m = g1 * 12 + g2 * 4 + g3
                assert av.decode_mode(m) == (g1, g2, g3)
                assert av.classify_positions(av.mode_waypoints(m)) == m


def test_gap_centres_between_posts_and_walls():
    assert av.gap_centers(0) == pytest.approx((0.305, 0.695))
    assert av.gap_centers(1) == pytest.approx((0.27, 0.5, 0.73))
    assert av.gap_centers(2) == pytest.approx((0.2325, 0.425, 0.575, 0.7675))


@pytest.mark.parametrize("mode", range(24))
def test_scene0_every_mode_succeeds_and_is_classified(mode):
    for seed in range(2):
        info, states, n = run_expert(0, mode, seed=seed)
        assert info["is_success"] and not info["collided"], (av.MODE_NAMES[mode], seed, info)
        assert info["min_clearance"] > 0.01 and info["mode"] == mode
        assert SUITE.classify_mode(states) == mode
        assert n < SUITE.max_episode_steps


@pytest.mark.parametrize("scene,feasible", [(1, 6), (2, 23)])
def test_scene_leaves_exactly_one_training_mode(scene, feasible):
    ok = [m for m in range(24) if run_expert(scene, m, seed=0)[0]["is_success"]]
    assert ok == [feasible]
    assert run_expert(scene, feasible, seed=1)[0]["is_success"]


def test_scene1_and_scene2_keep_different_modes():
    assert {6, 23} == {SUITE.mode_names.index("L-M-3"), SUITE.mode_names.index("R-R-4")}


def test_scene3_blocks_all_modes_and_shipped_route_succeeds():
    for m in range(24):
        info, _, _ = run_expert(3, m, seed=0)
        assert not info["is_success"], av.MODE_NAMES[m]
    sc = load_scene(3, "avoiding")
    assert sc.remove == ("post_r3_1",)
    for seed in range(3):
        info, states, _ = run_expert(3, waypoints=sc.waypoints, seed=seed)
        assert info["is_success"] and not info["collided"]
        assert SUITE.classify_mode(states) == NOVEL


def test_collision_with_post_terminates():
    env = gym.make(av.GYM_ID, start_noise=0.0)
    env.reset(seed=0)
    # head for the row-1 post at (0.5, -0.10)
    for _ in range(100):
        obs, _, terminated, _, info = env.step(np.array([-0.12, 1.0]))
        if terminated:
            break
    assert info["collided"] and not info["is_success"] and info["min_clearance"] < 0
    assert np.hypot(obs["agent_pos"][0] - 0.5, obs["agent_pos"][1] + 0.10) < 0.03 + 0.01 + 0.003


def test_classifier_novel_cases():
    assert av.classify_positions(np.array([[0.5, -0.3], [0.3, 0.0]])) == NOVEL  # stops before row 2
    through_post = np.array([[0.5, -0.3], [0.3, -0.1], [0.3, 0.0], [0.5, 0.1], [0.5, 0.4]])
    assert av.classify_positions(through_post) == NOVEL  # crosses row 3 where a post stands
    with pytest.raises(ValueError, match=r"mode must be an int in \[0, 23\]"):
        av.mode_waypoints(24)
    with pytest.raises(ValueError, match=r"\[x, y\]"):
        av.expert_from_waypoints([[0.5, 0.1, 0.0]], np.random.default_rng(0))


def test_no_route_around_the_outside_of_a_wall():
    """The desired position is clamped between the walls, so hugging the workspace edge means touching one."""
    env = gym.make(av.GYM_ID, scene=3)
    env.reset(seed=0)
    info = {}
    for t in range(SUITE.max_episode_steps):
        _, _, terminated, truncated, info = env.step(np.array([-1.0, 0.0]) if t < 40 else np.array([0.0, 1.0]))
        if terminated or truncated:
            break
    assert info["collided"] and not info["is_success"]
