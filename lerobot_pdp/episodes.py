"""Whole demonstrations of a local LeRobotDataset, and the mode labels their task strings may carry.

The training loader yields windows; the behavior encoder, latent fitting and the benchmark need complete
episodes, read here straight from the dataset's parquet files.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def read_episodes(root: str | Path, keys: list[str], episodes: list[int] | None = None) -> dict[int, dict]:
    """Whole episodes of a local LeRobotDataset v3 as numpy arrays: {episode_index: {key: [T, ...], "task": str}}.

    Reads the parquet files directly: the training loader only yields windows, but the behavior encoder
    needs complete demonstrations.
    """
    import pandas as pd

    root = Path(root)
    files = sorted((root / "data").glob("**/*.parquet"))
    if not files:
        raise FileNotFoundError(f"no parquet data files under {root / 'data'}; is {root} a LeRobotDataset v3?")
    tasks_path = root / "meta" / "tasks.parquet"
    task_by_index: dict[int, str] = {}
    if tasks_path.is_file():
        t = pd.read_parquet(tasks_path)
        task_by_index = {int(i): str(task) for task, i in zip(t.index, t["task_index"], strict=True)}
    cols = list(dict.fromkeys(["episode_index", "frame_index", "index", "task_index", *keys]))
    frames = []
    for f in files:
        df = pd.read_parquet(f)
        missing = [c for c in cols if c not in df.columns]
        if missing:
            raise KeyError(f"{f}: dataset has no column(s) {missing}; columns are {sorted(df.columns)}")
        frames.append(df[cols])
    df = pd.concat(frames, ignore_index=True)
    if episodes is not None:
        df = df[df["episode_index"].isin(list(episodes))]
    out: dict[int, dict] = {}
    for ep, g in df.groupby("episode_index", sort=True):
        g = g.sort_values("frame_index")
        item = {k: np.stack(g[k].to_numpy()).astype(np.float64) for k in keys}
        item["task"] = task_by_index.get(int(g["task_index"].iloc[0]), "")
        item["from_index"] = int(g["index"].iloc[0])  # global frame index of the episode's first frame
        out[int(ep)] = item
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
