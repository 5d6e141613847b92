"""Whole demonstrations of a local LeRobotDataset, and their mode labels (an episode-level label file
beside the dataset, or task strings of the form ``"mode <id>: <name>"``).

The training loader yields windows; the behavior encoder, latent fitting and the benchmark need complete
episodes, read here straight from the dataset's parquet files.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np


def read_episodes(root: str | Path, keys: list[str], episodes: list[int] | None = None,
                  images: list[str] = (), mode_labels: bool = True) -> dict[int, dict]:
    """Whole episodes of a local LeRobotDataset v3 as numpy arrays: {episode_index: {key: [T, ...], "task": str}},
    plus ``"mode"`` / ``"mode_name"`` when the dataset has episode-level labels (``meta/mode_labels.json``).

    Reads the parquet files directly: the training loader only yields windows, but the behavior encoder
    needs complete demonstrations. ``images``: camera columns stored as images, returned as their cells
    (PNG bytes; see :func:`read_episode_frames`). ``mode_labels=False`` leaves the label file unread (for
    the writers that replace it, whatever a stale one says).
    """
    import pandas as pd

    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"dataset folder {root} does not exist" if not root.exists() else
                                f"{root} is a file; give a LeRobotDataset v3 folder")
    files = sorted((root / "data").glob("**/*.parquet"))
    if not files:
        raise FileNotFoundError(f"no parquet data files under {root / 'data'}; is {root} a LeRobotDataset v3?")
    tasks_path = root / "meta" / "tasks.parquet"
    task_by_index: dict[int, str] = {}
    if tasks_path.is_file():
        t = pd.read_parquet(tasks_path)
        task_by_index = {int(i): str(task) for task, i in zip(t.index, t["task_index"], strict=True)}
    import pyarrow.parquet as pq

    cols = list(dict.fromkeys(["episode_index", "frame_index", "index", "task_index", *keys, *images]))
    # only the needed columns and episodes are read: a camera dataset's other columns (image cells) and a
    # large dataset's other episodes would dominate reading one demonstration
    rows = [("episode_index", "in", [int(e) for e in episodes])] if episodes is not None else None
    frames = []
    for f in files:
        have = pq.read_schema(f).names
        missing = [c for c in cols if c not in have]
        if missing:
            raise KeyError(f"{f}: dataset has no column(s) {missing}; columns are {sorted(have)}")
        frames.append(pd.read_parquet(f, columns=cols, filters=rows))
    df = pd.concat(frames, ignore_index=True)
    out: dict[int, dict] = {}
    for ep, g in df.groupby("episode_index", sort=True):
        g = g.sort_values("frame_index")
        item = {k: np.stack(g[k].to_numpy()).astype(np.float64) for k in keys}
        item.update({k: list(g[k]) for k in images})
        item["task"] = task_by_index.get(int(g["task_index"].iloc[0]), "")
        item["from_index"] = int(g["index"].iloc[0])  # global frame index of the episode's first frame
        out[int(ep)] = item
    labels = read_mode_labels(root) if mode_labels else None
    if labels is not None:
        for ep, item in out.items():
            if ep not in labels[0]:
                raise ValueError(f"{root / 'meta' / MODE_LABELS_FILE}: episode {ep} has no mode label "
                                 "(label every episode, or remove the file)")
            item["mode"] = labels[0][ep]
            item["mode_name"] = labels[1].get(labels[0][ep], "")
    return out


def read_episode_frames(root: str | Path, episode: int, keys: list[str]) -> dict[str, np.ndarray]:
    """Camera frames of one episode of a local LeRobotDataset, uint8 [T, 3, H, W] by camera key.

    Cameras stored as video are decoded with LeRobot's own decoder (all frames of the episode in one pass,
    at the episode's offset in the shared video file); cameras stored as images are read from the parquet
    files (PNG bytes). ``read_episodes`` gives the vectors of the same frames.
    """
    if not keys:
        return {}
    import io

    from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
    from lerobot.datasets.video_utils import decode_video_frames, get_safe_default_video_backend
    from PIL import Image

    root = Path(root)
    meta = LeRobotDatasetMetadata(f"local/{root.name}", root=root)
    missing = [k for k in keys if k not in meta.video_keys and k not in meta.image_keys]
    if missing:
        raise KeyError(f"{root}: no camera {missing}; its cameras are {sorted(meta.video_keys + meta.image_keys)}")
    image_keys = [k for k in keys if k in meta.image_keys]
    frames = read_episodes(root, ["timestamp"], [episode], images=image_keys)
    if episode not in frames:
        raise KeyError(f"{root} has no episode {episode}")
    item = frames[episode]
    out: dict[str, np.ndarray] = {}
    for key in keys:
        if key in image_keys:
            out[key] = np.stack([np.asarray(Image.open(io.BytesIO(cell["bytes"])).convert("RGB")).transpose(2, 0, 1)
                                 for cell in item[key]])
            continue
        offset = float(meta.episodes[episode][f"videos/{key}/from_timestamp"])
        video = decode_video_frames(root / meta.get_video_file_path(episode, key),
                                    [offset + float(t) for t in item["timestamp"]], tolerance_s=1e-4,
                                    backend=get_safe_default_video_backend(), return_uint8=True)
        out[key] = video.numpy()
    return out


def check_finite(name: str, array: np.ndarray, where: str) -> None:
    """Raise naming the episode/key and the first bad frame if ``array`` has NaN or inf."""
    bad = ~np.isfinite(array)
    if bad.any():
        frame = int(np.argwhere(bad)[0][0])
        raise ValueError(f"{where}: '{name}' has non-finite values (first at frame {frame}: {array[frame].tolist()})")


def parse_task_mode(task: str) -> int | str | None:
    """The mode label of an episode's task string: ``"mode 3: left-wide"`` -> 3, ``"mode novel: ..."`` ->
    ``"novel"``; None for a task string without one (e.g. a language instruction)."""
    if not isinstance(task, str) or not task.startswith("mode "):
        return None
    head = task[5:].split(":", 1)[0].strip()
    if head.isdigit():
        return int(head)
    return head or None


def parse_task_name(task: str) -> str:
    """The mode name of a ``"mode <id>: <name>"`` task string (``""`` when it has none)."""
    return task.split(":", 1)[1].strip() if isinstance(task, str) and ":" in task else ""


# Mode labels that live beside a dataset instead of in its task strings (which stay free for instructions).
MODE_LABELS_FILE = "mode_labels.json"


def read_mode_labels(root: str | Path) -> tuple[dict[int, int], dict[int, str]] | None:
    """The episode-level mode labels of a dataset, ``meta/mode_labels.json``, or None when it has none.

    Format (every episode listed, ids are integers >= 0, names optional)::

        {"episodes": {"0": 3, "1": 3, "2": 0, ...}, "names": {"0": "left, tight", "3": "right, wide"}}

    Returns ({episode index: mode id}, {mode id: name}). A malformed file is an error naming the key.
    """
    path = Path(root) / "meta" / MODE_LABELS_FILE
    return read_mode_labels_file(path) if path.is_file() else None


def read_mode_labels_file(path: str | Path) -> tuple[dict[int, int], dict[int, str]]:
    """A label file in the format of :func:`read_mode_labels`, checked; errors name the file and entry."""
    import json

    if not Path(path).is_file():
        raise FileNotFoundError(f"label file {path} does not exist (--labels: a JSON file "
                                '{"episodes": {"<episode index>": <mode id>, ...}, "names": {...}})')
    try:
        data = json.loads(Path(path).read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not JSON ({e})") from e
    if not isinstance(data, dict) or not isinstance(data.get("episodes"), dict):
        raise ValueError(f'{path}: expected {{"episodes": {{"<episode index>": <mode id>, ...}}, "names": {{...}}}}')
    return validate_mode_labels(data["episodes"], data.get("names") or {}, str(path))


def validate_mode_labels(episodes: dict, names: dict, where: str) -> tuple[dict[int, int], dict[int, str]]:
    """Check and convert label mappings (keys may be strings, as in JSON); errors name the entry."""
    labels: dict[int, int] = {}
    for key, value in episodes.items():
        if not str(key).lstrip("-").isdigit() or int(key) < 0:
            raise ValueError(f"{where}: episode key {key!r} is not an episode index (an integer >= 0)")
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{where}: episode {key} has mode {value!r}; expected an integer mode id >= 0")
        labels[int(key)] = value
    out_names: dict[int, str] = {}
    for key, value in names.items():
        if not str(key).isdigit():
            raise ValueError(f"{where}: names key {key!r} is not a mode id (an integer >= 0)")
        if not isinstance(value, str):
            raise ValueError(f"{where}: name of mode {key} is {value!r}; expected a string")
        out_names[int(key)] = value
    return labels, out_names


def write_mode_labels(root: str | Path, labels: dict[int, int], names: dict[int, str] | None = None) -> Path:
    """Write ``meta/mode_labels.json`` for the dataset at ``root`` (every episode must be labelled)."""
    import json

    from .atomic import write_text_atomic

    root = Path(root)
    info = root / "meta" / "info.json"
    if not info.is_file():
        raise FileNotFoundError(f"{root} is not a LeRobotDataset (no meta/info.json)")
    labels, names = validate_mode_labels(labels, names or {}, str(root / "meta" / MODE_LABELS_FILE))
    total = json.loads(info.read_text()).get("total_episodes")
    missing = sorted(set(range(total)) - set(labels)) if isinstance(total, int) else []
    extra = sorted(set(labels) - set(range(total))) if isinstance(total, int) else []
    if missing or extra:
        raise ValueError(f"{root}: labels must cover episodes 0..{total - 1} exactly; missing {missing[:10]}, "
                         f"not in the dataset {extra[:10]}")
    path = root / "meta" / MODE_LABELS_FILE
    write_text_atomic(path, json.dumps({"episodes": {str(k): v for k, v in sorted(labels.items())},
                                        "names": {str(k): v for k, v in sorted(names.items())}}, indent=1))
    return path


def feature_problems(required: dict[str, tuple[int, ...]], features: dict[str, dict],
                     names: dict[str, list[str]] | None = None) -> list[str]:
    """How dataset-format ``features`` (a recording's ``meta/info.json``, a robot's or a robot client's; cameras stored
    (H, W, C)) differ from what a policy was trained on (``required``: key -> shape, cameras (C, H, W); ``names``: the
    training data's value names by key, ``PDPConfig.dataset_feature_names``): each key lacking (with what is there in
    its place), of another shape, or naming its values in another order; [] when they fit."""
    problems = order_problems({k: v for k, v in (names or {}).items() if k in required}, features)
    for key, shape in required.items():
        ft = features.get(key)
        if ft is None:
            camera = key.startswith("observation.images.")  # name what is there in its place
            alike = [k for k in features if k.startswith("observation.") and k.startswith("observation.images.") == camera]
            kind = "camera" if camera else "observation"
            there = f"{kind}s {', '.join(map(repr, alike))}" if alike else f"no {kind}"
            problems.append(f"lacks '{key}' (it has {there})")
            continue
        got = policy_shape(ft)
        if got != tuple(shape):
            names = ft.get("names") if ft.get("dtype") not in ("image", "video") else None  # cameras: (C, H, W) both
            problems.append(f"'{key}' has shape {got}{f' (names {names})' if isinstance(names, list) else ''}, "
                            f"the policy was trained on {tuple(shape)}")
    return problems


def value_names(feature: dict) -> list[str] | None:
    """A vector feature's value names as a list (LeRobot stores a list, or a dict of one list such as
    ``{"motors": [...]}``); None where it names none."""
    names = feature.get("names")
    if isinstance(names, dict) and len(names) == 1:
        names = next(iter(names.values()))
    if isinstance(names, list) and names and all(isinstance(n, str) for n in names):
        return list(names)
    return None


def order_problems(trained: dict[str, list[str]], features: dict[str, dict]) -> list[str]:
    """Vector features naming the values the policy was trained on (``trained``: key -> names in the training data's
    order) in another order: read position by position, each value would be taken for another. Names are compared
    without LeRobot's hardware suffix (``shoulder_pan.pos`` is ``shoulder_pan``: a robot's recording of a
    dataset's state); values named otherwise altogether are not compared (another naming, not another order)."""
    problems = []
    for key, want in trained.items():
        got = value_names(features.get(key) or {})
        if got is None or len(got) != len(want):
            continue
        stems, wanted = [_stem(n) for n in got], [_stem(n) for n in want]
        if stems != wanted and sorted(stems) == sorted(wanted):
            problems.append(f"'{key}' names its values {got}, in another order than the policy's training data "
                            f"({want}): reorder them to the training data's")
    return problems


