"""LeRobot env configs (``--env.type=pdp_*``): registration, features from env spaces, and real
``lerobot-train`` / ``lerobot-eval`` runs on a generated dataset (slow)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from lerobot.configs import FeatureType
from lerobot.envs.configs import EnvConfig
from lerobot.envs.factory import make_env, make_env_config

import lerobot_pdp.envs as envs
from lerobot_pdp.envs.configs import ENV_CONFIGS, PDPSuiteEnvConfig
from lerobot_pdp.envs.recording import make_dataset

TYPES = ("pdp_reach_around", "pdp_avoiding", "pdp_pick_place", "pdp_kitchen_microwave")
BIN = Path(sys.executable).parent


def test_all_four_types_registered():
    known = EnvConfig.get_known_choices()
    for t in TYPES:
        assert t in known and t in ENV_CONFIGS
        assert issubclass(EnvConfig.get_choice_class(t), PDPSuiteEnvConfig)


@pytest.mark.parametrize("env_type", TYPES)
def test_features_come_from_env_spaces(env_type):
    suite = next((s for s in envs.SUITE.values() if s.lerobot_env_type == env_type), None)
    assert suite is not None, f"{env_type}: no suite env registers it"
    cfg = make_env_config(env_type)
    import gymnasium as gym

    env = gym.make(suite.gym_id)
    assert cfg.features["agent_pos"].shape == env.observation_space["agent_pos"].shape
    assert cfg.features["agent_pos"].type is FeatureType.STATE
    assert cfg.features["environment_state"].shape == env.observation_space["environment_state"].shape
    assert cfg.features["action"].shape == env.action_space.shape
    assert cfg.features_map == {"agent_pos": "observation.state", "environment_state": "observation.environment_state",
                                "action": "action"}
    assert cfg.gym_id == suite.gym_id and cfg.fps == suite.fps
    env.close()


def test_scene_as_int_string_or_path_and_vector_env(tmp_path):
    assert make_env_config("pdp_reach_around", scene=2).scene == "2"
    scene_file = tmp_path / "s.json"
    scene_file.write_text(json.dumps({"barriers": [{"shape": "box", "pos": [0.3, 0, 0.4],
                                                    "half_size": [0.05, 0.03, 0.4]}]}))
    cfg = make_env_config("pdp_reach_around", scene=scene_file, episode_length=50)
    assert cfg.scene == str(scene_file)
    assert cfg.gym_kwargs == {"scene": str(scene_file), "render_mode": "rgb_array", "max_episode_steps": 50,
                              "episode_length": 50}
    vec = make_env(cfg, n_envs=2)["pdp_reach_around"][0]
    obs, _ = vec.reset(seed=[0, 1])
    assert obs["agent_pos"].shape == (2, 6) and obs["environment_state"].shape == (2, 6)
    assert vec.call("_max_episode_steps") == (50, 50)
    assert all(vec.call("task_description"))
    assert vec.envs[0].unwrapped.barriers[0].pos == (0.3, 0.0, 0.4)
    _, _, _, _, info = vec.step(np.zeros((2, 3), dtype=np.float32))
    assert info["is_success"].shape == (2,)
    vec.close()


def test_config_errors():
    with pytest.raises(ValueError, match="fixed 50 Hz"):
        make_env_config("pdp_reach_around", fps=30)
    with pytest.raises(envs.SceneError, match="ships no scene 9"):
        make_env_config("pdp_avoiding", scene="9")


# ---- slow: LeRobot's own train / eval scripts on a generated dataset -------------------------------------


def _run(cmd: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled", "TQDM_DISABLE": "1"}
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
    if proc.returncode != 0:
        tail = "\n".join((proc.stdout + proc.stderr).splitlines()[-40:])
        pytest.fail(f"{Path(cmd[0]).name} failed ({proc.returncode}):\n{tail}")
    return proc


@pytest.fixture(scope="module")
def diffusion_checkpoint(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("train")
    ds = make_dataset("reach-around", root / "ds", episodes_per_mode=2, seed=0, progress=False)
    out = root / "out"
    _run([str(BIN / "lerobot-train"), "--policy.type=diffusion", "--policy.down_dims=[32,64]",
          "--policy.n_obs_steps=2", "--policy.horizon=16", "--policy.n_action_steps=8",
          "--policy.num_train_timesteps=10", "--policy.num_inference_steps=4", "--policy.push_to_hub=false",
          "--policy.device=cpu", "--steps=3", "--batch_size=4", "--num_workers=0", "--save_freq=3",
          "--log_freq=1", "--wandb.enable=false", "--dataset.repo_id=local/reach", f"--dataset.root={ds}",
          f"--output_dir={out}"], cwd=root)
    ckpt = out / "checkpoints" / "last" / "pretrained_model"
    assert (ckpt / "model.safetensors").is_file()
    return ckpt


@pytest.mark.slow
def test_lerobot_train_diffusion_on_generated_dataset(diffusion_checkpoint):
    cfg = json.loads((diffusion_checkpoint / "config.json").read_text())
    assert cfg["type"] == "diffusion"
    assert cfg["input_features"]["observation.environment_state"]["shape"] == [6]


@pytest.mark.slow
def test_lerobot_eval_runs_in_scene1(diffusion_checkpoint, tmp_path):
    out = tmp_path / "eval"
    _run([str(BIN / "lerobot-eval"), f"--policy.path={diffusion_checkpoint}", "--policy.device=cpu",
          "--env.type=pdp_reach_around", "--env.scene=1", "--eval.n_episodes=2", "--eval.batch_size=1",
          f"--output_dir={out}"], cwd=tmp_path)
    info = json.loads((out / "eval_info.json").read_text())
    assert info["overall"]["n_episodes"] == 2 and info["overall"]["pc_success"] in (0.0, 50.0, 100.0)  # of 2
