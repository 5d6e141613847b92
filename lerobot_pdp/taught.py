"""Taught checkpoints: a trained PDP that learned one demonstration as a new mode, kept as a checkpoint of its own.

``lerobot-pdp teach CKPT --demo DATASET --out TAUGHT`` (:func:`teach_checkpoint`) runs
:func:`~lerobot_pdp.teaching.teach_new_mode` once and writes TAUGHT whole: the base's processors and training
config, the fine-tuned weights with the grown behaviour bank, the config naming the new mode, ``teaching.json``
(where the demonstration came from, the settings, the loss, the time), the taught demonstrations
(``taught_demonstrations.safetensors``: rehearsed when it is taught again) and a model card section. The new mode is
then a mode like the others: ``--policy.steer_mode=<id>`` in ``lerobot-eval`` / ``lerobot-rollout``.

``lerobot-pdp teach CKPT --taught-from TAUGHT --out NEW`` (:func:`teach_again_from`) teaches CKPT every mode TAUGHT
was taught, from the demonstrations TAUGHT keeps: how taught modes are carried over to a checkpoint that
``lerobot-train`` trained without them (it keeps and rehearses them where it can: :mod:`.taught_rehearsal`; it warns
when it drops them).
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

from .atomic import move_into_place, staging_dir
from .checkpoint import ADAPTATION_INFO, ADAPTATION_TENSORS, CARD_HEADING
from .checkpoint_files import read_config_json, require_checkpoint_files, require_new_folder
from .configuration_pdp import STEERING_FIELDS, PDPConfig
from .console import latent_text
from .demonstration import Demonstration, Episode, check_demonstration, check_recording_exists
from .model_card import checkpoint_card
from .taught_demos import TAUGHT_DEMOS, TEACHING_INFO, tensors_to_demos
from .teaching import TEACH_DEMO_SHARE, TEACH_LATENT, TEACH_LR, TEACH_STEPS, TeachResult, read_rehearsal

logger = logging.getLogger(__name__)

# written anew for the taught policy; every other file of the base is copied
_REWRITTEN = ("config.json", "model.safetensors", "README.md", ADAPTATION_TENSORS, ADAPTATION_INFO, TEACHING_INFO,
              TAUGHT_DEMOS)


def training_data_of(checkpoint: str | Path) -> Path:
    """The local training dataset a LeRobot checkpoint names in its ``train_config.json`` (``dataset.root``)."""
    path = Path(checkpoint) / "train_config.json"
    if not path.is_file():
        raise FileNotFoundError(f"{checkpoint} has no train_config.json naming its training dataset: give it with "
                                "--data (the dataset the checkpoint was trained on)")
    train = read_config_json(path)  # a damaged file: an error naming it
    dataset = train.get("dataset") if isinstance(train, dict) else None
    root = dataset.get("root") if isinstance(dataset, dict) else None
    if not root:
        raise ValueError(f"{path} names no local dataset root (dataset.root): give the training dataset with --data")
    return _from_launch_folder(Path(root), Path(checkpoint), train.get("output_dir"))


def _training_data(base: Path, training_data: str | Path | None) -> Path:
    """``training_data``, or the dataset ``base``'s train_config.json names (an error if it is not here)."""
    data = Path(training_data) if training_data is not None else training_data_of(base)
    if training_data is None and not data.is_dir():  # a path the user never typed: say where it came from
        raise FileNotFoundError(f"{base / 'train_config.json'} names the training dataset {data}, which is not here "
                                "(moved, or on another machine): give the dataset the checkpoint was trained on with --data")
    return data


def _from_launch_folder(root: Path, checkpoint: Path, output_dir: str | None) -> Path:
    """lerobot-train records ``--dataset.root`` as typed: a relative root is relative to the folder it was run
    in. Found from here as given; else from that folder, which a checkpoint under ``OUTPUT_DIR/checkpoints/
    STEP/pretrained_model`` tells when ``output_dir`` is relative too (``runs/x`` run in ``/lab``: ``/lab``)."""
    if root.is_absolute() or root.exists() or not output_dir or Path(output_dir).is_absolute():
        return root
    parents = checkpoint.resolve().parents
    run, parts = (parents[2] if len(parents) > 2 else None), Path(output_dir).parts
    if run is None or run.parts[-len(parts):] != parts:
        return root
    launch = Path(*run.parts[: -len(parts)])
    return launch / root if (launch / root).exists() else root


def teach_checkpoint(base: str | Path, episode: Episode, out: str | Path, training_data: str | Path | None = None,
                     steps: int = TEACH_STEPS, lr: float = TEACH_LR, demo_share: float = TEACH_DEMO_SHARE,
                     seed: int = 0, name: str | None = None, latent: str = TEACH_LATENT,
                     device: str = "cpu") -> tuple[Path, TeachResult]:
    """Teach ``base`` one demonstration as a new mode and write the taught checkpoint ``out`` (which must not
    exist); ``training_data`` defaults to the dataset the base's ``train_config.json`` names."""
    out, results = teach_checkpoint_modes(base, [episode], out, training_data, steps, lr, demo_share, seed,
                                          None if name is None else [name], latent, device)
    return out, results[0]


