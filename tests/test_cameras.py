"""Camera observations of the suite envs: images in the env's observation, camera datasets stored as video,
and the LeRobot env configs' image features (``--env.camera``)."""

from __future__ import annotations

import json
import os

import gymnasium as gym
import numpy as np
import pytest
import torch
from lerobot.configs import FeatureType
from lerobot.envs.factory import make_env, make_env_config
from lerobot.envs.utils import env_to_policy_features, preprocess_observation

import lerobot_pdp.envs as envs
from lerobot_pdp.cli import main as cli_main
from lerobot_pdp.envs.camera import CameraSpec, RayCaster, Solid, parse_image_size
from lerobot_pdp.envs.recording import _dataset_features, make_dataset, read_dataset_meta

SIZE = 32
CAMERAS = {"reach-around": ("top", "front", "oblique"), "avoiding": ("top",), "pick-place": ("top", "side", "oblique")}


def _make(env: str, scene: int = 0, **kwargs) -> gym.Env:
    return gym.make(envs.get_suite_env(env).gym_id, scene=scene, disable_env_checker=True, **kwargs)


@pytest.mark.parametrize("env_name", sorted(CAMERAS))
def test_obs_carries_declared_images(env_name):
    cams = CAMERAS[env_name]
    env = _make(env_name, camera=",".join(cams), image_size=SIZE)
    obs, _ = env.reset(seed=0)
    obs, *_ = env.step(env.action_space.sample() * 0)
    space = env.observation_space["pixels"]
    assert set(obs["pixels"]) == set(space.spaces) == set(cams)
    for cam in cams:
        img = obs["pixels"][cam]
        assert img.shape == (SIZE, SIZE, 3) and img.dtype == np.uint8
        assert space[cam].dtype == np.uint8 and space[cam].contains(img)
        assert img.std() > 0  # not a blank frame
    env.close()
    plain = _make(env_name)
    assert "pixels" not in plain.observation_space.spaces and "pixels" not in plain.reset(seed=0)[0]
    plain.close()


def test_non_square_size_and_bit_identical_frames():
    a = _make("reach-around", camera="top", image_size="24x40")
    b = _make("reach-around", camera="top", image_size=(24, 40))
    ia, ib = a.reset(seed=3)[0]["pixels"]["top"], b.reset(seed=3)[0]["pixels"]["top"]
    assert ia.shape == (24, 40, 3) and np.array_equal(ia, ib)


def test_the_camera_sees_the_agent_move_and_not_its_path():
    env = _make("reach-around", camera="top", image_size=SIZE)
    first = env.reset(seed=0)[0]["pixels"]["top"]
    for _ in range(15):
        obs, *_ = env.step(np.array([1.0, 0.0, 0.0], dtype=np.float32))
    moved = obs["pixels"]["top"]
    assert not np.array_equal(first, moved)
    for _ in range(15):
        obs, *_ = env.step(np.array([-1.0, 0.0, 0.0], dtype=np.float32))
    for _ in range(10):  # settle back on the start
        obs, *_ = env.step(np.zeros(3, dtype=np.float32))
    back = obs["pixels"]["top"].astype(int)
    # back where it started: the image matches the first again (a camera shows no trail)
    assert np.abs(back - first.astype(int)).max() <= 40 and np.abs(back - moved.astype(int)).max() > 40


def test_supersampling_keeps_a_subpixel_agent_visible():
    spec = CameraSpec("top", eye=(0, 0, 2), target=(0, 0, 0), up=(0, 1, 0), fovy=60)
    floor = [Solid("floor", (0, 0, 0), (), (0.8, 0.8, 0.8))]
    # at z = 0.5 a pixel is 2 * 1.5 * tan(30 deg) / 32 = 0.054 m; a sphere 0.8 px across centred on a pixel
    # corner falls between the single rays of four pixels but not between 2x2 sub-rays
    tiny = [Solid("sphere", (0.0, 0.0, 0.5), (0.022,), (1.0, 0.0, 0.0))]
    one = RayCaster(spec, (SIZE, SIZE), floor, supersample=1)
    assert np.array_equal(one.render(tiny), one.render([]))
    two = RayCaster(spec, (SIZE, SIZE), floor)
    seen = np.any(two.render(tiny) != two.render([]), axis=-1)
    assert seen[15:17, 15:17].all() and seen.sum() == 4


@pytest.mark.parametrize(("env_name", "cam"), [("reach-around", "top"), ("reach-around", "front"),
                                               ("pick-place", "top"), ("avoiding", "top")])
def test_a_shifted_scene_is_visible(env_name, cam):
    images = []
    for scene in (0, 3):
        env = _make(env_name, scene=scene, camera=cam, image_size=SIZE)
        images.append(env.reset(seed=0)[0]["pixels"][cam].astype(int))
        env.close()
    diff = np.abs(images[0] - images[1]).sum(axis=-1) > 30
    assert diff.sum() >= 10
    if (env_name, cam) in (("reach-around", "top"), ("pick-place", "top")):
        # scene 3's wall runs across the whole width (along x) at one y: a band of rows, all columns
        rows = np.nonzero(diff.any(axis=1))[0]
        assert diff.any(axis=0).sum() > 0.8 * SIZE and rows.max() - rows.min() <= SIZE // 4
        if env_name == "reach-around":  # the wall stands at y = 0, under the camera: the middle rows
            assert abs(rows.mean() - (SIZE - 1) / 2) <= 2
        else:  # at y = +0.25: the upper half (+y is up in the image)
            assert rows.max() < SIZE / 2


