"""One demonstration as the steering API reads it: validated, split into phases and windowed once.

A demonstration is a dict of unnormalised arrays (as stored in a LeRobotDataset: ``observation.*``, ``action``,
shapes [T, ...]) or a ``(LeRobotDataset | dataset folder, episode index)`` pair. :func:`read_demonstration`
checks it against the policy's features (a clear error naming the key, shape, episode and file), converts
camera frames as LeRobotDataset yields them, and splits it into the frame ranges that get one latent each;
:func:`demonstration_windows` normalises it with the policy's statistics and cuts the training-style windows
that fitting scores. Encoding and fitting (``adaptation``, ``latent_fitting``) take what this module returns.
"""

from __future__ import annotations

import operator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lerobot.utils.constants import ACTION
from torch import Tensor, nn

from .behavior import gripper_segments
from .chunk_windows import DemoWindows, frame_windows
from .configuration_pdp import PDPConfig
from .episodes import check_finite, check_recording, read_episode_frames, read_episodes, recording_info  # noqa: F401  (re-exported)
from .normalization import FeatureStats

Episode = dict[str, Any] | tuple[Any, int]


@dataclass
class Demonstration:
    """One demonstration as the steering API uses it, validated and split once."""

    arrays: dict[str, np.ndarray]  # unnormalised float64 [T, dim] per feature key
    segments: list[tuple[int, int]]  # frame ranges that get one latent each
    per_phase: bool  # segments were asked for: latents are [M, d_z], else [d_z]


def read_demonstration(episode: Episode, config: PDPConfig, action_dim: int, segments="auto",
                       need_action: bool = True, acting: bool = False) -> Demonstration:
    """Validate a demonstration and split it into the segments that get one latent each.

    ``episode``: a dict of unnormalised arrays/tensors as stored in a LeRobotDataset (``observation.*``,
    ``action``; shapes [T, ...]) or a ``(LeRobotDataset | root path, episode_index)`` pair. ``segments``: None
    (one z), a list of frame ranges, or ``"gripper"`` (split on gripper events of ``config.segment_gripper_dim``):
    one z per phase, used in order during the rollout. ``"auto"`` (default): as the policy was trained, i.e.
    ``"gripper"`` when ``config.segment_gripper_dim`` is set, else None. ``acting``: the latents will be acted
    under, so several segments on a policy without phases are refused now, not after a fit.
    """
    segments = segments_as_trained(config, segments)
    if acting and config.segment_gripper_dim is None and not isinstance(segments, str) and segments is not None \
            and len(segments) > 1:
        raise ValueError(f"segments {list(segments)} ask for one latent per phase, but this policy has no phases "
                         "(trained without segment_gripper_dim): only the first would ever act. Fit one latent "
                         "(segments=None), or fit with activate=False to compare the segments' latents")
    arrays = _episode_arrays(episode, config, action_dim, need_action=need_action or segments == "gripper")
    return Demonstration(arrays, _resolve_segments(config, arrays, segments), per_phase=segments is not None)


def check_recording_exists(episode: Episode) -> None:
    """A ``(folder, index)`` demonstration whose folder holds no recording is named at once, before the seconds a
    checkpoint takes to load (the full check, against the policy's features, comes with the read)."""
    if isinstance(episode, (tuple, list)) and len(episode) == 2 and isinstance(episode[0], (str, Path)):
        recording_info(episode[0])


def segments_as_trained(config: PDPConfig, segments):
    """``"auto"``: split demonstrations the way the training behaviors were split."""
    if isinstance(segments, str) and segments == "auto":
        return "gripper" if config.segment_gripper_dim is not None else None
    return segments