def _stem(name: str) -> str:
    """A value's name without LeRobot's hardware suffix (``.pos``, ``.vel``...)."""
    return name.rsplit(".", 1)[0] if "." in name else name


def dataset_value_names(features: dict[str, dict], keys: list[str]) -> dict[str, list[str]] | None:
    """The value names of a dataset's vector ``keys`` (``PDPConfig.dataset_feature_names``); None when it names none."""
    names = {k: n for k in keys if (n := value_names(features.get(k) or {})) is not None}
    return names or None


def check_camera_sizes(cameras: dict[str, Any], root: object, features: dict[str, dict]) -> None:
    """Refuse a training dataset whose cameras (``features``, as stored) are not the size of the policy's
    (``cameras``: key -> feature of shape (C, H, W)), before its behaviours are read: a checkpoint fine-tuned on
    another dataset (``lerobot-train --policy.path=...``) keeps its features, and would fail only at its first step.
    Keys the dataset lacks are left to LeRobot's own checks (a ``rename_map`` may name them)."""
    wrong = feature_problems({k: tuple(ft.shape) for k, ft in cameras.items() if k in features}, features)
    if wrong:
        raise ValueError(f"dataset {root}: its frames are not the size this policy was trained on ({'; '.join(wrong)}); "
                         "fine-tune on frames of the policy's size, or train a new policy on this dataset")