def test_preprocess_observation_maps_pixels_to_observation_images():
    cfg = make_env_config("pdp_reach_around", camera="top", image_size=SIZE, scene=3)
    vec = make_env(cfg, n_envs=2)["pdp_reach_around"][0]
    obs, _ = vec.reset(seed=[0, 1])
    batch = preprocess_observation(obs)
    img = batch["observation.images.top"]
    assert img.shape == (2, 3, SIZE, SIZE) and img.dtype == torch.float32
    assert 0.0 <= float(img.min()) and float(img.max()) <= 1.0
    assert batch["observation.state"].shape == (2, 6)
    vec.close()


@pytest.mark.parametrize(("env_type", "cam"), [("pdp_reach_around", "top"), ("pdp_pick_place", "oblique"),
                                               ("pdp_avoiding", "top")])
def test_env_config_declares_the_camera(env_type, cam):
    cfg = make_env_config(env_type, camera=cam, image_size=SIZE)
    feat = cfg.features[f"pixels/{cam}"]
    assert feat.type is FeatureType.VISUAL and feat.shape == (SIZE, SIZE, 3)
    assert cfg.features_map[f"pixels/{cam}"] == f"observation.images.{cam}"
    assert cfg.gym_kwargs["camera"] == cam and parse_image_size(cfg.gym_kwargs["image_size"]) == (SIZE, SIZE)
    policy_feats = env_to_policy_features(cfg)
    assert policy_feats[f"observation.images.{cam}"].shape == (3, SIZE, SIZE)
    plain = make_env_config(env_type)
    assert not any(k.startswith("pixels") for k in plain.features) and "camera" not in plain.gym_kwargs


def test_bad_camera_names_the_valid_ones(tmp_path):
    with pytest.raises(ValueError, match="unknown camera 'side'; valid cameras: top, front, oblique"):
        _make("reach-around", camera="side")
    with pytest.raises(ValueError, match="valid cameras: top, side, oblique"):
        make_env_config("pdp_pick_place", camera="front")
    with pytest.raises(ValueError, match="valid cameras: top"):
        make_dataset("avoiding", tmp_path / "d", camera="front", episodes_per_mode=1, progress=False)
    assert not (tmp_path / "d").exists()
    with pytest.raises(ValueError, match="HxW"):
        _make("reach-around", camera="top", image_size="big")
    assert cli_main(["make-dataset", "--env", "reach-around", "--camera", "nope", "--out", str(tmp_path / "e"),
                     "--no-progress"]) == 2
    assert not (tmp_path / "e").exists()


def test_state_only_features_unchanged():
    env = _make("reach-around")
    assert set(_dataset_features(env)) == {"observation.state", "observation.environment_state", "action"}
    env.close()
    env = _make("reach-around", camera="top", image_size=SIZE)
    feats = _dataset_features(env)
    assert feats["observation.images.top"] == {"dtype": "video", "shape": (SIZE, SIZE, 3),
                                               "names": ["height", "width", "channels"]}
    env.close()


def test_make_dataset_camera_writes_video_lerobot_reads(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    out = tmp_path / "cam"
    policy = os.sched_getscheduler(0)
    assert cli_main(["make-dataset", "--env", "reach-around", "--modes", "0", "--episodes-per-mode", "1",
                     "--camera", "top", "--image-size", str(SIZE), "--out", str(out), "--no-progress"]) == 0
    # LeRobot's AV1 encoder raises its thread to real-time priority where it may (root): undone
    assert os.sched_getscheduler(0) == policy
    info = json.loads((out / "meta" / "info.json").read_text())
    feat = info["features"]["observation.images.top"]
    assert feat["dtype"] == "video" and tuple(feat["shape"]) == (SIZE, SIZE, 3)
    assert list(out.glob("videos/observation.images.top/*/*.mp4"))
    assert read_dataset_meta(out)["cameras"] == ["top"] and read_dataset_meta(out)["image_size"] == [SIZE, SIZE]
    assert not list(tmp_path.glob(".cam.partial-*"))  # written atomically
    assert not (out / "images").exists()  # the frames LeRobot encoded into videos leave no empty folders

    ds = LeRobotDataset("local/cam", root=out)
    first, later = ds[0], ds[len(ds) - 1]
    img = first["observation.images.top"]
    assert img.shape == (3, SIZE, SIZE) and img.dtype == torch.float32
    assert 0.0 <= float(img.min()) and float(img.max()) <= 1.0
    assert first["observation.state"].shape == (6,)
    # the decoded frame is the env's image up to compression, and the agent moved by the end
    env = _make("reach-around", camera="top", image_size=SIZE)
    env.reset(seed=0)
    env.unwrapped.data.qpos[:3] = first["observation.state"][:3].numpy()
    import mujoco

    mujoco.mj_forward(env.unwrapped.model, env.unwrapped.data)
    expected = torch.from_numpy(env.unwrapped.camera_images()["top"]).permute(2, 0, 1).float() / 255
    assert float((img - expected).abs().mean()) < 0.05
    assert float((later["observation.images.top"] - img).abs().max()) > 0.1
