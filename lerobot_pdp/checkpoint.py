"""A PDP checkpoint on disk: written whole, loaded into buffers sized by the checkpoint, first-release keys.

``PDPPolicy`` is LeRobot's ``PreTrainedPolicy``: ``save_pretrained`` / ``from_pretrained`` are LeRobot's. What
PDP adds: the weights are written into a temporary folder and moved in last (a crash never leaves a half
checkpoint); the behavior bank's buffers take the checkpoint's sizes before loading (their size is the
training set's); checkpoints keep the flat key names of the first release; a config saved before a field
existed gets that field's legacy default.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch
from huggingface_hub.constants import CONFIG_NAME, SAFETENSORS_SINGLE_FILE
from huggingface_hub.serialization import save_torch_state_dict
from safetensors.torch import save_model as save_model_as_safetensor
from torch import Tensor, nn

from .atomic import staging_dir
from .configuration_pdp import apply_legacy_defaults
from .pdp_model import BEHAVIOR_BUFFERS


def save_checkpoint(policy: Any, save_directory: str | Path, state_dict: dict[str, Tensor] | None = None) -> None:
    """Write ``policy``'s config + weights into a temporary folder next to ``save_directory``, then move them
    in, so a crash mid-write never leaves a half checkpoint (weights are moved last)."""
    save_directory = Path(save_directory)
    save_directory.mkdir(parents=True, exist_ok=True)
    try:
        with staging_dir(save_directory, prefix=".pdp-save-") as tmp:
            policy.config._save_pretrained(tmp)
            if state_dict is None:
                save_model_as_safetensor(policy, str(tmp / SAFETENSORS_SINGLE_FILE))
            else:
                save_torch_state_dict(state_dict, str(tmp), max_shard_size=10**12)
            names = sorted(p.name for p in tmp.iterdir())
            for name in sorted(names, key=lambda n: n.endswith(".safetensors")):
                os.replace(tmp / name, save_directory / name)
    finally:
        if not any(save_directory.iterdir()):
            save_directory.rmdir()


def resize_to_checkpoint(model: nn.Module, model_file: str) -> None:
    """Give the dataset-sized buffers of ``model`` (a ``PDPModel``) the shapes ``model_file`` holds."""
    from safetensors import safe_open

    with safe_open(model_file, framework="pt") as f:
        keys = set(f.keys())
        model.resize_behaviors({name: tuple(f.get_slice(name).get_shape()) for name in BEHAVIOR_BUFFERS if name in keys})


def apply_saved_config(policy: Any, model_file: str) -> None:
    """Legacy defaults for the fields a checkpoint's config.json predates (it lies beside the weights: a local
    folder, or the hub snapshot the config came from); the sampler is rebuilt when they changed it."""
    saved = Path(model_file).with_name(CONFIG_NAME)
    if saved.is_file() and apply_legacy_defaults(policy.config, json.loads(saved.read_text())):
        policy.model.set_sampler(policy.config.timestep_spacing, policy.config.use_clipped_model_output)


def flatten_model_keys(module: nn.Module, state_dict: dict[str, Tensor], prefix: str, local_metadata) -> None:
    """``model.vae.x`` -> ``vae.x``: the checkpoint keys of the first release, before the model module."""
    for key in [k for k in state_dict if k.startswith(prefix + "model.")]:
        state_dict[prefix + key[len(prefix) + len("model."):]] = state_dict.pop(key)


def nest_model_keys(module: nn.Module, state_dict: dict[str, Tensor], prefix: str, *args) -> None:
    """The inverse of :func:`flatten_model_keys` when a checkpoint is loaded."""
    for key in [k for k in state_dict if k.startswith(prefix) and not k.startswith((prefix + "stats.", prefix + "model."))]:
        state_dict[prefix + "model." + key[len(prefix):]] = state_dict.pop(key)
    # saved before the training error was tracked: no reference (FitResult.error_ratio stays None), no warning
    state_dict.setdefault(prefix + "model.train_loss_dp", torch.tensor(float("nan")))