def teach_checkpoint_modes(base: str | Path, episodes: list[Episode], out: str | Path,
                           training_data: str | Path | None = None, steps: int = TEACH_STEPS, lr: float = TEACH_LR,
                           demo_share: float = TEACH_DEMO_SHARE, seed: int = 0, names: list[str | None] | None = None,
                           latent: str = TEACH_LATENT, device: str = "cpu") -> tuple[Path, list[TeachResult]]:
    """Teach ``base`` several demonstrations, a new mode each, in order (each rehearsing the ones before), and
    write one taught checkpoint ``out``: one load and one read of the training dataset for them all, as
    :func:`teach_checkpoint` one by one would teach them otherwise. ``names``: one per demonstration (or None)."""
    if not episodes:
        raise ValueError("teach: no demonstration given")
    names = list(names) if names is not None else [None] * len(episodes)
    if len(names) != len(episodes):
        raise ValueError(f"teach: {len(names)} mode name(s) for {len(episodes)} demonstration(s): give one per "
                         "demonstration, or none")
    given = [n for n in names if n is not None]
    if len(set(given)) != len(given):
        raise ValueError(f"teach: mode names {given} repeat a name; each new mode needs its own")
    settings = {"steps": steps, "lr": lr, "demo_share": demo_share, "seed": seed, "latent": latent}
    lessons = [(episode, name, None) for episode, name in zip(episodes, names, strict=True)]
    return Path(out), _teach_and_write(Path(base), lessons, Path(out), training_data, device, settings)


def _teach_and_write(base: Path, lessons: list[tuple[Episode, str | None, dict | None]], out: Path,
                     training_data: str | Path | None, device: str, settings: dict) -> list[TeachResult]:
    """Load ``base`` once, teach it each ``(demonstration, mode name, what teaching.json says of it)`` in turn
    (each rehearsing the ones before), and write the taught checkpoint ``out`` whole, its teaching.json holding
    every teaching (the last one's record, the others as ``earlier_teachings``)."""
    from .adapted import LOAD_ONLY_FIELDS, load_base_policy

    require_checkpoint_files(base)
    require_new_folder(out, "taught", base)
    for episode, _, _ in lessons:
        check_recording_exists(episode)
    if (base / ADAPTATION_INFO).is_file():  # the weights are taught; the taught checkpoint acts unadapted
        logger.warning("%s carries an adaptation (%s): teaching its weights without it; %s carries none (steer it "
                       "to the new mode, or adapt it again)", base, ADAPTATION_INFO, out)
    data = _training_data(base, training_data)
    policy = load_base_policy(base, device)
    results = []
    if len(lessons) > 1:  # a recording that cannot be taught is named before the first teaching's minutes
        for episode, _, _ in lessons:
            check_demonstration(episode, policy.config, policy.action_dim)
    # several lessons rehearse the same training windows: read (and, with cameras, decode) the dataset once
    rehearsal = read_rehearsal(policy, data) if len(lessons) > 1 else data
    for i, (episode, name, demo_record) in enumerate(lessons):
        if len(lessons) > 1:
            logger.info("teaching %s (%d of %d)", name, i + 1, len(lessons))
        result = policy.teach(episode, rehearsal, name=name, progress=True, **settings)
        results.append(result)
        if demo_record is not None:  # a demonstration a taught checkpoint kept: teaching.json names that one
            policy.model.bank.teachings[result.mode]["demonstration"] = demo_record
    policy.eval()
    saved = PDPConfig.from_pretrained(base)  # written as the base's: use_adaptation=False would hide a later adaptation
    steering = {f: getattr(saved, f) for f in STEERING_FIELDS if getattr(saved, f) is not None}
    if steering:  # run at every load, they would steer the taught checkpoint past its new mode (or fit again)
        logger.warning("%s's config.json steers it as it loads (%s): the taught checkpoint is written without that; "
                       "steer it when loading it", base, ", ".join(f"{k}={v!r}" for k, v in steering.items()))
    for field in LOAD_ONLY_FIELDS:
        setattr(policy.config, field, None if field in STEERING_FIELDS else getattr(saved, field))
    with staging_dir(out, prefix=".pdp-teach-") as tmp:
        for f in base.iterdir():
            if f.name not in _REWRITTEN:
                (shutil.copytree if f.is_dir() else shutil.copy2)(f, tmp / f.name)
        policy.save_pretrained(tmp)  # with teaching.json: this teaching, and the base's as earlier_teachings
        info = read_config_json(tmp / TEACHING_INFO)
        card = checkpoint_card(base, policy.config).split(f"\n{CARD_HEADING}\n")[0]  # no adaptation section
        (tmp / "README.md").write_text(card.rstrip() + "\n\n" + _card_section(info))
        move_into_place(tmp, out)
    return results


