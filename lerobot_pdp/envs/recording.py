"""Scripted demonstrations -> LeRobotDataset v3, one command per env and scene.

State-only by default; with ``camera=`` each camera adds ``observation.images.<name>``, stored as video as
LeRobot stores camera data.

Every episode is a full expert rollout that reached the goal without collision (and, for mode demos, that
the env's classifier labels with the intended mode); failed attempts are retried with fresh jitter, a
bounded number of times, so a mode that is infeasible in the scene fails loudly instead of looping.
The dataset is written into a temporary directory next to ``out`` and renamed only when complete, so an
interrupted run never leaves something that looks like a dataset.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from ..atomic import staging_dir
from ..cpu_priority import keep_cpu_scheduling
from .camera import DEFAULT_IMAGE_SIZE, parse_image_size
from .scene import VALIDATION_SCENE, Scene, SceneError, load_scene, read_scene_file, scenes_with_waypoints
from .suite import NOVEL, SuiteEnv, get_suite_env

META_FILE = "pdp_suite.json"  # extra file in meta/: which env/scene generated the dataset (for plotting)
WAYPOINT_JOB = 10_000  # rng stream id of way-point demos (mode ids are < this)


class DemoGenerationError(RuntimeError):
    """The expert could not produce an acceptable demonstration within the retry budget."""


def _resolve_modes(suite: SuiteEnv, modes: Sequence[int | str] | None) -> list[int]:
    if modes is None:
        return list(range(suite.n_modes))
    out = []
    for m in modes:
        if isinstance(m, str) and not m.strip().lstrip("-").isdigit():
            if m not in suite.mode_names:
                raise ValueError(f"{suite.name}: unknown mode {m!r}; modes are {list(suite.mode_names)}")
            out.append(suite.mode_names.index(m))
            continue
        i = int(m)
        if not 0 <= i < suite.n_modes:
            raise ValueError(f"{suite.name}: mode {i} out of range [0, {suite.n_modes - 1}]")
        out.append(i)
    if not out:
        raise ValueError("modes must not be empty")
    return out


def resolve_waypoints(waypoints: Any, scene: Any, suite: SuiteEnv) -> np.ndarray:
    """Way-points from ``"scene"`` (the scene's own), a JSON/YAML file (a list, or a scene file), or a list."""
    where = ""  # a file's way-points are named with the file
    if isinstance(waypoints, str) and waypoints == "scene":
        sc = load_scene(scene, suite.scene_key)
        if sc.waypoints is None:
            raise SceneError(f"{sc.source}: waypoints='scene' but the scene has no 'waypoints' (the shipped "
                             f"{suite.name} scenes with way-points: {', '.join(scenes_with_waypoints(suite.scene_key))};"
                             " or give them in a JSON/YAML file)")
        return np.asarray(sc.waypoints, dtype=float)
    if isinstance(waypoints, (str, Path)):
        path = Path(waypoints)
        if path.is_dir():
            raise IsADirectoryError(f"way-point file {path} is a folder: give a JSON/YAML file (a list of points or "
                                    "a scene file with 'waypoints') or 'scene'")
        if not path.is_file():
            inline = str(waypoints).lstrip().startswith("[")
            raise FileNotFoundError(f"way-point file {path} does not exist" + (
                "; points are not read from the command line: write them to a JSON file ([[x, y, z], ...]) or give "
                "'scene'" if inline else ""))
        try:
            if path.suffix.lower() in (".yaml", ".yml"):
                import yaml

                data = yaml.safe_load(path.read_text())
            else:
                data = json.loads(path.read_text())
        except Exception as e:  # noqa: BLE001 - json's and yaml's parse errors: named with the file
            raise ValueError(f"way-point file {path} is not valid {'YAML' if path.suffix.lower() in ('.yaml', '.yml') else 'JSON'}"
                             f" ({e}); give a list of [x, y(, z)] points or a scene file with 'waypoints'") from e
        if isinstance(data, dict):
            sc = read_scene_file(path)
            if sc.waypoints is None:
                raise SceneError(f"{path}: a mapping must be a scene file with 'waypoints'")
            return np.asarray(sc.waypoints, dtype=float)
        waypoints, where = data, f"way-point file {path}: "
    try:
        arr = np.asarray(waypoints, dtype=float)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}way-points must be a list of points of the same size ([x, y] or [x, y, z], one "
                         f"coordinate per trace dim of the env), got {waypoints!r}") from e
    if arr.ndim != 2 or len(arr) == 0 or not np.all(np.isfinite(arr)):
        raise ValueError(f"{where}way-points must be a non-empty list of finite points, got {waypoints!r}")
    return arr


