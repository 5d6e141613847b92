"""Pre/post-processors of PDP: LeRobot's standard pipelines (rename, batch, device, normalise / unnormalise).

PDP normalises like LeRobot's diffusion policy (min-max to [-1, 1] for states, env states and actions, mean-std
for cameras), so the DDIM sampler's clipping range [-1, 1] matches the action range. The policy keeps a copy of the same
statistics to normalise whole demonstrations in ``fit_latent``/``encode``.
"""

from __future__ import annotations

import logging
from typing import Any

import torch
from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

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
    return make_default_pre_post_processors(config, dataset_stats)
