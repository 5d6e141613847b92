"""Pre/post-processors of PDP: LeRobot's standard pipelines (rename, batch, device, normalise / unnormalise).

PDP normalises like LeRobot's diffusion policy (min-max to [-1, 1] for states, env states and actions, mean-std
for cameras), so the DDIM sampler's clipping range [-1, 1] matches the action range. The policy keeps a copy of the same
statistics to normalise whole demonstrations in ``fit_latent``/``encode``. Two steps of PDP's own come first:
:class:`CameraFrameCheck`, a camera frame in another layout than LeRobot's (uint8, channels last, 0-255, one channel)
refused by name before the normaliser, which would otherwise fail on it with a bare torch error or broadcast it; and
:class:`VectorSizeCheck`, a state of another size refused by name (the normaliser's error names no key).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from lerobot.processor import (
    ObservationProcessorStep,
    PolicyAction,
    PolicyProcessorPipeline,
    ProcessorStepRegistry,
    RenameObservationsProcessorStep,
    make_default_pre_post_processors,
)

from .configuration_pdp import PDPConfig

logger = logging.getLogger(__name__)


def make_pdp_pre_post_processors(
    config: PDPConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[PolicyProcessorPipeline[dict[str, Any], dict[str, Any]], PolicyProcessorPipeline[PolicyAction, PolicyAction]]:
    """Return ``(preprocessor, postprocessor)`` for a PDP policy; saved next to its checkpoints. Without
    ``dataset_stats`` they do not normalise (LeRobot's normaliser passes values through): said, since a policy
    acting on raw values does so silently; a checkpoint's own come with ``make_pre_post_processors(config,
    pretrained_path=...)``, a policy's with ``dataset_stats=policy.stats.as_dict()``."""
    if dataset_stats is None:
        logger.warning("PDP processors built without dataset_stats do not normalise: the policy would act on raw "
                       "values. Load a checkpoint's with make_pre_post_processors(config, pretrained_path=<checkpoint>) "
                       "or pass dataset_stats=policy.stats.as_dict()")
    pre, post = make_default_pre_post_processors(config, dataset_stats)
    cameras = {k: list(ft.shape) for k, ft in config.image_features.items()}
    vectors = {k: list(ft.shape) for k, ft in config.condition_features.items() if k not in cameras}
    # after the rename (the policy's keys), before the normaliser
    checks = ([CameraFrameCheck(cameras)] if cameras else []) + ([VectorSizeCheck(vectors)] if vectors else [])
    after = next((i + 1 for i, step in enumerate(pre.steps) if isinstance(step, RenameObservationsProcessorStep)), 0)
    pre.steps[after:after] = checks
    return pre, post


# Camera frames reach the preprocessor as LeRobot gives them (env and robot paths alike): float, channels first, in
# [0, 1]; a little slack for resampling and colour jitter
FRAME_RANGE_SLACK = 1e-3


@ProcessorStepRegistry.register(name="pdp_camera_frames")
@dataclass
class CameraFrameCheck(ObservationProcessorStep):
    """Refuse a camera frame the policy would misread, naming its key, what it is and what is expected: an integer
    frame (``uint8`` from a camera driver), channels last ``[H, W, C]``, other channels or size, values outside
    [0, 1]. It changes nothing it lets through. ``cameras``: key -> ``[C, H, W]`` the policy was trained on."""

    cameras: dict[str, list[int]] = field(default_factory=dict)

    def observation(self, observation: dict[str, Any]) -> dict[str, Any]:
        for key, chw in self.cameras.items():
            x = observation.get(key)
            if isinstance(x, (torch.Tensor, np.ndarray)):  # missing keys and other types: the policy names them
                check_camera_frame(key, x, chw)
        return observation

    def get_config(self) -> dict[str, Any]:
        return {"cameras": self.cameras}

    def transform_features(self, features: dict) -> dict:
        return features


@ProcessorStepRegistry.register(name="pdp_observation_sizes")
@dataclass
class VectorSizeCheck(ObservationProcessorStep):
    """Refuse a state-like observation of another size than the policy's, naming its key, its shape and the
    expected size: LeRobot's normaliser fails on it with a bare broadcasting error ("The size of tensor a (5) must
    match ..."). It changes nothing. ``vectors``: key -> ``[D]`` the policy was trained on."""

    vectors: dict[str, list[int]] = field(default_factory=dict)

    def observation(self, observation: dict[str, Any]) -> dict[str, Any]:
        for key, shape in self.vectors.items():
            x = observation.get(key)
            if isinstance(x, (torch.Tensor, np.ndarray)) and (x.ndim == 0 or list(x.shape[-1:]) != shape[-1:]):
                raise ValueError(f"observation {key!r} has shape {list(x.shape)}; this policy expects [..., "
                                 f"{shape[-1]}], its training dataset's {key} (the env or robot it was trained on, "
                                 "with the same features)")
        return observation

    def get_config(self) -> dict[str, Any]:
        return {"vectors": self.vectors}

    def transform_features(self, features: dict) -> dict:
        return features


def check_camera_frame(key: str, x: torch.Tensor | np.ndarray, chw: list[int]) -> None:
    """One camera's frame(s) ``[..., C, H, W]`` against LeRobot's convention (float in [0, 1], channels first)."""
    c, h, w = chw
    fix = "torch.from_numpy(frame).permute(2, 0, 1).float() / 255 turns a uint8 [H, W, C] frame into one"
    shape = list(x.shape)
    if not (x.dtype.is_floating_point if isinstance(x, torch.Tensor) else np.issubdtype(x.dtype, np.floating)):
        raise ValueError(f"camera {key!r} is {x.dtype} {shape}: PDP, as LeRobot's policies, takes float frames in "
                         f"[0, 1], channels first [..., {c}, {h}, {w}] ({fix})")
    if shape[-3:] == [h, w, c] and c != h:
        raise ValueError(f"camera {key!r} has shape {shape} (channels last); this policy expects [..., {c}, {h}, {w}] "
                         f"(channels first, as its training dataset's frames; {fix})")
    if shape[-3:] != [c, h, w]:
        size = f"{h}" if h == w else f"{h}x{w}"
        raise ValueError(f"camera {key!r} has shape {shape} (another size or channel count); this policy expects "
                         f"[..., {c}, {h}, {w}], its training dataset's frames (lerobot_pdp's envs: "
                         f"--env.image_size={size}; a robot's camera or a dataset: frames of that size)")
    if x.size == 0 if isinstance(x, np.ndarray) else x.numel() == 0:
        return
    lo, hi = map(float, torch.aminmax(torch.as_tensor(x)))  # one pass over the frames: also on every training batch
    if lo < -FRAME_RANGE_SLACK or hi > 1 + FRAME_RANGE_SLACK:
        raise ValueError(f"camera {key!r} holds values in [{lo:.3g}, {hi:.3g}]; camera frames are float in [0, 1] "
                         f"(0-255 values: divide by 255; {fix})")
