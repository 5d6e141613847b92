"""Scenes as data: shipped files load, bad files fail with errors that name the key/value, envs check them."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import lerobot_pdp.envs  # noqa: F401  (registers the gym ids)
from lerobot_pdp.envs.point_mass import PrimitiveSet
from lerobot_pdp.envs.scene import Barrier, SceneError, load_scene, shipped_scene_path

ENVS = {"reach_around": "lerobot_pdp/ReachAround-v0", "avoiding": "lerobot_pdp/Avoiding-v0"}


def _write(tmp_path: Path, data, name: str = "scene.json") -> Path:
    p = tmp_path / name
    p.write_text(data if isinstance(data, str) else json.dumps(data))
    return p


@pytest.mark.parametrize("key", sorted(ENVS))
@pytest.mark.parametrize("index", [0, 1, 2, 3])
def test_shipped_scenes_load_and_build(key: str, index: int):
    assert shipped_scene_path(key, index).is_file()
    sc = load_scene(index, key)
    assert sc.name.startswith(f"scene {index}")
    assert (sc.waypoints is not None) == (index == 3)  # scene 3 ships the route of its new demonstration
    env = gym.make(ENVS[key], scene=index)
    env.reset(seed=0)
    env.close()


@pytest.mark.parametrize("scene", [1, "1", "2"])
def test_scene_index_as_int_or_string(scene):
    assert load_scene(scene, "reach_around") == load_scene(int(scene), "reach_around")


@pytest.mark.parametrize("scene", [3, "val3"])
def test_scene_by_the_envs_cli_name(scene):
    """``load_scene`` takes the env as the CLI names it (``reach-around``) as well as by its scene key."""
    assert load_scene(scene, "reach-around") == load_scene(scene, "reach_around")


def test_scene_from_mapping_and_object():
    d = {"name": "one slab", "barriers": [{"shape": "box", "pos": [0.3, 0, 0.4], "half_size": [0.05, 0.03, 0.4]}]}
    env = gym.make(ENVS["reach_around"], scene=d)
    assert len(env.unwrapped.barriers) == 1
    env2 = gym.make(ENVS["reach_around"], scene=load_scene(d, "reach_around"))
    assert env2.unwrapped.barriers == env.unwrapped.barriers


def test_unknown_scene_index():
    with pytest.raises(SceneError, match=r"ships no scene 7 .*; it ships scenes \[0, 1, 2, 3\] and \['val1', "):
        gym.make(ENVS["reach_around"], scene=7)


def test_unknown_top_level_key(tmp_path):
    p = _write(tmp_path, {"name": "x", "barriers": [], "obstacles": []})
    with pytest.raises(SceneError, match=r"unknown key\(s\) \['obstacles'\]") as e:
        gym.make(ENVS["reach_around"], scene=str(p))
    assert str(p) in str(e.value)


def test_unknown_barrier_key(tmp_path):
    p = _write(tmp_path, {"barriers": [{"shape": "box", "pos": [0.3, 0, 0.4], "half_size": [0.1, 0.1, 0.1],
                                        "size": 1}]})
    with pytest.raises(SceneError, match=r"barriers\[0\].*unknown key\(s\) \['size'\]"):
        gym.make(ENVS["reach_around"], scene=p)


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity"])
def test_non_finite_json_number(tmp_path, literal):
    text = '{"barriers": [{"shape": "box", "pos": [0.3, 0, LIT], "half_size": [0.1, 0.1, 0.1]}]}'
    p = _write(tmp_path, text.replace("LIT", literal))
    with pytest.raises(SceneError, match="non-finite"):
        gym.make(ENVS["reach_around"], scene=p)


def test_non_finite_yaml_number(tmp_path):
    p = _write(tmp_path, "barriers:\n  - {shape: cylinder, pos: [0.3, 0.1], radius: .inf, half_height: 0.05}\n",
               "scene.yaml")
    with pytest.raises(SceneError, match=r"radius: expected a finite number"):
        gym.make(ENVS["avoiding"], scene=p)


def test_wrong_types_named(tmp_path):
    p = _write(tmp_path, {"barriers": [{"shape": "box", "pos": [0.3, 0], "half_size": [0.1, 0.1, 0.1]}]})
    with pytest.raises(SceneError, match=r"barriers\[0\]\.pos: expected a list of 3 numbers"):
        gym.make(ENVS["reach_around"], scene=p)
    p = _write(tmp_path, {"barriers": [{"shape": "sphere", "pos": [0.3, 0, 0.4]}]})
    with pytest.raises(SceneError, match=r"shape: expected 'box' or 'cylinder', got 'sphere'"):
        gym.make(ENVS["reach_around"], scene=p)


@pytest.mark.parametrize("where,point", [("start", (0.0, -0.30, 0.40)), ("goal", (0.0, 0.30, 0.40))])
def test_barrier_covering_start_or_goal_reach_around(tmp_path, where, point):
    p = _write(tmp_path, {"barriers": [{"shape": "box", "pos": list(point), "half_size": [0.05, 0.05, 0.05]}]})
    with pytest.raises(SceneError, match=f"covers the {where}"):
        gym.make(ENVS["reach_around"], scene=p)


def test_barrier_covering_start_avoiding(tmp_path):
    p = _write(tmp_path, {"barriers": [{"shape": "cylinder", "pos": [0.53, -0.27], "radius": 0.02,
                                        "half_height": 0.05}]})
    with pytest.raises(SceneError, match="covers the start"):
        gym.make(ENVS["avoiding"], scene=p)


def test_remove_unknown_obstacle(tmp_path):
    p = _write(tmp_path, {"remove": ["post_r9_9"]})
    with pytest.raises(SceneError, match=r"unknown obstacle\(s\) \['post_r9_9'\]"):
        gym.make(ENVS["avoiding"], scene=p)


def test_remove_obstacle_takes_it_out_of_physics():
    env = gym.make(ENVS["avoiding"], scene={"remove": ["post_r1_0"]}).unwrapped
    names = [env.model.geom(i).name for i in range(env.model.ngeom)]
    assert "obstacle_post_r1_0" not in names and "obstacle_post_r2_0" in names


def test_barrier_off_the_plane_of_a_2d_env(tmp_path):
    p = _write(tmp_path, {"barriers": [{"shape": "box", "pos": [0.3, 0.0, 0.5], "half_size": [0.1, 0.01, 0.05]}]})
    with pytest.raises(SceneError, match="misses the motion plane"):
        gym.make(ENVS["avoiding"], scene=p)


def test_primitive_set_matches_barrier_signed_distance():
    prims = [
        Barrier("box", (0.1, 0.0, 0.4), half_size=(0.08, 0.04, 0.08)),
        Barrier("cylinder", (0.5, -0.1), radius=0.03, half_height=0.05),
        Barrier("cylinder", (-0.2, 0.2, 0.3), radius=0.05, half_height=0.1),
    ]
    ps = PrimitiveSet(prims, default_z=0.0)
    rng = np.random.default_rng(0)
    for p in rng.uniform(-0.6, 0.6, size=(200, 3)):
        ref = min(b.signed_distance(p) for b in prims)
        assert ps.signed_distance(p) == pytest.approx(ref, abs=1e-12)


def test_scene_roundtrip_dict():
    sc = load_scene(3, "avoiding")
    again = load_scene(sc.to_dict(), "avoiding")
    assert (again.barriers, again.remove, again.waypoints) == (sc.barriers, sc.remove, sc.waypoints)
