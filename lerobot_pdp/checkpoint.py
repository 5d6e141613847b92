"""A PDP checkpoint on disk: written whole, loaded into buffers sized by the checkpoint, first-release keys,
and the adaptation an adapted checkpoint carries.

``PDPPolicy`` is LeRobot's ``PreTrainedPolicy``: ``save_pretrained`` / ``from_pretrained`` are LeRobot's. What
PDP adds: the weights are written into a temporary folder and moved in last (a crash never leaves a half
checkpoint); the behavior bank's buffers take the checkpoint's sizes before loading (their size is the
training set's); checkpoints keep the flat key names of the first release; a config saved before a field
existed gets that field's legacy default.

An *adapted* checkpoint is a base checkpoint (weights unchanged, bit for bit) plus two small files: the
active latent (one per phase) and chunk noises in ``adaptation.safetensors``, and where they came from in
``adaptation.json`` (the demonstration, the fit settings, the fit error and its ratio to the training error,
the date). Loading it makes the policy act adapted from the first action.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from huggingface_hub.constants import CONFIG_NAME, SAFETENSORS_SINGLE_FILE
from huggingface_hub.serialization import save_torch_state_dict
from lerobot.configs.types import NormalizationMode
from safetensors.torch import save_model as save_model_as_safetensor
from torch import Tensor, nn

from .atomic import staging_dir, write_text_atomic
from .behavior_bank import CHECKPOINT_KEYS, TAUGHT_KEY
from .checkpoint_files import (
    PROCESSOR_FILES,
    PROCESSOR_PREFIXES,
    damaged_weights,
    optional_checkpoint_file,
    read_config_json,
    read_weight_shapes,
)
from .configuration_pdp import STEERING_FIELDS, apply_legacy_defaults
from .console import latent_text
from .lerobot_command import given_policy_fields
from .taught_demos import TAUGHT_DEMOS, TEACHING_INFO, write_taught_demos, write_teachings

logger = logging.getLogger(__name__)

ADAPTATION_TENSORS = "adaptation.safetensors"
ADAPTATION_INFO = "adaptation.json"
CARD_HEADING = "## Adaptation"  # the model card's section on the adaptation, replaced when it changes


def save_checkpoint(policy: Any, save_directory: str | Path, state_dict: dict[str, Tensor] | None = None) -> None:
    """Write ``policy``'s config + weights (+ its active adaptation, its taught demonstrations and their teaching
    records, if any) into a temporary folder next to ``save_directory``, then move them in. A new (or empty) folder
    is the staging folder renamed: a crash leaves no checkpoint or a whole one. Into an existing checkpoint the
    files move one by one, weights last: each file is whole, but a crash between two moves leaves new files beside
    old ones. A folder reused for a policy without an adaptation (or taught modes) loses its stale files, and its
    model card's adaptation section is rewritten for the adaptation saved (:func:`refresh_card`)."""
    save_directory = Path(save_directory)
    made = not save_directory.exists()
    save_directory.mkdir(parents=True, exist_ok=True)
    fresh = not any(save_directory.iterdir())
    try:
        with staging_dir(save_directory, prefix=".pdp-save-") as tmp:
            saved_config(policy)._save_pretrained(tmp)
            if state_dict is None:
                save_model_as_safetensor(policy, str(tmp / SAFETENSORS_SINGLE_FILE))
            else:
                save_torch_state_dict(state_dict, str(tmp), max_shard_size=10**12)
            adapted = write_adaptation(policy.steering, tmp)
            taught = write_taught_demos(policy.model.bank, set(policy.config.image_features), tmp)
            recorded = write_teachings(policy.model.bank, tmp)
            write_processors(policy, tmp, save_directory)
            if fresh:
                os.replace(tmp, save_directory)  # onto an empty folder: one rename
                return
            names = sorted(p.name for p in tmp.iterdir())
            for name in sorted(names, key=lambda n: n.endswith(".safetensors")):
                os.replace(tmp / name, save_directory / name)
            if not adapted:  # only once the new checkpoint is in place: a failed save keeps the old one whole
                for name in (ADAPTATION_TENSORS, ADAPTATION_INFO):
                    (save_directory / name).unlink(missing_ok=True)
            if not taught:
                (save_directory / TAUGHT_DEMOS).unlink(missing_ok=True)
            if not recorded:
                (save_directory / TEACHING_INFO).unlink(missing_ok=True)
            refresh_card(save_directory, policy.steering if adapted else None)
    finally:  # a failed save into a folder it made leaves none (a folder the caller had stays)
        if made and save_directory.exists() and not any(save_directory.iterdir()):
            save_directory.rmdir()