def taught_demonstrations(checkpoint: str | Path) -> list[tuple[int, str, Demonstration]]:
    """The demonstrations a taught checkpoint keeps (``taught_demonstrations.safetensors``), in the order they were
    taught: ``(mode id, mode name, demonstration)``. An error naming the file when it keeps none or is damaged."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    checkpoint = Path(checkpoint)
    path = checkpoint / TAUGHT_DEMOS
    if not path.is_file():
        raise FileNotFoundError(f"{checkpoint} keeps no taught demonstrations ({TAUGHT_DEMOS}): it is no taught "
                                "checkpoint, or one taught by a release that did not keep them (teach each "
                                "demonstration again with --demo)")
    try:
        demos = tensors_to_demos(load_file(str(path)), str(path))
    except (SafetensorError, OSError) as e:
        raise ValueError(f"{path} is damaged ({e}): its taught demonstrations cannot be read") from e
    if not demos:
        raise ValueError(f"{path} holds no demonstration")
    config = checkpoint / "config.json"
    names = (read_config_json(config).get("mode_names") or {}) if config.is_file() else {}
    return [(mode, str(names.get(str(mode), f"taught mode {mode}")), demo) for mode, demo in sorted(demos.items())]


def teach_again_from(base: str | Path, taught_from: str | Path, out: str | Path,
                     training_data: str | Path | None = None, steps: int = TEACH_STEPS, lr: float = TEACH_LR,
                     demo_share: float = TEACH_DEMO_SHARE, seed: int = 0, latent: str = TEACH_LATENT,
                     device: str = "cpu") -> tuple[Path, list[tuple[int, TeachResult]]]:
    """Teach ``base`` every mode the taught checkpoint ``taught_from`` was taught, from the demonstrations it keeps,
    in their order and under their names, and write the result to ``out``: each teaching rehearses the ones
    before, as teaching them one by one would. For a checkpoint ``lerobot-train`` trained without them (another
    dataset whose modes take their ids, or ``--policy.taught_rehearsal_share=0``).
    Returns ``out`` and ``(mode id in taught_from, result)`` per mode."""
    taught_from = Path(taught_from)
    demos = taught_demonstrations(taught_from)
    kept = {name: mode for mode, name, _ in taught_demonstrations(Path(base))} \
        if (Path(base) / TAUGHT_DEMOS).is_file() else {}  # lerobot-train kept them (rehearsing their demonstrations)
    held = [(mode, name) for mode, name, _ in demos if name in kept]
    if held:
        said = ", ".join(f"{kept[name]} ({name!r})" for _, name in held)
        if len(held) == len(demos):
            raise ValueError(f"{base} still holds every mode taught to {taught_from}: {said} (lerobot-train kept "
                             "them): nothing to teach again")
        logger.info("%s still holds %s (lerobot-train kept them): teaching only the others", base, said)
        demos = [d for d in demos if d[1] not in kept]
    lessons = [(demo.arrays, name, {"taught_checkpoint": str(taught_from.resolve()), "mode": mode})
               for mode, name, demo in demos]
    settings = {"steps": steps, "lr": lr, "demo_share": demo_share, "seed": seed, "latent": latent}
    results = _teach_and_write(Path(base), lessons, Path(out), training_data, device, settings)
    return Path(out), [(mode, res) for (mode, _, _), res in zip(demos, results, strict=True)]


def _demo_source(demo: dict) -> str:
    """Where a teaching.json demonstration record says the demonstration came from, in a few words."""
    if "taught_checkpoint" in demo:
        return f"mode {demo.get('mode', '?')} kept by `{Path(str(demo['taught_checkpoint'])).name}`"
    if "dataset" in demo:
        return f"episode {demo.get('episode', '?')} of `{Path(str(demo['dataset'])).name}`"
    return "arrays given in memory"


def _card_section(info: dict) -> str:
    """The model card's section on every mode the checkpoint was taught (teaching.json's records, oldest first)."""
    records = [*info.get("earlier_teachings", []), info]
    learned = ("one demonstration as a new mode" if len(records) == 1
               else f"{len(records)} demonstrations, a new mode each (each teaching rehearsing the ones before)")
    modes = "".join(f"- mode {r['mode']} ({r['mode_name']}), latent `{latent_text(r['latent'])}`: {_demo_source(r['demonstration'])},"
                    f" {r['settings']['steps']} fine-tuning steps ({r['date']})\n" for r in records)
    return (f"## Taught mode\n\nThis checkpoint learned {learned}: its denoiser was fine-tuned with rehearsal of the "
            f"training data, the encoder kept as trained.\n\n{modes}\nSteer to one with "
            f"`--policy.steer_mode=<mode>`; the other modes keep their latents. `lerobot-train --policy.path` on "
            f"this checkpoint keeps the modes, rehearsing the demonstrations kept in `{TAUGHT_DEMOS}`. "
            f"`{TEACHING_INFO}` holds the provenance.\n")
