"""The PDP explorer as a Hugging Face Space (Gradio SDK), or locally with ``python app.py``.

The same app as ``lerobot-pdp explore``, configured by environment variables (a Space's variables):

    PDP_CHECKPOINT  a local pretrained_model folder, or a Hub model repo id (downloaded)   required
    PDP_ENV         suite env to roll out in (reach-around, avoiding, ...); unset: no rollouts
    PDP_SCENE       scene index 0-3, a validation scene or a scene file (default 0)
    PDP_ROLLOUTS    rollouts per selected latent (default 8)
    PDP_DATASET     a LeRobotDataset folder for demonstrations and the decoder's view

A Space holds this file as ``app.py`` and a ``requirements.txt`` naming ``lerobot_policy_pdp[explore]`` (and,
for rollouts, ``lerobot_env_pdp``). Locally:

    PDP_CHECKPOINT=runs/pdp/checkpoints/last/pretrained_model PDP_ENV=reach-around \
        PDP_SCENE=3 python examples/explorer/app.py
"""

from __future__ import annotations

import os
from pathlib import Path

from lerobot_pdp.explorer import Explorer
from lerobot_pdp.explorer_app import build_app


def checkpoint_folder(source: str) -> Path:
    """A local folder as is; a Hub model repo id downloaded (cached) once; anything else named."""
    if Path(source).is_dir():
        return Path(source)
    from huggingface_hub import snapshot_download
    from huggingface_hub.errors import HFValidationError
    from huggingface_hub.utils import validate_repo_id

    try:
        validate_repo_id(source)
    except HFValidationError:
        raise SystemExit(f"PDP_CHECKPOINT={source}: no such folder, and not a Hub repo id (user/name)") from None
    return Path(snapshot_download(source))


def rollouts() -> int:
    value = os.environ.get("PDP_ROLLOUTS", "8")
    if not value.strip().isdigit():
        raise SystemExit(f"PDP_ROLLOUTS={value}: give a whole number of rollouts per selected latent (default 8)")
    return int(value)


def make_app(checkpoint: str | None = None):
    source = checkpoint or os.environ.get("PDP_CHECKPOINT")
    if not source:
        raise SystemExit("set PDP_CHECKPOINT to a PDP checkpoint folder or Hub repo id")
    explorer = Explorer(checkpoint_folder(source), env=os.environ.get("PDP_ENV") or None,
                        scene=os.environ.get("PDP_SCENE", "0"), rollouts=rollouts(),
                        dataset=os.environ.get("PDP_DATASET") or None)
    return build_app(explorer)


demo = make_app()  # a Space serves the module's `demo`

if __name__ == "__main__":
    demo.launch()