def saved_config(policy: Any) -> Any:
    """The config a checkpoint of ``policy`` is written with. A policy acting under a steering state saves that state
    as its adaptation, so the ``steer_*`` fields that set it are not saved with it: every load would run them again
    over the adaptation (a fit to a recording by a path relative to wherever it ran, a mode over a fitted latent);
    and ``use_adaptation`` is true, so the adaptation acts. Otherwise (a training run's flags) the config as it is."""
    cfg = policy.config
    if not policy.steering.active:
        return cfg
    spent = {f: None for f in STEERING_FIELDS if getattr(cfg, f) is not None}
    if not spent and cfg.use_adaptation:
        return cfg
    if spent:
        logger.info("saved with the active latent as its adaptation, without %s (run at load, they would redo or "
                    "override it)", ", ".join(f"{f}={getattr(cfg, f)!r}" for f in spent))
    return dataclasses.replace(cfg, **spent, use_adaptation=True)


def write_processors(policy: Any, tmp: Path, save_directory: Path) -> None:
    """LeRobot's processor files beside the weights, so that a folder saved from Python (an adapted or taught
    policy) is a checkpoint ``lerobot-eval`` / ``lerobot-rollout`` load: the ones of the checkpoint the policy was
    loaded from, else built from the policy's statistics (as ``lerobot-train`` builds them). A folder holding some
    keeps its own, and ``lerobot-train`` writes its own after the weights."""
    if any((save_directory / name).is_file() for name in PROCESSOR_FILES):
        return
    source = getattr(policy, "_loaded_from", None)
    if source is not None and all((source / name).is_file() for name in PROCESSOR_FILES):
        for f in source.iterdir():
            if f.is_file() and f.name.startswith(PROCESSOR_PREFIXES):
                shutil.copy2(f, tmp / f.name)
    elif bool(policy.stats.loaded):
        from .processor_pdp import make_pdp_pre_post_processors

        stats = {k: {s: v.cpu() for s, v in d.items()} for k, d in policy.stats.as_dict().items()}
        for pipeline in make_pdp_pre_post_processors(policy.config, stats):
            pipeline.save_pretrained(tmp)


def refresh_card(folder: Path, steering: Any) -> None:
    """A model card (``README.md``) with an adaptation section describes the adaptation now saved in ``folder``
    (``steering``; None: none), so a card never names a latent the checkpoint no longer acts under."""
    card = folder / "README.md"
    if not card.is_file():
        return
    text = card.read_text()
    if f"\n{CARD_HEADING}\n" not in text:
        return
    text = text.split(f"\n{CARD_HEADING}\n")[0].rstrip() + "\n"
    if steering is not None:
        noises = len(steering.noises.noise)
        source = (steering.provenance or {}).get("source", "set_latent")
        text += "\n" + card_section(f"This checkpoint acts under the latent `{steering.latent.tolist()}`"
                                    f"{f' and {noises} sampler noises (one per chunk)' if noises else ''} from its "
                                    f"first action, saved from Python ({source}).")
    write_text_atomic(card, text)


def card_section(what: str) -> str:
    """The model card's adaptation section: ``what`` the checkpoint acts under, and what every adapted one shares."""
    return (f"{CARD_HEADING}\n\n{what} Weights are the base checkpoint's; `{ADAPTATION_INFO}` holds the provenance. "
            "`--policy.use_adaptation=false` (or `policy.set_latent(None)`) acts as the base.\n")