def policy_shape(feature: dict) -> tuple[int, ...]:
    """A dataset feature's shape as the policy sees it: cameras stored (H, W, C) are (C, H, W)."""
    shape = tuple(feature.get("shape") or ())
    return (shape[2], shape[0], shape[1]) if feature.get("dtype") in ("image", "video") and len(shape) == 3 else shape


def recording_info(root: str | Path) -> dict:
    """A recording's ``meta/info.json``; a missing folder, a folder that is no LeRobotDataset or a damaged file
    is an error naming it (the light check; :func:`check_recording` reads the data files too)."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"recording {root} does not exist")
    info_path = root / "meta" / "info.json"
    if not info_path.is_file():
        raise FileNotFoundError(f"{root} is not a LeRobotDataset (no meta/info.json)")
    try:
        return json.loads(info_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{info_path} is not valid JSON ({e}): the recording's metadata is damaged") from e


def check_data_files(root: Path, files: list[Path]) -> None:
    """Each of a recording's parquet ``files`` opens (a file cut off while written has no footer); else an error
    naming it, where pyarrow names only "<Buffer>"."""
    import pyarrow.parquet as pq

    for f in files:
        try:
            pq.ParquetFile(f)
        except Exception as e:  # noqa: BLE001 - any unreadable file means the same thing here
            raise ValueError(f"recording {root}: {f.relative_to(root)} is unreadable ({e}); the recording was "
                             "probably interrupted while writing: record it again") from e


def check_recording(root: str | Path, episode: int, required: dict[str, tuple[int, ...]],
                    min_frames: int | None = None, what: str = "recording",
                    advice: str = "Record with the robot/env (and features) the policy was trained on",
                    fps: float | None = None, names: dict[str, list[str]] | None = None) -> None:
    """Fail early, naming the problem, on a recording PDP cannot fit z to.

    Checks what deep reads would report obscurely: a missing folder, an empty recording (no episode saved), an
    interrupted one (a data file without its parquet footer), an episode index out of range, and features
    that differ from the checkpoint's (``required``: key -> shape the policy was trained on; cameras are
    compared as (C, H, W) against the recording's (H, W, C); ``names``: the training data's value names, compared
    for their order), a frame rate other than ``fps`` (the training data's; not for a simulated recording); with
    ``min_frames``, an episode shorter than that (one action chunk: the horizon). Torch-free: ``lerobot-pdp steer``
    checks a recording with it.
    """
    root = Path(root)
    info = recording_info(root)
    total = int(info.get("total_episodes") or 0)
    files = sorted((root / "data").glob("**/*.parquet"))
    if total == 0 or not files:
        raise ValueError(f"recording {root} is empty (no saved episode): record at least one whole episode "
                         "(an episode cut off by Ctrl-C is dropped, not saved)")
    check_data_files(root, files)
    if not 0 <= int(episode) < total:
        raise KeyError(f"recording {root} has {total} episode(s) (0..{total - 1}); no episode {episode}")
    problems = feature_problems(required, info.get("features", {}), names)
    recorded_fps = info.get("fps")
    if fps is not None and isinstance(recorded_fps, (int, float)) and abs(float(recorded_fps) - float(fps)) > 1e-6 \
            and not simulated_recording(info):
        problems.append(f"it was recorded at {recorded_fps:g} fps, the policy's training data at {fps:g} fps (each "
                        f"action spans another time: record at {fps:g} fps, --dataset.fps={fps:g})")
    if problems:
        cameras = "observation.images." in " ".join(problems)  # which recording flags set a camera's name and size
        raise ValueError(f"{what} {root} does not match the checkpoint: " + "; ".join(problems) + f". {advice}"
                         + (" (pdp_sim: --robot.camera_names, --robot.camera_size)" if cameras else ""))
    if min_frames is not None:
        length = _episode_length(root, int(episode))
        if length is not None and length < min_frames:
            raise ValueError(f"recording {root}: episode {episode} has {length} frames, shorter than one action chunk "
                             f"(horizon {min_frames})")


def simulated_robot(robot_type: str | None) -> bool:
    """This project's simulation (the ``pdp_sim`` robot, or ``make-dataset``'s ``pdp_<env>``): one env step per action
    whatever the loop's pace, so a frame rate is no time scale there (``lerobot-rollout``'s episodic strategy even
    labels its recordings with ``--dataset.fps``, 30 by default, while the loop runs at ``--fps``)."""
    return str(robot_type or "").startswith("pdp_")


def simulated_recording(info: dict) -> bool:
    """A recording (its ``meta/info.json``) of this project's simulation: :func:`simulated_robot`."""
    return simulated_robot(info.get("robot_type"))


