"""A checkpoint folder's files checked before anything is built from them: a clear error naming the folder or
file (a missing folder, a damaged config.json or model.safetensors, missing processor files, non-finite processor
statistics) instead of
huggingface_hub's or json's. Apart from checkpoint.py so that the config's own loader can use it."""

from __future__ import annotations

import json
import logging
from pathlib import Path

from huggingface_hub.constants import CONFIG_NAME, SAFETENSORS_SINGLE_FILE

from .lerobot_command import lerobot_program

logger = logging.getLogger(__name__)

PROCESSOR_FILES = ("policy_preprocessor.json", "policy_postprocessor.json")
PROCESSOR_PREFIXES = ("policy_preprocessor", "policy_postprocessor")  # the pipelines and their steps' statistics
# LeRobot programs that load a checkpoint's processor files right after the policy (a checkpoint without them
# is refused there, before LeRobot's misleading message); in-process loading only logs it.
DEPLOY_PROGRAMS = ("lerobot-eval", "lerobot-rollout")


def require_checkpoint_files(folder: str | Path) -> Path:
    """``folder`` as a Path when it is a local folder holding a checkpoint's two files (config.json,
    model.safetensors), else a FileNotFoundError saying what is wrong: no such folder, a file, or the file it
    lacks (with where a checkpoint is below a training run's folder)."""
    folder = Path(folder)
    give = "give a local pretrained_model folder holding config.json and model.safetensors"
    if not folder.is_dir():
        what = f"{folder} is a file, not a checkpoint folder" if folder.exists() else f"no such checkpoint folder: {folder}"
        raise FileNotFoundError(f"{what} ({give})")
    missing = [n for n in (CONFIG_NAME, SAFETENSORS_SINGLE_FILE) if not (folder / n).is_file()]
    if missing:
        raise FileNotFoundError(f"{folder} is not a PDP checkpoint folder (config.json + model.safetensors): it holds "
                                f"no {' and no '.join(missing)}{layout_hint(folder)}")
    return folder


def require_new_folder(out: str | Path, what: str, base: str | Path | None = None) -> Path:
    """``out`` as a Path when nothing is there yet (an adapted or taught checkpoint is written whole, never over
    another), else a FileExistsError naming it; ``what``: "adapted" or "taught". With ``base`` (the checkpoint
    whose files ``out`` gets), ``out`` inside it is refused: copying ``base`` would copy ``out`` being written."""
    out = Path(out)
    if out.exists():
        raise FileExistsError(f"{out} exists: give a new folder for the {what} checkpoint")
    if base is not None and out.resolve().is_relative_to(Path(base).resolve()):
        raise ValueError(f"{out} lies inside the checkpoint {base}, whose every file the {what} checkpoint "
                         "copies: give a folder outside it")
    return out


def layout_hint(folder: Path) -> str:
    """Where the checkpoint is in LeRobot's training layout below ``folder`` (``checkpoints/last`` holds
    ``pretrained_model``, which is the checkpoint): "; did you mean ...?", or ""."""
    return next((f"; did you mean {folder / sub}?" for sub in ("pretrained_model", "checkpoints/last/pretrained_model")
                 if (folder / sub / CONFIG_NAME).is_file()), "")


