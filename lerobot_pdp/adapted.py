"""Adapted checkpoints: a trained PDP adapted to one demonstration, kept as a checkpoint of its own.

``lerobot-pdp adapt CKPT --demo DATASET --out ADAPTED`` (:func:`adapt_checkpoint`) fits the latent (and, if
asked, one sampler noise per chunk) once, and writes ADAPTED whole: every file of CKPT (weights bit for bit,
config, processors, model card) plus the adaptation files of ``checkpoint.py``. Loading ADAPTED with
``PDPPolicy.from_pretrained``, ``lerobot-eval`` or ``lerobot-rollout --policy.path=ADAPTED`` acts adapted from
the first action, in any process, with no fit and no steering flag.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
import time
from pathlib import Path

from .atomic import staging_dir
from .checkpoint import ADAPTATION_INFO, ADAPTATION_TENSORS, write_adaptation
from .configuration_pdp import PDPConfig
from .demonstration import Episode

logger = logging.getLogger(__name__)


def adapt_checkpoint(base: str | Path, episode: Episode, out: str | Path, noise: str | None = None,
                     steps: int | None = None, lr: float | None = None, seed: int | None = 0,
                     device: str = "cpu") -> Path:
    """Fit ``base`` to one demonstration (``episode``: a ``(dataset folder, episode index)`` pair or arrays) and
    write the adapted checkpoint ``out`` (which must not exist); ``None`` settings take the checkpoint's
    ``fit_*`` defaults. Returns ``out``."""
    from .modeling_pdp import PDPPolicy

    base, out = Path(base), Path(out)
    if not (base / "model.safetensors").is_file() or not (base / "config.json").is_file():
        raise FileNotFoundError(f"{base} is not a PDP checkpoint folder (config.json + model.safetensors)")
    if out.exists():
        raise FileExistsError(f"{out} exists: give a new folder for the adapted checkpoint")
    if (base / ADAPTATION_INFO).is_file():  # its card and provenance would describe two adaptations
        try:
            origin = json.loads((base / ADAPTATION_INFO).read_text()).get("base_checkpoint")
        except ValueError:
            origin = None
        raise ValueError(f"{base} is already an adapted checkpoint ({ADAPTATION_INFO}): adapt its base checkpoint "
                         f"{origin or '(named in that file)'} instead")
    # fitted from the base behaviour, whatever adaptation or steering the base checkpoint carries
    cfg = dataclasses.replace(PDPConfig.from_pretrained(base), device=device, use_adaptation=False, steer_latent=None,
                              steer_mode=None, steer_dataset_root=None, steer_episode_index=None, steer_file=None)
    policy = PDPPolicy.from_pretrained(base, config=cfg)
    policy.eval()
    t0 = time.perf_counter()
    result = policy.fit_latent(episode, steps=steps, lr=lr, seed=seed, noise=noise, progress=True)
    logger.info("fitted in %.1f s: latent %s, error ratio %s", time.perf_counter() - t0, result.z.tolist(),
                "n/a" if result.error_ratio is None else f"{result.error_ratio:.2f}")
    policy.steering.provenance = {**policy.steering.provenance, "base_checkpoint": str(base.resolve())}
    with staging_dir(out, prefix=".pdp-adapt-") as tmp:
        for f in base.iterdir():
            if f.name in (ADAPTATION_TENSORS, ADAPTATION_INFO):
                continue
            (shutil.copytree if f.is_dir() else shutil.copy2)(f, tmp / f.name)
        write_adaptation(policy.steering, tmp)
        card = tmp / "README.md"
        if card.is_file():
            card.write_text(card.read_text().rstrip() + "\n\n" + _card_section(policy.steering.provenance, result))
        os.replace(tmp, out)
    return out


def _card_section(provenance: dict, result) -> str:
    demo = provenance.get("demonstration", {})
    ratio = "n/a" if result.error_ratio is None else f"{result.error_ratio:.2f}"
    noises = "" if result.noise is None else f" and {len(result.noise)} sampler noises (one per chunk)"
    return (f"## Adaptation\n\nThis checkpoint is adapted to one demonstration (episode {demo.get('episode', '?')} of "
            f"`{Path(str(demo.get('dataset', 'arrays'))).name}`): it acts under the fitted latent "
            f"`{result.z.tolist()}`{noises} from its first action (fit error ratio {ratio}, {provenance['date']}). "
            f"Weights are the base checkpoint's; `{ADAPTATION_INFO}` holds the provenance. "
            "`--policy.use_adaptation=false` (or `policy.set_latent(None)`) acts as the base.\n")