def load_weights(policy: Any, model_file: str, load: Callable[[Any], Any]) -> Any:
    """LeRobot's load of ``model_file`` into ``policy`` (``load(policy)``), with PDP's steps around it: the
    behavior bank's buffers take the checkpoint's sizes, the weights must fit the config and be finite, and a
    config saved before a field existed gets that field's legacy default (and the sampler it implies)."""
    from safetensors import SafetensorError

    shapes = read_weight_shapes(model_file)  # a damaged file: an error naming it
    bank = policy.model.bank
    read = bank.snapshot() if len(bank.episode) else None  # the training dataset's, read by lerobot-train
    built_stats = _training_stats(policy) if read is not None else None
    resize_to_checkpoint(policy.model, shapes)
    check_weight_shapes(policy, model_file, shapes)  # e.g. latent_dim edited in config.json
    try:
        policy = load(policy)
    except SafetensorError as e:
        raise damaged_weights(model_file, e) from e
    check_finite_weights(policy, model_file)
    policy._loaded_from = Path(model_file).parent  # its processors go with a folder it is saved to
    apply_saved_config(policy, model_file)
    apply_training_stats(policy, built_stats, model_file)
    if read is not None:
        keep_training_behaviors(policy, read, model_file)
    return policy


# how far (a share of the old min-max range) a resumed run's data may reach past the checkpoint's statistics unsaid:
# a grown dataset's few percent are within what the networks extrapolate; a new region of the workspace is not
RESUME_RANGE_TOLERANCE = 0.05


def _training_stats(policy: Any) -> tuple[dict[str, dict[str, Tensor]], bool] | None:
    """Under lerobot-train, the dataset statistics the policy was built with and whether this run resumes
    (``--resume``); None elsewhere or without statistics."""
    import sys

    from .lerobot_command import running_lerobot_train, train_value

    if not bool(policy.stats.loaded) or not running_lerobot_train(sys.argv):
        return None
    resume = train_value(sys.argv, "--resume", ("resume",)) is True  # the command line's, else its config file's
    return {k: {s: v.detach().clone() for s, v in d.items()} for k, d in policy.stats.as_dict().items()}, resume


def apply_training_stats(policy: Any, built: tuple[dict[str, dict[str, Tensor]], bool] | None, model_file: str) -> None:
    """Fine-tuning (``--policy.path``): LeRobot's processors normalise every batch with the dataset's statistics,
    so the policy's own copy (fit_latent, teach, taught rehearsal, phases) takes them too. Resuming: LeRobot keeps
    the checkpoint's processors, so its statistics stay; a dataset that reaches past their min/max is warned of,
    since the sampler clips actions to that range (clip_sample) and such actions can never be produced."""
    if built is None:
        return
    stats, resume = built
    if not resume:
        policy.stats.load(stats)
        return
    saved = policy.stats.as_dict()
    wider = []
    for key, ft in policy.stats.features.items():
        if policy.config.normalization_mapping.get(ft.type.value) is not NormalizationMode.MIN_MAX or key not in stats:
            continue
        lo, hi = saved[key]["min"].cpu(), saved[key]["max"].cpu()
        span = (hi - lo).clamp_min(1e-8)
        out = torch.maximum((lo - stats[key]["min"].cpu()) / span, (stats[key]["max"].cpu() - hi) / span).max()
        if float(out) > RESUME_RANGE_TOLERANCE:
            wider.append(f"{key} by up to {float(out):.0%} of its range")
    if wider:
        logger.warning("resuming %s on a dataset whose values reach past the checkpoint's normalisation statistics "
                       "(min/max), which a resumed run keeps: %s. Actions beyond them can never be sampled (clip_sample "
                       "clips to the old range), observations beyond them are ones the networks never saw; to train "
                       "on the new range, start from the checkpoint with --policy.path instead of --resume",
                       model_file, "; ".join(wider))


