"""KitchenMicrowave-v0 on real gymnasium-robotics physics: routes, scenes, classifier and input errors."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from lerobot_pdp.envs import NOVEL, SceneError, get_suite_env, load_scene
from lerobot_pdp.envs import kitchen_microwave as km
from lerobot_pdp.envs.scene import scene_from_dict


def rollout(env: km.KitchenMicrowaveEnv, expert, seed: int = 0) -> tuple[dict, int]:
    obs, _ = env.reset(seed=seed)
    expert.reset(obs)
    for t in range(env._max_episode_steps):
        obs, _, terminated, truncated, info = env.step(expert(obs))
        if terminated or truncated:
            return info, t + 1
    raise AssertionError("episode did not end")


@pytest.fixture(scope="module")
def envs():
    made = {k: km.KitchenMicrowaveEnv(scene=k) for k in range(4)}
    yield made
    for e in made.values():
        e.close()


def test_registration_and_spaces():
    spec = get_suite_env("kitchen-microwave")
    assert spec.gym_id == km.GYM_ID and spec.trace_dims == (0, 1, 2) and spec.n_modes == 5
    env = gym.make(km.GYM_ID, scene=0)
    obs, info = env.reset(seed=0)
    assert obs["agent_pos"].shape == (21,) and obs["environment_state"].shape == (5,)
    assert env.observation_space.contains(obs)
    assert env.unwrapped._max_episode_steps == km.MAX_EPISODE_STEPS
    assert env.unwrapped.task_description
    # The module's frame constants are the simulator's values at the deterministic reset.
    np.testing.assert_allclose(obs["agent_pos"][:3], km.EE_START, atol=2e-3)
    np.testing.assert_allclose(obs["environment_state"][1:4], km.HANDLE, atol=1e-3)
    assert info["collided"] is False and info["min_clearance"] == np.inf
    env.close()


def test_reset_pose_clear_in_every_scene(envs):
    for k, env in envs.items():
        _, info = env.reset(seed=0)
        assert not env._barrier_contact() and env.barrier_contacts() == [], k
        assert info["clearance"] > 0.02, (k, info["clearance"])


def test_every_training_route_succeeds_in_scene0_and_is_classified(envs):
    for mode, name in enumerate(km.MODE_NAMES):
        info, steps = rollout(envs[0], km.make_expert(name, np.random.default_rng(mode)), seed=mode)
        assert info["is_success"] and not info["collided"], (name, info)
        assert info["mode"] == mode, (name, info["mode"])
        assert steps < km.MAX_EPISODE_STEPS


@pytest.mark.parametrize("scene, feasible", [(1, "high"), (2, "right")])
def test_scenes_1_2_leave_exactly_one_route(envs, scene, feasible):
    ok = {name: rollout(envs[scene], km.make_expert(i, np.random.default_rng(0)))[0]
          for i, name in enumerate(km.MODE_NAMES)}
    assert [n for n, info in ok.items() if info["is_success"]] == [feasible]
    assert all(info["collided"] for n, info in ok.items() if n != feasible)
    assert ok[feasible]["min_clearance"] > 0.01


def test_scene3_blocks_all_routes_and_shipped_waypoints_succeed(envs):
    for i in range(len(km.MODE_NAMES)):
        info, _ = rollout(envs[3], km.make_expert(i, np.random.default_rng(0)))
        assert not info["is_success"] and info["collided"], km.MODE_NAMES[i]
        # the collision step's contacts are named: which barrier, which robot body
        hits = envs[3].barrier_contacts()
        barrier_names = {b.name or f"barriers[{j}]" for j, b in enumerate(envs[3].scene.barriers)}
        assert hits and all(h.split(" / ")[0] in barrier_names and h.split(" / ")[1].startswith("panda0_")
                            for h in hits), (km.MODE_NAMES[i], hits)
    info, _ = rollout(envs[3], km.expert_from_waypoints(None, np.random.default_rng(0), scene=3))
    assert info["is_success"] and info["mode"] == -1 and info["mode_name"] == NOVEL


def test_barrier_on_start_or_kettle_is_rejected():
    sc = load_scene(0, "kitchen_microwave")
    on_start = scene_from_dict({"barriers": [{"shape": "box", "pos": list(km.EE_START), "half_size": [0.05] * 3}]})
    with pytest.raises(SceneError, match="start end effector"):
        on_start.check_clear({"start end effector": km.EE_START}, margin=0.05)
    with pytest.raises(SceneError, match="start end effector"):
        km.KitchenMicrowaveEnv(scene=on_start)
    on_kettle = {"barriers": [{"shape": "cylinder", "pos": [-0.27, 0.35, 1.75], "radius": 0.05, "half_height": 0.05}]}
    with pytest.raises(SceneError, match="kettle"):
        km.KitchenMicrowaveEnv(scene=on_kettle)
    with pytest.raises(SceneError, match="remove"):
        km.KitchenMicrowaveEnv(scene={"barriers": [], "remove": ["kettle"]})
    assert sc.barriers == ()


def test_bad_inputs_raise_clear_errors(envs):
    with pytest.raises(ValueError, match="unknown kitchen-microwave mode"):
        km.make_expert("left", np.random.default_rng(0))
    with pytest.raises(ValueError, match="x, y, z"):
        km.expert_from_waypoints([[0.1, 0.2]], np.random.default_rng(0))
    with pytest.raises(ValueError, match="reaches"):
        km.expert_from_waypoints([[-2.0, 0.0, 1.8]], np.random.default_rng(0))
    with pytest.raises(ValueError, match="ships no 'waypoints'"):
        km.expert_from_waypoints(None, np.random.default_rng(0), scene=1)
    with pytest.raises(ValueError, match="9 joint-velocity"):
        envs[0].reset(seed=0)
        envs[0].step(np.zeros(7))
    with pytest.raises(ValueError, match="agent_pos rows"):
        km.classify_mode(np.zeros((5, 2)))


def test_classifier_labels_a_standing_still_trace_novel():
    assert km.classify_mode(np.tile(km.EE_START, (20, 1))) == NOVEL