def _resolve_segments(config: PDPConfig, ep: dict[str, np.ndarray], segments) -> list[tuple[int, int]]:
    T = len(ep[config.trace_key])
    if segments is None:
        return [(0, T)]
    if isinstance(segments, str) and segments != "gripper":
        raise ValueError(f"segments must be None, 'auto', 'gripper' or a list of (start, end) frame ranges, "
                         f"got {segments!r}")
    if segments == "gripper":
        if config.segment_gripper_dim is None:
            raise ValueError("segments='gripper' needs config.segment_gripper_dim (the gripper action dim)")
        return gripper_segments(ep[ACTION], config.segment_gripper_dim,
                                config.segment_gripper_threshold)
    segs = [(int(a), int(b)) for a, b in segments]
    for a, b in segs:
        if not 0 <= a < b <= T:
            raise ValueError(f"segment ({a}, {b}) is not a non-empty frame range within the episode's {T} frames")
    # every window is fitted under the phase of its frame: the phases must tile the episode, in order
    if not segs or segs[0][0] != 0 or segs[-1][1] != T or any(b != a for (_, b), (a, _) in zip(segs[:-1], segs[1:], strict=True)):
        raise ValueError(f"segments {segs} must cover the episode's {T} frames in order, each starting where the "
                         f"one before ends (e.g. [(0, k), (k, {T})]): one latent per phase, used in order")
    return segs


def episode_index(index: Any, root: Any = None) -> int:
    """An episode index as an int; a float such as 0.9 is an error (``int()`` would read it as episode 0)."""
    try:
        if isinstance(index, bool):
            raise TypeError
        return operator.index(index.item() if isinstance(index, Tensor) else index)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(f"episode index must be an integer{f' (an episode of {root})' if root is not None else ''}, "
                        f"got {type(index).__name__} {index!r}") from None


def _required_features(cfg: PDPConfig, action_dim: int, need_action: bool) -> dict[str, tuple[int, ...]]:
    required = {cfg.trace_key: tuple(cfg.input_features[cfg.trace_key].shape)}
    if need_action:
        required.update({k: tuple(ft.shape) for k, ft in cfg.condition_features.items()})
        required[ACTION] = (action_dim,)
    return required


def demonstration_source(episode: Any) -> dict[str, Any]:
    """Where a demonstration came from, as adaptation.json and teaching.json record it: ``{"dataset": <its folder,
    absolute>, "episode": <index>}`` for a ``(folder or LeRobotDataset, index)`` pair, else arrays given in memory."""
    if not isinstance(episode, tuple):
        return {"arrays": "given in memory"}
    source, index = episode
    root = source if isinstance(source, (str, Path)) else getattr(source, "root", source)
    return {"dataset": str(Path(str(root)).resolve()), "episode": int(index)}


def _recorded_episode(episode: tuple, required: dict[str, tuple[int, ...]], config: PDPConfig) -> tuple[Path | str, int]:
    """A ``(dataset, episode index)`` pair's folder and index, the recording checked (empty, interrupted,
    index out of range, features that differ, values in another order, another frame rate: a clear error) without
    reading its frames."""
    source, index = episode
    root = source if isinstance(source, (str, Path)) else getattr(source, "root", None)
    if root is None:
        raise TypeError(f"episode source must be a LeRobotDataset or a dataset folder, got {type(source)}")
    index = episode_index(index, root)
    check_recording(root, index, required, fps=config.dataset_fps, names=config.dataset_feature_names)
    return root, index


def check_demonstration(episode: Episode, config: PDPConfig, action_dim: int, need_action: bool = True) -> None:
    """What :func:`read_demonstration` refuses about a recorded episode before reading it, without reading it (so
    a bad one of several is named before work on the first); arrays given in memory are checked when read."""
    if isinstance(episode, tuple):
        _recorded_episode(episode, _required_features(config, action_dim, need_action), config)