def keep_training_behaviors(policy: Any, read: dict[str, Tensor], model_file: str) -> None:
    """A checkpoint loaded to train on (lerobot-train ``--policy.path`` or ``--resume``) over a dataset whose
    behaviours differ from the ones the checkpoint's bank holds (another dataset, a grown one, other episodes, or
    taught modes): training goes on with the dataset's, ``read`` when the policy was built, so that every training
    window is conditioned on its own episode's latent; the checkpoint's bank would give each a stranger's, or fail at
    the first episode it lacks. Its taught modes are kept and rehearsed (:func:`keep_taught_behaviors`) where their
    ids stay free. Said in a warning, with what changes (its mode latents, taught modes)."""
    bank = policy.model.bank
    loaded = bank.snapshot()
    if bank.same_behaviors(loaded, read):
        # the same behaviours, but this run's sdtw_gamma / sdtw_normalize / geo_kappa may give other distances
        if loaded["distances"].shape != read["distances"].shape or not (
                torch.allclose(loaded["distances"], read["distances"], rtol=1e-4, atol=1e-6)
                and torch.allclose(loaded["kappa"], read["kappa"], rtol=1e-5)):
            logger.info("%s: the behaviours are the same, their soft-DTW distances / kappa follow this run's config "
                        "(kappa %.4g -> %.4g)", model_file, float(loaded["kappa"]), float(read["kappa"]))
            bank.distances, bank.kappa = read["distances"], read["kappa"]
        return
    n_taught = loaded["taught"].shape[0]
    trained = {k: v[: len(v) - n_taught] for k, v in loaded.items() if k in ("episode", "start", "end", "global_start",
                                                                            "mode", "traces")}
    same = bank.same_behaviors(trained, read)
    taught = ""
    if n_taught:  # lerobot-train samples the dataset alone: the taught modes' demonstrations join its batches
        names = _saved_mode_names(model_file)
        text = _taught_modes_text(loaded["mode"][-n_taught:], names)
        why = ("with taught_rehearsal_share=0 lerobot-train does not rehearse them"
               if policy.config.taught_rehearsal_share == 0 else
               None if same else _taught_ids_taken(policy, read, int(loaded["mode"][-n_taught:].min())))
        if why is None:
            if not same:
                _carry_taught(bank, loaded, read, names)
            keep_taught_behaviors(policy, len(read["episode"]), names)
            if same:
                return
            taught = f"; its taught {text} join them, rehearsed in every batch"
        else:
            again = (f"teach them to the trained checkpoint again from the demonstrations {Path(model_file).parent} "
                     f"keeps: lerobot-pdp teach <trained checkpoint> --taught-from {Path(model_file).parent} --out "
                     "<folder>")
            if same:
                logger.warning("%s was taught %s; %s: they are dropped, and the trained policy holds this dataset's "
                               "behaviours; %s", model_file, text, why, again)
                bank.restore(read)
                return
            taught = f"; its taught {text} are dropped ({why}; {again})"
            bank.restore(read)
    else:
        bank.restore(read)
    logger.warning("%s holds the behaviours of other data (%d episode(s), %d behaviours) than the dataset this "
                   "policy trains on (%d episode(s), %d behaviours): training goes on with this dataset's behaviour "
                   "bank (its traces, modes and soft-DTW distances), so mode latents now describe this dataset%s",
                   model_file, len(trained["episode"].unique()), len(trained["episode"]), len(read["episode"].unique()),
                   len(read["episode"]), taught)


def _taught_ids_taken(policy: Any, read: dict[str, Tensor], first_taught: int) -> str | None:
    """Why the dataset's own modes (``read``) would take the taught modes' ids (the first is ``first_taught``), or
    None when they stay below it: its mode labels, or without labels the clusters ``mode_latents()`` will discover
    in it (clustered by soft-DTW divergences, which training does not change)."""
    modes = read["mode"]
    if bool((modes >= 0).all()):
        top = int(modes.max())
        return None if top < first_taught else f"this dataset's mode labels reach {top}, which takes their ids"
    bank = policy.model.bank
    bank.restore(read)
    try:
        k = bank.discover_modes(policy.model.vae).k
    except ValueError as e:
        return f"this dataset has no mode labels, and its modes could not be discovered ({e})"
    return None if k <= first_taught else (f"this dataset has no mode labels, and the {k} clusters discovered in it "
                                           f"take ids up to {k - 1}, theirs among them")


def _carry_taught(bank: Any, loaded: dict[str, Tensor], read: dict[str, Tensor], names: dict[str, str]) -> None:
    """The dataset's behaviours (``read``), then the loaded bank's taught ones appended in order under their ids,
    latents and names (their soft-DTW distances to this dataset's computed); the dataset's modes stay below their
    ids (:func:`_taught_ids_taken`)."""
    first = len(loaded["mode"]) - len(loaded["taught"])
    bank.restore(read)
    for mode in sorted(set(loaded["mode"][first:].tolist())):
        rows = torch.nonzero(loaded["mode"] == mode).flatten()  # one per phase, in order
        segments = list(zip(loaded["start"][rows].tolist(), loaded["end"][rows].tolist(), strict=True))
        bank.append(loaded["traces"][rows].cpu().numpy(), segments, names.get(str(mode), f"taught mode {mode}"),
                    loaded["taught"][rows - first], mode)


