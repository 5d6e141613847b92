"""Pre/post-processors of PDP: LeRobot's standard pipelines (rename, batch, device, normalise / unnormalise).

PDP normalises like LeRobot's diffusion policy (min-max to [-1, 1] for states, env states and actions, mean-std
for cameras), so the DDIM sampler's clipping range [-1, 1] matches the action range. The policy keeps a copy of the same
statistics to normalise whole demonstrations in ``fit_latent``/``encode``.
"""

from __future__ import annotations

from typing import Any

import torch
from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

from .configuration_pdp import PDPConfig


def make_pdp_pre_post_processors(
    config: PDPConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[PolicyProcessorPipeline[dict[str, Any], dict[str, Any]], PolicyProcessorPipeline[PolicyAction, PolicyAction]]:
    """Return ``(preprocessor, postprocessor)`` for a PDP policy; saved next to its checkpoints."""
    return make_default_pre_post_processors(config, dataset_stats)
