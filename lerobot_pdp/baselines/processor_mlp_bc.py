"""Pre/post-processors of the MLP-BC baseline: LeRobot's standard pipelines, as for PDP and DP.

LeRobot resolves ``make_mlp_bc_pre_post_processors`` in this module by naming convention
(``configuration_mlp_bc`` -> ``processor_mlp_bc``).
"""

from __future__ import annotations

from typing import Any

import torch
from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

from .configuration_mlp_bc import MLPBCConfig


def make_mlp_bc_pre_post_processors(
    config: MLPBCConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[PolicyProcessorPipeline[dict[str, Any], dict[str, Any]], PolicyProcessorPipeline[PolicyAction, PolicyAction]]:
    """Return ``(preprocessor, postprocessor)``: rename, batch, device, normalise / unnormalise, to CPU."""
    return make_default_pre_post_processors(config, dataset_stats)