def keep_taught_behaviors(policy: Any, n_trained: int, names: dict[str, str]) -> None:
    """Training goes on with the bank's taught behaviours (the rows past ``n_trained``) kept under the names the
    checkpoint's config.json gives them (``names``: the dataset named the others), and L_embed trains on the
    dataset's behaviours alone; their demonstrations are rehearsed in every batch once read
    (:func:`lerobot_pdp.taught_rehearsal.rehearse_taught_modes`)."""
    bank, cfg = policy.model.bank, policy.config
    taught = {str(m) for m in bank.taught_modes()}
    cfg.mode_names = {**(cfg.mode_names or {}), **{m: n for m, n in names.items() if m in taught}}
    if not len(bank.embed_pool):  # all behaviours: now the dataset's, not the taught ones
        bank.embed_pool = torch.arange(n_trained, device=bank.episode.device)
    bank.taught_in_training = True


def _saved_mode_names(model_file: str) -> dict[str, str]:
    """The ``mode_names`` of the config.json beside ``model_file`` (none when it is absent or damaged: a damaged
    config.json was reported where it was read)."""
    saved = Path(model_file).with_name(CONFIG_NAME)
    try:
        return (read_config_json(saved).get("mode_names") or {}) if saved.is_file() else {}
    except ValueError:
        return {}


def _taught_modes_text(modes: Tensor, names: dict[str, str]) -> str:
    """"mode(s) 4 ('around the crate')": the taught modes, named as the checkpoint's config.json names them."""
    ids = sorted({int(m) for m in modes.tolist()})
    return "mode(s) " + ", ".join(f"{m} ({names[str(m)]!r})" if str(m) in names else str(m) for m in ids)


def check_weight_shapes(policy: Any, model_file: str, shapes: dict[str, tuple[int, ...]]) -> None:
    """Weights that do not fit the model config.json builds: an error naming the config field where it can be
    told from the weights (latent_dim, vae_hidden_dims), else the first mismatched tensors."""
    built = {k: tuple(v.shape) for k, v in policy.state_dict().items()}
    wrong = [(k, shapes[k], built[k]) for k in built if k in shapes and shapes[k] != built[k]]
    if not wrong:
        return
    cfg, where = policy.config, Path(model_file).with_name(CONFIG_NAME)
    other = _other_features(cfg, where)
    if other:  # features from --env.type (lerobot-eval), the robot (lerobot-rollout) or the data (lerobot-train)
        raise ValueError(f"{model_file} was trained on other inputs or outputs than this run gives it: {other}. Is "
                         "this the env (--env.type, --env.*), robot or dataset (--dataset.*: fine-tuning) the policy "
                         f"was trained on? Its features are in {where}")
    changed = _changed_on_command_line(cfg, where)
    if changed:  # --policy.<field>=... over a checkpoint: the networks built differ from the weights
        raise ValueError(f"{', '.join(changed)} given on the command line change the networks' shapes, but the weights "
                         f"of {model_file} were trained with the values in {where}; a checkpoint's network sizes cannot "
                         "change when it is loaded: drop the flag(s), or train a new policy with them")
    encoder = sorted((int(k.split(".")[2]), v) for k, v in shapes.items()
                     if k.startswith("vae.encoder.") and k.endswith(".weight"))
    fields = []
    if encoder:
        if encoder[-1][1][0] // 2 != cfg.latent_dim:
            fields.append(f"latent_dim is {encoder[-1][1][0] // 2} in the weights, {cfg.latent_dim} in {where}")
        hidden = tuple(v[0] for _, v in encoder[:-1])
        if hidden != tuple(cfg.vae_hidden_dims):
            fields.append(f"vae_hidden_dims is {hidden} in the weights, {tuple(cfg.vae_hidden_dims)} in {where}")
    tensors = "; ".join(f"'{k}' is {a} in the weights, {b} as configured" for k, a, b in wrong[:3])
    raise ValueError(f"{model_file} does not match its config: {'; '.join(fields) or tensors}"
                     f"{f' ({tensors})' if fields else ''}. Was {CONFIG_NAME} edited? Use the config.json saved "
                     "with these weights")


