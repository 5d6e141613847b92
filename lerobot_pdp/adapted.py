"""Adapted checkpoints: a trained PDP adapted to one demonstration or to an outcome, kept as a checkpoint of its own.

``lerobot-pdp adapt CKPT --demo DATASET --out ADAPTED`` (:func:`adapt_checkpoint`) fits the latent (and, if
asked, one sampler noise per chunk) once, and writes ADAPTED whole: every file of CKPT (weights bit for bit,
config, processors, model card) plus the adaptation files of ``checkpoint.py``. Loading ADAPTED with
``PDPPolicy.from_pretrained``, ``lerobot-eval`` or ``lerobot-rollout --policy.path=ADAPTED`` acts adapted from
the first action, in any process, with no fit and no steering flag. ``lerobot-pdp search CKPT --env ... --out
ADAPTED`` (:func:`search_checkpoint`) writes the same files for a latent searched by outcome (success, reward or
way-points), without a demonstration.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import time
from pathlib import Path
from typing import Any

from .atomic import move_into_place, staging_dir
from .candidate_rollouts import EnvFactory
from .checkpoint import (
    ADAPTATION_INFO,
    ADAPTATION_TENSORS,
    CARD_HEADING,
    card_section,
    read_adaptation,
    write_adaptation,
)
from .checkpoint_files import read_config_json, require_checkpoint_files, require_new_folder
from .configuration_pdp import STEERING_FIELDS, PDPConfig
from .demonstration import Episode, check_recording_exists
from .latent_search import SearchResult
from .model_card import checkpoint_card
from .outcome_scores import Score

logger = logging.getLogger(__name__)



def adapt_checkpoint(base: str | Path, episode: Episode, out: str | Path, noise: str | None = None,
                     steps: int | None = None, lr: float | None = None, seed: int | None = 0,
                     device: str = "cpu") -> Path:
    """Fit ``base`` to one demonstration (``episode``: a ``(dataset folder, episode index)`` pair or arrays) and
    write the adapted checkpoint ``out`` (which must not exist); ``None`` settings take the checkpoint's
    ``fit_*`` defaults. An adapted ``base`` is fitted as its weights act: the new adaptation replaces its own
    (an adapted checkpoint shares its base's weights; one saved from Python after ``teach`` or received from
    elsewhere may name no base at hand). Returns ``out``."""
    base, out = Path(base), Path(out)
    _check_folders(base, out)
    check_recording_exists(episode)
    if (base / ADAPTATION_INFO).is_file():  # its weights are what is fitted; the new adaptation replaces its own
        logger.warning("%s carries an adaptation (%s): fitting its weights without it; %s gets the new adaptation "
                       "in its place", base, ADAPTATION_INFO, out)
    policy = load_base_policy(base, device)
    t0 = time.perf_counter()
    result = policy.fit_latent(episode, steps=steps, lr=lr, seed=seed, noise=noise, progress=True)
    logger.info("fitted in %.1f s: latent %s, error ratio %s", time.perf_counter() - t0, result.z.tolist(),
                "n/a" if result.error_ratio is None else f"{result.error_ratio:.2f}")
    policy.steering.provenance = {**policy.steering.provenance,  # a re-adapted checkpoint names the base it came from
                                  "base_checkpoint": _origin(base) or str(base.resolve())}
    write_adapted_checkpoint(base, policy, out, _card_section(policy.steering.provenance, result))
    return out


def search_checkpoint(base: str | Path, env_factory: EnvFactory, score: str | Score, out: str | Path | None = None,
                      init: Any = "modes", device: str = "cpu", provenance: dict | None = None,
                      **search: Any) -> SearchResult:
    """Search ``base``'s latent by outcome (:func:`lerobot_pdp.latent_search.search_latent`; ``search`` holds its
    settings) and, with ``out`` (which must not exist), write the best latent as an adapted checkpoint.

    ``init="adaptation"`` starts from the latent ``base`` carries (an adapted checkpoint, e.g. a fit); ``out`` is
    then written from ``base``'s files with the search in place of that adaptation. ``provenance`` adds to
    what ``adaptation.json`` records (e.g. the env and scene)."""
    base = Path(base)
    _check_folders(base, out)
    policy = load_base_policy(base, device)
    if isinstance(init, str) and init == "adaptation":
        carried = read_adaptation(base)
        if carried is None:
            raise ValueError(f"init 'adaptation': {base} carries no {ADAPTATION_TENSORS} (not an adapted checkpoint); "
                             "start from 'modes' or give a latent")
        init = carried[0]["latent"]
        init = init[0] if len(init) == 1 else init
        noises = len(carried[0].get("noise", ()))
        if noises:  # the search moves the latent alone; the fitted noises were fitted to the old one
            logger.warning("init 'adaptation': %s carries %d fitted chunk noises besides its latent; the search moves "
                           "the latent alone and scores it with drawn noises, and %s carries no chunk noises (adapt "
                           "it with --noise chunks again to fit them to the searched latent)", base, noises,
                           out if out is not None else "the result")
    if "processors" not in search and (base / "policy_preprocessor.json").is_file():  # as lerobot-eval loads them
        from lerobot.policies.factory import make_pre_post_processors

        search["processors"] = make_pre_post_processors(
            policy.config, pretrained_path=str(base), preprocessor_overrides={"device_processor": {"device": device}})
    result = policy.search_latent(env_factory, score, init=init, **search)
    logger.info("searched in %.0f s: latent %s, score %.3g, success %.0f %%", result.seconds, result.latent.tolist(),
                result.score, 100 * result.success)
    if out is not None:
        policy.steering.provenance = {**policy.steering.provenance, **(provenance or {}),
                                      "base_checkpoint": _origin(base) or str(base.resolve())}
        write_adapted_checkpoint(base, policy, Path(out), _search_card_section(policy.steering.provenance, result))
    return result


# the config fields load_base_policy sets for its load alone (a checkpoint written from that policy restores them)
LOAD_ONLY_FIELDS = ("device", "use_adaptation", *STEERING_FIELDS)


def load_base_policy(base: Path, device: str = "cpu") -> Any:
    """``base`` as its weights act, whatever adaptation or steering it carries, in eval mode (the config fields
    :data:`LOAD_ONLY_FIELDS` differ from the saved ones)."""
    from .modeling_pdp import PDPPolicy

    cfg = dataclasses.replace(PDPConfig.from_pretrained(base), device=device, use_adaptation=False, steer_latent=None,
                              steer_mode=None, steer_dataset_root=None, steer_episode_index=None, steer_file=None)
    policy = PDPPolicy.from_pretrained(base, config=cfg)
    policy.eval()
    return policy


def write_adapted_checkpoint(base: Path, policy: Any, out: Path, card_section: str) -> None:
    """``out`` whole or not at all: every file of ``base`` but its adaptation, then ``policy``'s active latent
    with its provenance, and ``card_section`` in place of any earlier one in the model card."""
    with staging_dir(out, prefix=".pdp-adapt-") as tmp:
        for f in base.iterdir():
            if f.name in (ADAPTATION_TENSORS, ADAPTATION_INFO):
                continue
            (shutil.copytree if f.is_dir() else shutil.copy2)(f, tmp / f.name)
        write_adaptation(policy.steering, tmp)
        _acting_adapted(tmp / "config.json", base)
        text = checkpoint_card(base)
        if (base / ADAPTATION_INFO).is_file():  # a re-adapted checkpoint: its earlier section goes
            text = text.split(f"\n{CARD_HEADING}\n")[0]
        (tmp / "README.md").write_text(text.rstrip() + "\n\n" + card_section)
        move_into_place(tmp, Path(out))


def _acting_adapted(config: Path, base: Path) -> None:
    """An adapted checkpoint acts under its adaptation: ``use_adaptation`` false in the base's config.json (as a
    taught checkpoint of an earlier release saved it) would load it silently unadapted, and the base's ``steer_*``
    fields (run at every load) would override it, or fit again to their recording."""
    cfg = read_config_json(config)
    steering = {f: cfg[f] for f in STEERING_FIELDS if cfg.get(f) is not None}
    if cfg.get("use_adaptation", True) is True and not steering:
        return
    if steering:
        logger.warning("%s's config.json steers it as it loads (%s): the adapted checkpoint is written without that, "
                       "to act under its adaptation", base, ", ".join(f"{k}={v!r}" for k, v in steering.items()))
    cfg.update(use_adaptation=True, **dict.fromkeys(steering))
    config.write_text(json.dumps(cfg, indent=4) + "\n")


def _check_folders(base: Path, out: str | Path | None) -> None:
    require_checkpoint_files(base)
    if out is not None:
        require_new_folder(out, "adapted", base)


def _origin(base: Path) -> str | None:
    """The base checkpoint an adapted checkpoint names, if it is one."""
    try:
        return json.loads((base / ADAPTATION_INFO).read_text()).get("base_checkpoint")
    except (OSError, ValueError, AttributeError):
        return None


def _card_section(provenance: dict, result) -> str:
    demo = provenance.get("demonstration", {})
    ratio = "n/a" if result.error_ratio is None else f"{result.error_ratio:.2f}"
    noises = "" if result.noise is None else f" and {len(result.noise)} sampler noises (one per chunk)"
    return card_section(f"This checkpoint is adapted to one demonstration (episode {demo.get('episode', '?')} of "
                        f"`{Path(str(demo.get('dataset', 'arrays'))).name}`): it acts under the fitted latent "
                        f"`{result.z.tolist()}`{noises} from its first action (fit error ratio {ratio}"
                        f"{'' if result.noise is None else ' of the latent alone'}, {provenance['date']}).")


def _search_card_section(provenance: dict, result: SearchResult) -> str:
    objective = provenance.get("objective")
    what = (f"passing {len(objective['waypoints'])} way-points in order within {objective['radius']:g} m"
            + (", then succeeding" if objective.get("finish") else "")
            if isinstance(objective, dict) and "waypoints" in objective else f"its score `{objective}`")
    where = "".join(f", {k} `{provenance[k]}`" for k in ("env", "scene") if k in provenance)
    return card_section(f"This checkpoint acts under a latent found by searching for an outcome, without a "
                        f"demonstration ({result.method}, {result.rollouts_used} rollouts"
                        f"{f' of {result.budget}: interrupted' if result.interrupted else ''}{where}): "
                        f"`{result.latent.tolist()}`, {what}: score {result.score:.3g}, success "
                        f"{100 * result.success:.0f} % of its rollouts ({provenance['date']}).")