def check_checkpoint_source(pretrained: str | Path, need_config: bool = True, need_weights: bool = True) -> None:
    """Fail early, naming the file, on a local checkpoint folder PDP cannot load: one that does not exist
    (huggingface_hub would call its path an invalid repo id), lacks or holds a damaged config.json, or lacks
    model.safetensors. A folder without LeRobot's processor files is refused by name in lerobot-eval /
    lerobot-rollout (they load them next, and LeRobot then says the model "requires migration"); in-process
    it loads, with an info line naming them."""
    from huggingface_hub.errors import HFValidationError
    from huggingface_hub.utils import validate_repo_id

    folder = Path(pretrained)
    if not folder.exists():
        try:  # LeRobot's commands pass a Hub repo id as a Path too (--policy.path=user/repo)
            validate_repo_id(str(pretrained))
        except HFValidationError:
            raise FileNotFoundError(f"no such checkpoint folder: {pretrained} (give a pretrained_model folder "
                                    "holding config.json and model.safetensors, or a Hub repo id)") from None
        if _offline_and_not_cached(str(pretrained)):  # huggingface_hub would only say "check your connection"
            raise FileNotFoundError(f"no such checkpoint folder: {pretrained} (from {Path.cwd()}), and the Hub "
                                    "cannot be asked for a repo of that name (HF_HUB_OFFLINE is set) nor has it "
                                    "cached: give a pretrained_model folder holding config.json and model.safetensors")
        return  # a Hub repo id: huggingface_hub names what is missing there
    if not folder.is_dir():
        raise NotADirectoryError(f"{pretrained} is a file; give its checkpoint folder (config.json + model.safetensors)")
    config = folder / CONFIG_NAME
    if need_config:
        if not config.is_file():
            raise FileNotFoundError(f"{folder} holds no {CONFIG_NAME}: give a PDP pretrained_model folder"
                                    f"{layout_hint(folder)}")
        read_config_json(config)
    if not need_weights:
        return
    if not (folder / SAFETENSORS_SINGLE_FILE).is_file():
        raise FileNotFoundError(f"{folder} holds no {SAFETENSORS_SINGLE_FILE}: give a PDP pretrained_model folder"
                                f"{layout_hint(folder)}")
    missing = [name for name in PROCESSOR_FILES if not (folder / name).is_file()]
    if missing:
        program = lerobot_program()
        text = (f"{folder} lacks LeRobot's processor files {missing}, which lerobot-eval / lerobot-rollout load next "
                "(LeRobot then says the model 'requires migration'; it does not): copy them from the training run's "
                "checkpoint folder, where lerobot-train wrote them")
        if program in DEPLOY_PROGRAMS:
            raise FileNotFoundError(f"{program}: {text}")
        logger.info("%s; PDP itself loads without them", text)
    check_processor_statistics(folder)


def _offline_and_not_cached(repo_id: str) -> bool:
    from huggingface_hub import constants, try_to_load_from_cache

    return bool(constants.HF_HUB_OFFLINE) and not isinstance(try_to_load_from_cache(repo_id, CONFIG_NAME), str)


def check_processor_statistics(folder: Path) -> None:
    """Refuse a processor statistics file (``policy_*processor*.safetensors``: LeRobot's normaliser and
    unnormaliser state) holding a non-finite value, naming the file and tensor: the postprocessor's would turn
    every action non-finite after PDP's own check of the chunk, on the way to the robot."""
    from safetensors import SafetensorError, safe_open

    for path in sorted(folder.glob("policy_*processor*.safetensors")):
        try:
            with safe_open(str(path), framework="pt") as f:
                for key in f.keys():
                    t = f.get_tensor(key)
                    if t.is_floating_point() and not bool(t.isfinite().all()):
                        raise ValueError(f"{path}: statistic {key!r} holds {int((~t.isfinite()).sum())} non-finite "
                                         f"value(s) of {t.numel()}; the checkpoint's normalisation is damaged: copy "
                                         "the file again from the training run, or recompute the dataset's statistics")
        except (SafetensorError, OSError) as e:
            raise ValueError(f"{path} cannot be read ({e}): the file is damaged (cut off while written or "
                             "copied?); copy it again from the training run") from e


def read_config_json(path: str | Path) -> dict:
    """A checkpoint's config.json as a dict; a damaged one is an error naming the file."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path} is not valid JSON ({e}): the file is damaged (cut off while written or "
                         "copied?); copy it again from the training run") from e


def read_weight_shapes(model_file: str) -> dict[str, tuple[int, ...]]:
    """The tensor shapes in ``model_file``; a damaged file is an error naming it."""
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(model_file, framework="pt") as f:
            return {k: tuple(f.get_slice(k).get_shape()) for k in f.keys()}
    except (SafetensorError, OSError) as e:
        raise damaged_weights(model_file, e) from e


def damaged_weights(model_file: str, error: Exception) -> ValueError:
    """The error for a weights file safetensors cannot read (its header, or its tensors when loading)."""
    return ValueError(f"{model_file} is not a readable safetensors file ({error}): the file is damaged (cut off "
                      "while written or copied?); copy it again from the training run")


def optional_checkpoint_file(pretrained: str | Path, name: str, **hub) -> Path | None:
    """The file ``name`` of a checkpoint (a local folder, or a Hub repo: ``hub`` holds ``revision``, ``cache_dir``,
    ...), or None when the checkpoint has none."""
    folder = Path(pretrained)
    if folder.is_dir():
        return folder / name if (folder / name).is_file() else None
    from huggingface_hub import hf_hub_download
    from huggingface_hub.errors import EntryNotFoundError, LocalEntryNotFoundError

    kw = {k: hub[k] for k in ("revision", "cache_dir", "token", "local_files_only", "force_download") if k in hub}
    try:
        return Path(hf_hub_download(str(pretrained), name, **kw))
    except (EntryNotFoundError, LocalEntryNotFoundError):
        return None
