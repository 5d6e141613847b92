"""A small synthetic multimodal dataset written as a real LeRobotDataset v3: 2-D paths around an obstacle.

A point moves from (0, -1) to (0, 1) around a disc at the origin, passing it on the left or right, tight
or wide: 4 modes. Actions are per-step displacements / MAX_STEP, so a rollout is ``pos += a * MAX_STEP``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

START = np.array([0.0, -1.0])
GOAL = np.array([0.0, 1.0])
MAX_STEP = 0.08
MODES = {0: ("left-tight", -0.45), 1: ("left-wide", -0.9), 2: ("right-tight", 0.45), 3: ("right-wide", 0.9)}


def demo_path(mode: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Positions [T, 2] and actions [T, 2] of one demonstration of ``mode`` (jittered via-point/speed)."""
    x_via = MODES[mode][1] + rng.normal(0, 0.04)
    via = np.array([x_via, rng.normal(0, 0.05)])
    speed = MAX_STEP * rng.uniform(0.6, 0.8)
    pts = [START, via, GOAL]
    pos = [START.copy()]
    for a, b in zip(pts[:-1], pts[1:], strict=True):
        n = int(np.ceil(np.linalg.norm(b - a) / speed))
        for i in range(1, n + 1):
            pos.append(a + (b - a) * i / n)
    pos = np.array(pos)
    # hold at the goal a few steps so chunks near the end are well defined
    pos = np.concatenate([pos, np.repeat(pos[-1:], 4, axis=0)])
    act = np.diff(pos, axis=0, append=pos[-1:]) / MAX_STEP
    return pos.astype(np.float32), np.clip(act, -1, 1).astype(np.float32)


def camera_image(pos: np.ndarray, size: int) -> np.ndarray:
    """A top-down view [size, size, 3] uint8: the obstacle disc (grey), the goal (green), the point (red)."""
    u = (np.arange(size) + 0.5) / size * 2.4 - 1.2
    x, y = np.meshgrid(u, -u)
    img = np.full((size, size, 3), 240, dtype=np.uint8)
    img[x**2 + y**2 < 0.3**2] = (90, 90, 100)
    img[(x - GOAL[0]) ** 2 + (y - GOAL[1]) ** 2 < 0.1**2] = (60, 180, 60)
    img[(x - pos[0]) ** 2 + (y - pos[1]) ** 2 < 0.12**2] = (220, 0, 0)
    return img


def write_dataset(root: Path, episodes_per_mode: int = 10, seed: int = 0, modes=(0, 1, 2, 3),
                  task: str | None = None, cameras: tuple[str, ...] = (), image_size: int = 48,
                  video: bool = True) -> Path:
    """Write the dataset to ``root`` (must not exist); task strings are ``"mode <id>: <name>"``, or ``task``
    for every episode (an instruction, as in most LeRobot datasets: no mode labels). ``cameras``: names of
    top-down cameras ``observation.images.<name>`` (stored as video, or as images with ``video=False``)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    rng = np.random.default_rng(seed)
    features = {
        "observation.state": {"dtype": "float32", "shape": (2,), "names": ["x", "y"]},
        "observation.environment_state": {"dtype": "float32", "shape": (2,), "names": ["goal_x", "goal_y"]},
        "action": {"dtype": "float32", "shape": (2,), "names": ["dx", "dy"]},
    }
    for cam in cameras:
        features[f"observation.images.{cam}"] = {"dtype": "video" if video else "image",
                                                 "shape": (image_size, image_size, 3),
                                                 "names": ["height", "width", "channels"]}
    ds = LeRobotDataset.create(repo_id="local/synthetic", fps=10, features=features, root=root,
                               use_videos=video and bool(cameras))
    for _ in range(episodes_per_mode):
        for m in modes:
            pos, act = demo_path(m, rng)
            for p, a in zip(pos, act, strict=True):
                frame = {"observation.state": p, "observation.environment_state": GOAL.astype(np.float32),
                         "action": a, "task": task or f"mode {m}: {MODES[m][0]}"}
                for cam in cameras:
                    frame[f"observation.images.{cam}"] = camera_image(p, image_size)
                ds.add_frame(frame)
            ds.save_episode()
    ds.finalize()
    return root