def episode_first_tasks(root: str | Path) -> dict[int, str]:
    """Each episode's first task as the recording's episode metadata lists it (``meta/episodes``' ``tasks``, in the
    order LeRobot wrote them, which need not be the frames' order): the task LeRobot's ``--dataset.eval_split``
    groups an episode by. Empty where the metadata does not say."""
    return {ep: str(tasks[0]) if tasks else "" for ep, tasks in _episode_metadata(root, "tasks").items()}


def _episode_length(root: Path, episode: int) -> int | None:
    """An episode's frame count from the recording's episode metadata (None where it does not say)."""
    length = _episode_metadata(root, "length").get(int(episode))
    return None if length is None else int(length)


def _episode_metadata(root: str | Path, column: str) -> dict[int, Any]:
    """One column of a recording's episode metadata (``meta/episodes/**.parquet``) by episode index; empty where a
    file lacks it or cannot be read (the callers fall back to the frames)."""
    import pyarrow.parquet as pq

    values: dict[int, Any] = {}
    for f in sorted((Path(root) / "meta" / "episodes").glob("**/*.parquet")):
        try:
            table = pq.read_table(f, columns=["episode_index", column]).to_pydict()
        except Exception:  # noqa: BLE001 - other metadata: the frames stand in
            return {}
        values.update((int(ep), v) for ep, v in zip(table["episode_index"], table[column], strict=True))
    return values