def _changed_on_command_line(cfg: Any, saved_config: Path) -> list[str]:
    """``--policy.<field>=<value>`` flags of this command line that set a field to another value than the checkpoint's
    config.json (``saved_config``) holds, as ``--policy.<field>=<value> (saved: <value>)``."""
    from .lerobot_command import given_policy_fields

    try:
        saved = read_config_json(saved_config) if saved_config.is_file() else {}
    except ValueError:
        return []
    out = []
    for field in sorted(given_policy_fields()):
        now = getattr(cfg, field, None)
        was = saved.get(field)
        if field in saved and (list(now) if isinstance(now, tuple) else now) != was:
            out.append(f"--policy.{field}={now!r} (saved: {was!r})")
    return out


def _other_features(cfg: Any, saved_config: Path) -> str:
    """How the features the policy is built with differ from those its config.json was saved with ('' when they
    do not, or the file cannot tell)."""
    try:
        saved = read_config_json(saved_config) if saved_config.is_file() else {}
    except ValueError:
        return ""
    differ = []
    for field in ("input_features", "output_features"):
        was = {k: tuple(v.get("shape") or ()) for k, v in (saved.get(field) or {}).items()}
        now = {k: tuple(ft.shape) for k, ft in (getattr(cfg, field) or {}).items()}
        if not was:
            continue
        for key in sorted(was.keys() | now.keys()):
            if key not in now:
                differ.append(f"'{key}' {was[key]} is missing")
            elif key not in was:
                differ.append(f"'{key}' {now[key]} is new")
            elif was[key] != now[key]:
                differ.append(f"'{key}' is {now[key]}, trained on {was[key]}")
    return "; ".join(differ)


def check_finite_weights(policy: nn.Module, model_file: str) -> None:
    """Refuse a checkpoint with non-finite weights or statistics, naming the tensor (``train_loss_dp`` is
    NaN by design until trained). A NaN checkpoint would otherwise load and send NaN actions."""
    for name, t in policy.state_dict().items():
        if t.is_floating_point() and name != "train_loss_dp" and not bool(torch.isfinite(t).all()):
            n = int((~torch.isfinite(t)).sum())
            raise ValueError(f"{model_file}: tensor '{name}' {tuple(t.shape)} holds {n} non-finite value(s); "
                             "this checkpoint cannot act (was its training diverging?)")


def resize_to_checkpoint(model: nn.Module, shapes: dict[str, tuple[int, ...]]) -> None:
    """Give the dataset-sized buffers of ``model`` (a ``PDPModel``: its behavior bank) the checkpoint's ``shapes``."""
    model.bank.resize(shapes)


def apply_saved_config(policy: Any, model_file: str) -> None:
    """Legacy defaults for the fields a checkpoint's config.json predates (it lies beside the weights: a local
    folder, or the hub snapshot the config came from), except those given on the command line
    (``--policy.<field>``: LeRobot has merged them into the config by now); the sampler is rebuilt when they
    changed it, and the log says so (LeRobot printed the config before)."""
    saved = Path(model_file).with_name(CONFIG_NAME)
    if not saved.is_file():
        return
    changed = apply_legacy_defaults(policy.config, read_config_json(saved), given_policy_fields())
    if changed:
        policy.model.set_sampler(policy.config.timestep_spacing, policy.config.use_clipped_model_output)
        logger.info("%s predates %s: sampling as it was made, with %s (give --policy.<field>=... to change it)",
                    saved, ", ".join(changed), ", ".join(f"{n}={getattr(policy.config, n)}" for n in changed))


def flatten_model_keys(module: nn.Module, state_dict: dict[str, Tensor], prefix: str, local_metadata) -> None:
    """``model.vae.x`` -> ``vae.x``, ``model.bank.traces`` -> ``behavior_traces``: the checkpoint keys of the
    first release, before the model module and its behavior bank (``behavior_bank.CHECKPOINT_KEYS``)."""
    for key in [k for k in state_dict if k.startswith(prefix + "model.")]:
        name = key[len(prefix) + len("model."):]
        if name.startswith("bank."):
            name = {**CHECKPOINT_KEYS, "taught": TAUGHT_KEY}[name[len("bank."):]]
        state_dict[prefix + name] = state_dict.pop(key)


