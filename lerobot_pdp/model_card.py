"""The model card of a PDP checkpoint: LeRobot's own card (same template and context) plus what PDP is and
how to steer it. Unlike LeRobot's base class it validates the card against the Hub only when online, so
cards can be written and tested with ``HF_HUB_OFFLINE=1``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

MODEL_CARD_PDP = """

## Parameterized Diffusion Policy (PDP)

This checkpoint is a **Parameterized Diffusion Policy**: a diffusion policy whose denoiser is FiLM-modulated
by a low-dimensional *behavior latent* `z`. A trajectory VAE trained with a soft-DTW geometry loss makes
distances in `z` match distances between demonstrated trajectories, so `z` is a steering handle.

```python
from lerobot_pdp import PDPPolicy
policy = PDPPolicy.from_pretrained("<this repo or folder>")
policy.mode_latents()                      # per-mode mean latents of the training demonstrations
policy.set_latent(policy.mode_latents()[3]) # act like mode 3
policy.fit_latent((dataset, episode_index)) # adapt to ONE new demonstration: fits z only, weights frozen
```

From the command line: `lerobot-eval --policy.path=<this> --policy.steer_mode=3 ...`, or
`--policy.steer_dataset_root=DIR --policy.steer_episode_index=0` to fit `z` to a demonstration at start-up.
The same flags work with `lerobot-rollout` on a robot; add `--policy.steer_file=FILE` to change `z` while it
runs (`lerobot-pdp steer FILE --mode 3`, `--latent ..`, or `--dataset DIR` to fit a new recording), and
`--inference.type=rtc --inference.queue_threshold=7 --inference.rtc.execution_horizon=3` to generate chunks in the
background while the robot keeps its rate (check a task under it first: docs/deploy.md).
Requires `pip install lerobot_policy_pdp`.
"""


def pdp_model_card(config: Any, dataset_repo_id: str, model_type: str, license: str | None,
                   tags: list[str] | None, cfg: Any = None, dataset_meta: Any = None):
    """``huggingface_hub.ModelCard`` for a policy with ``config`` trained on ``dataset_repo_id``."""
    from importlib.resources import files

    from huggingface_hub import ModelCard, ModelCardData
    from huggingface_hub.constants import HF_HUB_OFFLINE
    from lerobot.policies.pretrained import _build_card_context

    card_data = ModelCardData(
        license=license or "apache-2.0", library_name="lerobot", pipeline_tag="robotics",
        tags=sorted(set(tags or []) | {"robotics", "lerobot", model_type, "parameterized-diffusion-policy"}),
        model_name=model_type, datasets=dataset_repo_id,
    )
    # LeRobot's context builder is private; it is what keeps the card identical to LeRobot's own policies'
    context = _build_card_context(cfg, dataset_meta, config.input_features, config.output_features)
    context["policy_repo_id"] = getattr(config, "repo_id", None)
    context["base_model"] = None
    template = files("lerobot.templates").joinpath("lerobot_modelcard_template.md").read_text(encoding="utf-8")
    card = ModelCard.from_template(card_data, template_str=template, **context)
    card.text = card.text + MODEL_CARD_PDP
    if not HF_HUB_OFFLINE:
        card.validate()
    return card


def checkpoint_card(folder: Path, config: Any = None) -> str:
    """The model card of checkpoint ``folder``: its README.md, else (a local ``lerobot-train`` checkpoint has none:
    LeRobot writes the card when it pushes) PDP's card from ``config`` (default: the folder's) and the dataset its
    train_config.json names, so that an adapted or taught checkpoint always carries one."""
    card = Path(folder) / "README.md"
    if card.is_file():
        return card.read_text()
    if config is None:
        from .configuration_pdp import PDPConfig

        config = PDPConfig.from_pretrained(folder)
    repo_id = "unknown"
    try:
        repo_id = json.loads((Path(folder) / "train_config.json").read_text())["dataset"]["repo_id"] or repo_id
    except (OSError, ValueError, KeyError, TypeError):
        pass  # no train_config.json (a checkpoint saved from Python): the card names no dataset
    return str(pdp_model_card(config, repo_id, config.type, getattr(config, "license", None),
                              getattr(config, "tags", None)))
