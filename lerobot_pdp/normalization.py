"""The policy's own copy of its dataset statistics, so that raw demonstrations handed to ``encode`` /
``fit_latent`` are normalised exactly as LeRobot's preprocessor normalises training batches.

The statistics are buffers (saved in the checkpoint, key names unchanged since the first release); the
maths is LeRobot's, through its public ``NormalizerProcessorStep`` / ``UnnormalizerProcessorStep``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from lerobot.configs import FeatureType
from lerobot.processor import (
    NormalizerProcessorStep,
    TransitionKey,
    UnnormalizerProcessorStep,
    create_transition,
)
from lerobot.utils.constants import ACTION
from torch import Tensor, nn

from .configuration_pdp import PDPConfig


class FeatureStats(nn.Module):
    """Normalisation statistics of the policy's state, environment-state, camera and action features.

    Camera statistics are per channel ([3, 1, 1]), as LeRobot computes them for images and videos.
    """

    STATS = ("min", "max", "mean", "std")

    def __init__(self, config: PDPConfig):
        super().__init__()
        self.config = config
        self.features = {k: ft for k, ft in {**config.input_features, **config.output_features}.items()
                         if ft.type in (FeatureType.STATE, FeatureType.ENV, FeatureType.ACTION, FeatureType.VISUAL)}
        for key, ft in self.features.items():
            shape = (ft.shape[0], 1, 1) if ft.type is FeatureType.VISUAL else tuple(ft.shape)
            for s in self.STATS:
                self.register_buffer(self._name(key, s), torch.zeros(shape) if s != "std" else torch.ones(shape))
        self.register_buffer("loaded", torch.tensor(False))
        self._steps: tuple[NormalizerProcessorStep, UnnormalizerProcessorStep] | None = None
        self._normalized: dict[tuple[str, int, float], float] = {}  # normalized_value's, per statistics

    @staticmethod
    def _name(key: str, stat: str) -> str:
        return f"{key.replace('.', '__')}__{stat}"

    def load(self, dataset_stats: dict[str, dict[str, Any]]) -> None:
        for key in self.features:
            if key not in dataset_stats:
                continue
            for s in self.STATS:
                if s in dataset_stats[key]:
                    buf = getattr(self, self._name(key, s))
                    value = torch.as_tensor(np.asarray(dataset_stats[key][s]), dtype=torch.float32)
                    if value.numel() != buf.numel():
                        raise ValueError(f"dataset statistics '{key}' {s} have shape {tuple(value.shape)}, "
                                         f"expected {tuple(buf.shape)}")
                    buf.copy_(value.reshape(buf.shape))
        self.loaded.fill_(True)
        self._steps, self._normalized = None, {}

    def as_dict(self) -> dict[str, dict[str, Tensor]]:
        return {k: {s: getattr(self, self._name(k, s)) for s in self.STATS} for k in self.features}

    def _load_from_state_dict(self, *args, **kwargs):
        self._steps, self._normalized = None, {}  # statistics change when a checkpoint is loaded
        super()._load_from_state_dict(*args, **kwargs)

    def _processor_steps(self) -> tuple[NormalizerProcessorStep, UnnormalizerProcessorStep]:
        """LeRobot's (un)normaliser over these statistics, built once (select_action may need it every step)."""
        if self._steps is None:
            if not bool(self.loaded):
                raise RuntimeError("the policy has no dataset statistics; build it with dataset_stats or load a "
                                   "checkpoint")
            kw = {"features": self.features, "norm_map": self.config.normalization_mapping,
                  "stats": {k: {s: v.cpu() for s, v in d.items()} for k, d in self.as_dict().items()}}
            self._steps = (NormalizerProcessorStep(**kw), UnnormalizerProcessorStep(**kw))
        return self._steps

    def normalize_episode(self, ep: dict[str, np.ndarray]) -> dict[str, Tensor]:
        """Normalised float32 tensors of raw episode arrays ([T, ...] by feature key)."""
        obs = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in ep.items() if k != ACTION}
        act = torch.as_tensor(ep[ACTION], dtype=torch.float32) if ACTION in ep else None
        out = self._processor_steps()[0](create_transition(observation=obs, action=act))
        result = dict(out[TransitionKey.OBSERVATION])
        if act is not None:
            result[ACTION] = out[TransitionKey.ACTION]
        return result

    def normalized_value(self, key: str, dim: int, raw: float) -> float:
        """``raw`` in dim ``dim`` of feature ``key``, normalised, computed once per statistics: the normalisation
        is increasing per dim, so a raw threshold compares with normalised values as this value does (a gripper
        command checked every control step without unnormalising the action)."""
        if (key, dim, raw) not in self._normalized:
            x = torch.zeros(1, self.features[key].shape[0])
            x[0, dim] = raw
            step = self._processor_steps()[0]
            out = step(create_transition(action=x))[TransitionKey.ACTION] if key == ACTION else \
                step(create_transition(observation={key: x}))[TransitionKey.OBSERVATION][key]
            self._normalized[(key, dim, raw)] = float(out[0, dim])
        return self._normalized[(key, dim, raw)]

    def unnormalize(self, key: str, x: Tensor) -> Tensor:
        """Raw values of the normalised ``x`` of feature ``key``, on ``x``'s device."""
        step = self._processor_steps()[1]
        if key == ACTION:
            return step(create_transition(action=x))[TransitionKey.ACTION]
        return step(create_transition(observation={key: x}))[TransitionKey.OBSERVATION][key]