def _episode_arrays(episode: Episode, config: PDPConfig, action_dim: int, need_action: bool) -> dict[str, np.ndarray]:
    """Validate a demonstration and return its arrays (unnormalised) by feature key: vectors as float64
    [T, dim], cameras as float32 [T, 3, H, W] in [0, 1]. The trace is always needed; the denoiser's
    observations and the actions only where the demonstration is fitted (``need_action``)."""
    cfg = config
    required = _required_features(cfg, action_dim, need_action)
    where = "episode"
    if isinstance(episode, tuple):
        root, index = _recorded_episode(episode, required, cfg)
        where = f"episode {index} of {root}"
        cameras = [k for k in required if k in cfg.image_features]
        eps = read_episodes(root, [k for k in required if k not in cameras], [index])
        if index not in eps:
            raise KeyError(f"{root} has no episode {index}")
        episode = {**eps[index], **read_episode_frames(root, index, cameras)}
    if not isinstance(episode, dict):
        source = episode[0] if isinstance(episode, list) and len(episode) == 2 else episode
        shown = repr(str(source)) if isinstance(source, (str, Path)) else "dataset" if hasattr(source, "root") else None
        hint = f": one episode of a recording is the tuple ({shown}, <episode index>)" if shown else ""
        raise TypeError(f"episode must be a dict of arrays or a (dataset, episode_index) tuple, got "
                        f"{type(episode).__name__}{hint}")
    out: dict[str, np.ndarray] = {}
    for key, shape in required.items():
        if key not in episode:
            raise KeyError(f"{where}: missing '{key}'; PDP needs {sorted(required)} (got {sorted(episode)})")
        v = episode[key]
        v = v.detach().cpu().numpy() if isinstance(v, Tensor) else np.asarray(v)
        out[key] = (_camera_frames(key, v, shape, where) if key in cfg.image_features
                    else _vector_frames(key, v, shape[0], where))
    lengths = {k: len(v) for k, v in out.items()}
    if len(set(lengths.values())) != 1:
        raise ValueError(f"{where}: keys have different lengths {lengths}")
    T = next(iter(lengths.values()))
    if T < cfg.horizon:
        raise ValueError(f"{where}: has {T} frames, shorter than one action chunk (horizon {cfg.horizon})")
    return out


def demonstration_windows(demo: Demonstration, config: PDPConfig, stats: FeatureStats, obs_encoder: nn.Module,
                          device: torch.device | str) -> DemoWindows:
    """The (normalised) training-style windows of ``demo``, each tagged with its phase; every frame is
    encoded once (cameras with the centre crop, as at inference)."""
    cfg = config
    norm = stats.normalize_episode({k: v for k, v in demo.arrays.items()
                                         if k in cfg.condition_features or k == ACTION})
    was_training = obs_encoder.training
    obs_encoder.eval()  # cameras: the centre crop, as at inference
    try:
        feats = obs_encoder.frame_features({k: v.to(device) for k, v in norm.items() if k != ACTION})
    finally:
        obs_encoder.train(was_training)
    return frame_windows(feats, norm[ACTION], cfg.n_obs_steps, cfg.horizon, demo.segments)


def _vector_frames(key: str, v: np.ndarray, dim: int, where: str) -> np.ndarray:
    v = v.astype(np.float64)
    if v.ndim != 2 or v.shape[1] != dim:
        raise ValueError(f"{where}: '{key}' has shape {tuple(v.shape)}, expected [T, {dim}]")
    check_finite(key, v, where)
    return v


def _camera_frames(key: str, v: np.ndarray, shape: tuple[int, ...], where: str) -> np.ndarray:
    """Camera frames as LeRobotDataset yields them, float32 [T, 3, H, W] in [0, 1]; uint8 frames (either
    channel order, as a camera or ``lerobot-record`` gives them) are converted."""
    c, h, w = shape
    if v.ndim == 4 and v.shape[1:] == (h, w, c) and v.shape[1:] != (c, h, w):
        v = v.transpose(0, 3, 1, 2)
    if v.ndim != 4 or v.shape[1:] != (c, h, w):
        raise ValueError(f"{where}: camera '{key}' has frames of shape {tuple(v.shape)}, expected [T, {c}, {h}, {w}] "
                         f"(or [T, {h}, {w}, {c}] uint8), the shape the policy was trained on")
    if v.dtype == np.uint8:
        return v.astype(np.float32) / 255.0
    if not np.issubdtype(v.dtype, np.floating):
        raise ValueError(f"{where}: camera '{key}' has {v.dtype} frames; expected uint8 (0-255) or float in [0, 1] "
                         "(as LeRobotDataset yields frames)")
    v = v.astype(np.float32)
    check_finite(key, v.reshape(len(v), -1), where)
    if v.min() < -1e-3 or v.max() > 1 + 1e-3:
        raise ValueError(f"{where}: camera '{key}' has float values in [{v.min():.3g}, {v.max():.3g}]; expected "
                         "[0, 1] (as LeRobotDataset yields frames) or uint8")
    return v
