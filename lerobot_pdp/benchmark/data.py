"""The benchmark's demonstrations: the scene-0 training dataset and one demonstration per shifted scene,
generated once into the run folder and reused."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import write_text_atomic
from ..envs.scene import load_scene
from ..envs.suite import SuiteEnv
from .settings import TrainSettings, scene_label, scene_seed_offset


def ensure_dataset(suite: SuiteEnv, out: Path, settings: TrainSettings, seed: int = 0) -> Path:
    """The scene-0 training dataset (generated once, then reused)."""
    from ..envs.recording import make_dataset

    root = scene0_root(suite, out)
    info = root / "meta" / "info.json"
    if not info.is_file():
        print(f"[benchmark] generating {suite.name} scene-0 dataset ({settings.episodes_per_mode}/mode) -> {root}")
        make_dataset(suite.name, root, scene=0, episodes_per_mode=settings.episodes_per_mode, seed=seed,
                     **suite.camera_kwargs)
    # Reusing a dataset of another size would silently mix runs trained on different data in one table.
    expected = suite.n_modes * settings.episodes_per_mode
    found = json.loads(info.read_text()).get("total_episodes")
    if found != expected:
        raise ValueError(f"{root} holds {found} episodes but this benchmark needs {expected} "
                         f"({settings.episodes_per_mode} per mode x {suite.n_modes} modes); use another --out "
                         f"or delete {out / 'data'} and {out / 'runs'}")
    return root


def scene0_root(suite: SuiteEnv, out: Path) -> Path:
    """Where a benchmark output folder ``out`` keeps the scene-0 training dataset."""
    return out / "data" / f"{suite.scene_key}_scene0{_camera_tag(suite)}"


def _camera_tag(suite: SuiteEnv) -> str:
    """Folder-name suffix of a camera variant's data (``_oblique64``): state and camera runs never share data."""
    cam = suite.camera_kwargs
    return f"_{cam['camera']}{cam['image_size']}" if cam else ""


def feasible_training_modes(suite: SuiteEnv, scene: Any, seed: int = 0) -> list[int]:
    """Training modes whose scripted expert succeeds in ``scene`` (one seeded try each)."""
    from ..envs.recording import run_expert_episode

    return [m for m in range(suite.n_modes)
            if run_expert_episode(suite, scene, mode=m, seed=seed + m)[0].get("is_success")]


def demo_root(suite: SuiteEnv, out: Path, scene: int | str) -> Path:
    """Where a benchmark output folder ``out`` keeps the demonstration of ``scene`` (an int or ``"val<k>"``)."""
    return out / "data" / f"{suite.scene_key}_{scene_label(scene)}_demo{_camera_tag(suite)}"


def ensure_demo(suite: SuiteEnv, out: Path, scene: int | str, seed: int = 0) -> tuple[Path, str]:
    """One successful demonstration in ``scene``: the scene's way-points if it ships them, else its only
    feasible training mode. Returns the dataset folder and a description."""
    from ..envs.recording import make_dataset

    root = demo_root(suite, out, scene)
    info_file = root / "meta" / "pdp_demo.json"
    if info_file.is_file():
        return root, json.loads(info_file.read_text())["source"]
    sc = load_scene(scene, suite.scene_key)
    if sc.waypoints is not None:
        source = "scene way-points (new route)"
        kwargs: dict[str, Any] = {"waypoints": "scene"}
    else:
        modes = feasible_training_modes(suite, scene, seed)
        if not modes:
            raise RuntimeError(f"{suite.name} scene {scene}: no training mode is feasible and no way-points ship")
        source = f"training mode {modes[0]} ({suite.mode_names[modes[0]]})"
        kwargs = {"modes": [modes[0]]}
    if root.exists():
        shutil.rmtree(root)
    make_dataset(suite.name, root, scene=scene, episodes_per_mode=1, seed=seed + 1000 * scene_seed_offset(scene),
                 progress=False, **kwargs, **suite.camera_kwargs)
    write_text_atomic(info_file, json.dumps({"source": source}))
    return root, source


def demo_episode(root: Path) -> dict[str, np.ndarray]:
    """The demonstration's arrays: state, environment state, action, and its cameras as float32
    [T, 3, H, W] in [0, 1] (as LeRobotDataset yields frames)."""
    from ..episodes import read_episode_frames, read_episodes

    eps = read_episodes(root, ["observation.state", "observation.environment_state", "action"], [0])
    out = {k: v for k, v in eps[0].items() if isinstance(v, np.ndarray)}
    features = json.loads((Path(root) / "meta" / "info.json").read_text())["features"]
    cameras = [k for k, ft in features.items() if ft.get("dtype") in ("video", "image")]
    out.update({k: v.astype(np.float32) / 255.0 for k, v in read_episode_frames(root, 0, cameras).items()})
    return out


def check_run_env(folder: Path, suite) -> None:
    """Refuse a benchmark folder of another env (its results.json, else its training dataset's name) before a
    demonstration is made or a checkpoint fails on the first observation."""
    import json

    from ..envs.suite import get_suite_env

    env = None
    if (folder / "results.json").is_file():
        try:
            env = json.loads((folder / "results.json").read_text()).get("env")
        except (OSError, json.JSONDecodeError, AttributeError):
            env = None
    if env is None:  # a run still going: its scene-0 dataset is data/<scene_key>_scene0*
        data = sorted(p.name for p in (folder / "data").glob("*_scene0*")) if (folder / "data").is_dir() else []
        if data and not any(n.startswith(f"{suite.scene_key}_scene0") for n in data):
            env = data[0].split("_scene0")[0]
    if env is not None and get_suite_env(env).name != suite.name:
        raise ValueError(f"{folder} is a benchmark run of {get_suite_env(env).name}, not {suite.name}: "
                         f"give --env {get_suite_env(env).name}")
