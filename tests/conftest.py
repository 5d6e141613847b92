"""Shared fixtures: offline Hugging Face, a real synthetic LeRobotDataset v3, a PDP trained by lerobot-train."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")
os.environ.setdefault("TQDM_DISABLE", "1")
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("LEROBOT_PDP_CACHE", tempfile.mkdtemp(prefix="pdp-cache-"))
warnings.filterwarnings("ignore", module="torchcodec")

import pytest  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))

VENV_BIN = Path(sys.executable).parent


def lerobot_cli(name: str) -> str:
    """Path of a LeRobot console script in this interpreter's environment."""
    p = VENV_BIN / name
    return str(p) if p.exists() else name


def run_cli(args: list[str], timeout: float = 900, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run a console script as a real subprocess; on failure show its output tail."""
    full_env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1", **(env or {})}
    proc = subprocess.run(args, capture_output=True, text=True, timeout=timeout, env=full_env)
    if proc.returncode != 0:
        raise AssertionError(f"{' '.join(args)} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-6000:]}")
    return proc


@pytest.fixture(scope="session")
def synthetic_dataset(tmp_path_factory) -> Path:
    """4-mode 2-D dataset, 10 episodes per mode (a real LeRobotDataset v3 on disk)."""
    from synthetic import write_dataset

    root = tmp_path_factory.mktemp("data") / "synthetic"
    return write_dataset(root, episodes_per_mode=10, seed=0)


@pytest.fixture(scope="session")
def synthetic_meta(synthetic_dataset):
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    return LeRobotDatasetMetadata("local/synthetic", root=synthetic_dataset)


@pytest.fixture(scope="session")
def trained_checkpoint(synthetic_dataset, tmp_path_factory) -> Path:
    """PDP trained on the synthetic dataset by a real `lerobot-train` process (~1-2 min on 2 cores)."""
    out = tmp_path_factory.mktemp("train") / "run"
    run_cli([
        lerobot_cli("lerobot-train"), "--policy.type=pdp", "--policy.push_to_hub=false", "--policy.device=cpu",
        "--dataset.repo_id=local/synthetic", f"--dataset.root={synthetic_dataset}", f"--output_dir={out}",
        "--steps=900", "--batch_size=64", "--policy.optimizer_lr=1e-3", "--policy.embedding_lr=1e-3",
        "--policy.scheduler_warmup_steps=50", "--log_freq=300", "--save_freq=900", "--num_workers=0",
        "--wandb.enable=false", "--seed=0",
    ], timeout=1500)
    ckpt = out / "checkpoints" / "last" / "pretrained_model"
    assert (ckpt / "model.safetensors").is_file(), sorted(p.name for p in out.rglob("*"))
    return ckpt