def check_waypoints(suite: SuiteEnv, waypoints: np.ndarray, source: Any) -> None:
    """Way-points that a path of ``suite`` can pass: one coordinate per trace dim, inside the env's workspace
    (where the env declares one); else a ValueError naming ``source``, the point and what was expected."""
    w = np.asarray(waypoints, dtype=float)
    if w.ndim != 2 or w.shape[1] != len(suite.trace_dims):
        raise ValueError(f"{source}: {suite.name} way-points are points of {len(suite.trace_dims)} coordinates (its "
                         f"path's dims), got shape {w.shape}")
    cls = gym.envs.registration.load_env_creator(gym.spec(suite.gym_id).entry_point)
    low, high = getattr(cls, "workspace_low", ()), getattr(cls, "workspace_high", ())
    if len(low) != w.shape[1] or len(high) != w.shape[1]:
        return
    for i, p in enumerate(w):
        if np.any(p < np.asarray(low)) or np.any(p > np.asarray(high)):
            raise ValueError(f"{source}: way-point {i} {p.tolist()} lies outside {suite.name}'s workspace "
                             f"{list(low)} .. {list(high)}: the agent can never pass it")


def _rollout(env: gym.Env, expert, reset_seed: int) -> tuple[list[dict[str, np.ndarray]], list[np.ndarray], dict]:
    """One expert episode: the observations it acted on (plus the final one), its actions, the last info."""
    obs, info = env.reset(seed=reset_seed)
    expert.reset(obs)
    observations, actions = [obs], []
    while True:
        action = np.asarray(expert(obs), dtype=np.float32)
        actions.append(action)
        obs, _, terminated, truncated, info = env.step(action)
        observations.append(obs)
        if terminated or truncated:
            return observations, actions, info


def run_expert_episode(suite: SuiteEnv, scene: Any = 0, mode: int | None = None, waypoints: Any = None,
                       seed: int = 0) -> tuple[dict, np.ndarray, int]:
    """Roll out a mode's expert (or a way-point expert) once in ``scene``: (last info, states, n_steps)."""
    env = gym.make(suite.gym_id, scene=scene, disable_env_checker=True)
    rng = np.random.default_rng(seed)
    expert = (suite.make_expert(mode, rng, scene=scene) if waypoints is None
              else suite.expert_from_waypoints(waypoints, rng, scene=scene))
    try:
        observations, _, info = _rollout(env, expert, seed)
    finally:
        env.close()
    return info, np.asarray([o["agent_pos"] for o in observations]), len(observations) - 1


def _dataset_features(env: gym.Env) -> dict[str, dict]:
    spaces = env.observation_space
    base = env.unwrapped

    def names(attr: str, n: int, prefix: str) -> list[str]:
        fn = getattr(base, attr, None)
        got = list(fn()) if callable(fn) else None
        return got if got is not None and len(got) == n else [f"{prefix}{i}" for i in range(n)]

    n_state = int(spaces["agent_pos"].shape[0])
    n_env = int(spaces["environment_state"].shape[0])
    n_act = int(env.action_space.shape[0])
    features = {
        "observation.state": {"dtype": "float32", "shape": (n_state,), "names": names("state_names", n_state, "s")},
        "observation.environment_state": {
            "dtype": "float32",
            "shape": (n_env,),
            "names": names("environment_state_names", n_env, "e"),
        },
        "action": {"dtype": "float32", "shape": (n_act,), "names": names("action_names", n_act, "a")},
    }
    if "pixels" in spaces.spaces:
        for cam, box in spaces["pixels"].spaces.items():
            features[f"observation.images.{cam}"] = {
                "dtype": "video",
                "shape": tuple(int(v) for v in box.shape),
                "names": ["height", "width", "channels"],
            }
    return features


@contextlib.contextmanager
def _skip_image_embedding(features: dict[str, dict]) -> Iterator[None]:
    """Skip LeRobot's per-row image-embedding pass when the dataset has no ``image`` features.

    ``DatasetWriter._save_episode_data`` maps ``embed_table_storage`` over every row even for state-only
    data, a no-op there that costs ~2 ms per frame (70 % of generation time). Video features are no
    exception: their frames live in mp4 files, not in the table. Only applied to datasets without
    ``image`` features, and restored afterwards.
    """
    if any(ft.get("dtype") == "image" for ft in features.values()):
        yield
        return
    try:
        from lerobot.datasets import dataset_writer
    except ImportError:  # pragma: no cover - layout of another lerobot version
        yield
        return
    original = getattr(dataset_writer, "embed_images", None)
    if original is None:  # pragma: no cover
        yield
        return
    dataset_writer.embed_images = lambda dataset: dataset
    try:
        yield
    finally:
        dataset_writer.embed_images = original


def _scene_tag(scene: Any) -> str:
    if isinstance(scene, Scene):
        return "custom"
    if isinstance(scene, (int, np.integer)) or (isinstance(scene, str) and scene.strip().isdigit()):
        return str(int(scene))
    return Path(str(scene)).stem if isinstance(scene, (str, Path)) else "custom"