def nest_model_keys(module: nn.Module, state_dict: dict[str, Tensor], prefix: str, *args) -> None:
    """The inverse of :func:`flatten_model_keys` when a checkpoint is loaded."""
    bank = {key: "bank." + name for name, key in {**CHECKPOINT_KEYS, "taught": TAUGHT_KEY}.items()}
    for key in [k for k in state_dict if k.startswith(prefix) and not k.startswith((prefix + "stats.", prefix + "model."))]:
        name = key[len(prefix):]
        state_dict[prefix + "model." + bank.get(name, name)] = state_dict.pop(key)
    # saved before the training error was tracked: no reference (FitResult.error_ratio stays None), no warning
    state_dict.setdefault(prefix + "model.train_loss_dp", torch.tensor(float("nan")))
    # saved before modes could be taught: none taught
    state_dict.setdefault(prefix + "model.bank.taught", torch.zeros(0, module.config.latent_dim))


def write_adaptation(steering: Any, directory: Path) -> bool:
    """The active latent, chunk noises and provenance of ``steering`` as the adaptation files in ``directory``
    (nothing, and False, when no latent is active)."""
    from safetensors.torch import save_file

    if not steering.active:
        return False
    tensors = {k: v.contiguous() for k, v in steering.state_tensors().items()}
    save_file(tensors, str(directory / ADAPTATION_TENSORS))
    info = {"latent": tensors["latent"].tolist(), "noise_chunks": len(tensors["noise"]),
            **(steering.provenance or {"source": "set_latent"})}
    (directory / ADAPTATION_INFO).write_text(json.dumps(info, indent=2) + "\n")
    return True


def apply_adaptation(policy: Any, pretrained: str | Path, **hub: Any) -> None:
    """Make ``policy`` act under the adaptation its checkpoint ``pretrained`` carries, if any (and unless
    ``config.use_adaptation`` is false): the active latent(s), chunk noises and provenance. Not when it is loaded
    to train (``hub`` holds lerobot-train's ``dataset_meta``): the adaptation was fitted to the weights it trains."""
    adaptation = read_adaptation(pretrained, **hub) if policy.config.use_adaptation else None
    if not policy.config.use_adaptation and (Path(pretrained) / ADAPTATION_TENSORS).is_file():  # (a local folder)
        logger.info("adapted checkpoint %s loaded without its adaptation (use_adaptation=false): acting as its base",
                    pretrained)
    if adaptation is not None and hub.get("dataset_meta") is not None:  # lerobot-train's fine-tune or resume
        logger.warning("%s is an adapted checkpoint (latent %s, %d chunk noise(s)), loaded to train: training moves "
                       "the weights that adaptation was fitted to, so this policy trains and is saved without it; adapt "
                       "the trained checkpoint again (lerobot-pdp adapt)", pretrained, adaptation[0]["latent"].tolist(),
                       len(adaptation[0].get("noise", ())))
        return
    if adaptation is not None:
        tensors, info = adaptation
        policy.steering.load_state_tensors(tensors, info)
        logger.info("adapted checkpoint %s: latent %s, %d chunk noise(s) (%s)", pretrained,
                    latent_text(tensors["latent"]), len(tensors.get("noise", ())), info.get("source", "?"))


def read_adaptation(pretrained: str | Path, **hub: Any) -> tuple[dict[str, Tensor], dict] | None:
    """The adaptation files of a checkpoint (a local folder, or a Hub repo: ``hub`` holds ``revision``,
    ``cache_dir``, ...), or None when it carries none. A damaged file is an error naming it."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    tensors_file = optional_checkpoint_file(pretrained, ADAPTATION_TENSORS, **hub)
    if tensors_file is None:
        return None
    info_file = optional_checkpoint_file(pretrained, ADAPTATION_INFO, **hub) or tensors_file.with_name(ADAPTATION_INFO)
    try:
        tensors = load_file(str(tensors_file))
        info = json.loads(info_file.read_text()) if info_file.is_file() else {}
    except (SafetensorError, OSError, ValueError) as e:
        raise ValueError(f"{tensors_file.parent}: the adaptation files ({ADAPTATION_TENSORS}, {ADAPTATION_INFO}) are "
                         f"damaged ({e}); adapt again, or load the base with --policy.use_adaptation=false") from e
    if "latent" not in tensors:
        raise ValueError(f"{tensors_file}: no 'latent' tensor (holds {sorted(tensors)})")
    return tensors, info