def _scene_meta(scene: Any) -> Any:
    if isinstance(scene, Scene):
        return scene.to_dict()
    if isinstance(scene, dict):
        return scene
    if isinstance(scene, Path):
        return str(scene.resolve())
    if isinstance(scene, str) and VALIDATION_SCENE.match(scene.strip()):
        return scene.strip()  # a shipped validation scene: its name, not a path in the working directory
    if isinstance(scene, str) and not scene.strip().isdigit():
        return str(Path(scene).resolve())
    return int(scene) if scene is not None else 0


def make_dataset(
    env: str,
    out: str | Path,
    scene: Any = 0,
    episodes_per_mode: int = 10,
    seed: int = 0,
    modes: Sequence[int | str] | None = None,
    waypoints: Any = None,
    progress: bool = True,
    max_attempts: int = 20,
    repo_id: str | None = None,
    camera: str | Sequence[str] | None = None,
    image_size: int | str | Sequence[int] = DEFAULT_IMAGE_SIZE,
) -> Path:
    """Generate expert demonstrations for ``env`` in ``scene`` and write them as a LeRobotDataset at ``out``.

    Beside LeRobot's metadata, ``meta/pdp_suite.json`` records how (env, scene, seed, modes or way-points)
    and, per episode, its mode and its closest approach to an obstacle (metres; null without obstacles).

    Args:
        env: suite env name (``reach-around``), scene key, gym id or ``pdp_*`` env type.
        out: dataset directory; must not exist.
        scene: scene index, scene file path, mapping or :class:`Scene`.
        episodes_per_mode: accepted demonstrations per mode (or along ``waypoints``).
        seed: all randomness (jitter, reset noise) derives from it; same seed -> same dataset.
        modes: training modes (ids or names) to record; default all. Exclusive with ``waypoints``.
        waypoints: record ``episodes_per_mode`` demos along these way-points instead of mode templates:
            ``"scene"`` (the scene file's own), a JSON/YAML path or a list of points. Each episode's task
            carries the classifier's label (usually ``novel``).
        max_attempts: tries per episode before giving up with :class:`DemoGenerationError`.
        repo_id: LeRobot repo id stored in the metadata (default ``local/pdp_<env>_scene<k>``).
        camera: camera name(s) of the env (``"top"``, ``"top,front"``); each adds a video feature
            ``observation.images.<name>`` of ``image_size`` pixels. None: state-only, as before.
        image_size: N or (H, W) pixels of each camera image.

    Returns:
        ``out`` as a :class:`Path`.
    """
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from tqdm.auto import tqdm

    import lerobot_pdp.envs  # noqa: F401  (registers every suite env)

    suite = get_suite_env(env)
    out = Path(out)
    if out.exists():
        raise FileExistsError(f"dataset output {out} already exists; choose a new path or delete it first")
    if episodes_per_mode < 1:
        raise ValueError(f"episodes_per_mode must be >= 1, got {episodes_per_mode}")
    if max_attempts < 1:
        raise ValueError(f"max_attempts must be >= 1, got {max_attempts}")
    if waypoints is not None and modes is not None:
        raise ValueError("give either modes or waypoints, not both")
    scene_obj = load_scene(scene, suite.scene_key)  # validate early, before any work
    camera_kwargs = _camera_kwargs(suite, camera, image_size)
    wps = resolve_waypoints(waypoints, scene, suite) if waypoints is not None else None
    if wps is not None:  # a point the agent can never reach would record idle or colliding episodes
        check_waypoints(suite, wps, waypoints if isinstance(waypoints, (str, Path)) else "waypoints")
    mode_list = _resolve_modes(suite, modes) if wps is None else []
    jobs: list[tuple[int | None, int]] = (
        [(m, e) for m in mode_list for e in range(episodes_per_mode)]
        if wps is None
        else [(None, e) for e in range(episodes_per_mode)]
    )

    gym_env = gym.make(suite.gym_id, scene=scene_obj, disable_env_checker=True, **camera_kwargs)
    rejected = 0
    labels: list[int | str] = []
    clearances: list[float | None] = []  # each accepted episode's closest approach to an obstacle
    features = _dataset_features(gym_env)
    cameras = [k.removeprefix("observation.images.") for k in features if k.startswith("observation.images.")]
    try:
        with staging_dir(out, prefix=f".{out.name}.partial-") as tmp, _skip_image_embedding(features):
            ds = LeRobotDataset.create(
                repo_id=repo_id or f"local/pdp_{suite.scene_key}_scene{_scene_tag(scene)}",
                fps=suite.fps,
                features=features,
                root=tmp / "dataset",
                robot_type=f"pdp_{suite.scene_key}",
                use_videos=bool(cameras),
            )
            bar = tqdm(jobs, desc=f"{suite.name} scene {_scene_tag(scene)}", unit="demo", disable=not progress)
            for mode, ep in bar:
                last = {}
                for attempt in range(max_attempts):
                    stream = WAYPOINT_JOB if mode is None else mode
                    rng = np.random.default_rng([seed, stream, ep, attempt])
                    if mode is None:
                        expert = suite.expert_from_waypoints(wps, rng, scene=scene_obj)
                    else:
                        expert = suite.make_expert(mode, rng, scene=scene_obj)
                    observations, actions, info = _rollout(gym_env, expert, int(rng.integers(2**31 - 1)))
                    states = np.stack([o["agent_pos"] for o in observations])
                    label = suite.classify_mode(states, scene=scene_obj)
                    ok = bool(info.get("is_success")) and not bool(info.get("collided", False))
                    if ok and (mode is None or label == mode):
                        break
                    rejected += 1
                    last = {
                        "is_success": info.get("is_success"),
                        "collided": info.get("collided"),
                        "min_clearance": info.get("min_clearance"),
                        "label": label,
                        "steps": len(actions),
                    }
                    bar.set_postfix(rejected=rejected)
                else:
                    what = f"mode {mode} ({suite.mode_names[mode]})" if mode is not None else "the given way-points"
                    raise DemoGenerationError(
                        f"{suite.name}, scene {_scene_tag(scene)}: no acceptable demonstration along {what} in "
                        f"{max_attempts} attempts (episode {ep}); last attempt: {last}. Is this route feasible "
                        f"in this scene?"
                    )
                task = suite.task_string(label if mode is None else mode)
                labels.append(label if mode is None else mode)
                clearance = info.get("min_clearance")  # inf in a scene without obstacles: JSON has no inf
                clearances.append(round(float(clearance), 5) if clearance is not None and np.isfinite(clearance)
                                  else None)
                for o, a in zip(observations[:-1], actions, strict=True):
                    frame = {
                        "observation.state": np.asarray(o["agent_pos"], dtype=np.float32),
                        "observation.environment_state": np.asarray(o["environment_state"], dtype=np.float32),
                        "action": np.asarray(a, dtype=np.float32),
                        "task": task,
                    }
                    for cam in cameras:
                        frame[f"observation.images.{cam}"] = o["pixels"][cam]
                    ds.add_frame(frame)
                with keep_cpu_scheduling():  # video encoding: the next episode's rollouts run at normal priority
                    ds.save_episode()
            with keep_cpu_scheduling():
                ds.finalize()
            _drop_empty_folders(tmp / "dataset" / "images")  # LeRobot's frames, encoded into videos: empty folders
            meta = {
                "env": suite.name,
                "scene": _scene_meta(scene),
                "seed": seed,
                "episodes_per_mode": episodes_per_mode,
                "modes": mode_list if wps is None else None,
                "waypoints": None if wps is None else wps.tolist(),
                "episode_modes": [lab if lab == NOVEL else int(lab) for lab in labels],
                "episode_min_clearance": clearances,
                "rejected_attempts": rejected,
            }
            if cameras:  # absent from state-only datasets, whose record stays as it was
                meta["cameras"] = cameras
                meta["image_size"] = list(parse_image_size(image_size))
            (tmp / "dataset" / "meta" / META_FILE).write_text(json.dumps(meta, indent=2))
            (tmp / "dataset").rename(out)
    finally:
        gym_env.close()
    return out


def _camera_kwargs(suite: SuiteEnv, camera: str | Sequence[str] | None,
                   image_size: int | str | Sequence[int]) -> dict[str, Any]:
    """Env kwargs for ``camera`` (empty without one), checked up front with errors that name the fix."""
    if camera is None or (isinstance(camera, str) and not camera.strip()):
        return {}
    from .configs import _accepts_kwarg

    if not _accepts_kwarg(suite.gym_id, "camera"):
        raise ValueError(f"{suite.name} has no camera observations; give no camera for it")
    parse_image_size(image_size)  # a clear error before the env is built
    return {"camera": camera, "image_size": image_size}


def read_dataset_meta(dataset_dir: str | Path) -> dict[str, Any] | None:
    """The generation record written by :func:`make_dataset`, or None for other datasets."""
    p = Path(dataset_dir) / "meta" / META_FILE
    return json.loads(p.read_text()) if p.is_file() else None


def _drop_empty_folders(folder: Path) -> None:
    """Remove ``folder`` and its subfolders when they hold no file (what LeRobot leaves after encoding videos)."""
    if not folder.is_dir():
        return
    for d in sorted((p for p in folder.rglob("*") if p.is_dir()), key=lambda p: len(p.parts), reverse=True):
        if not any(d.iterdir()):
            d.rmdir()
    if not any(folder.iterdir()):
        folder.rmdir()
