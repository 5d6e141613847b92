"""The demonstrations a policy was taught, kept with its checkpoint so that teaching it again rehearses them.

Teaching fine-tunes the denoiser on the new demonstration while rehearsing what the policy acts on, so that it
forgets nothing. The training dataset holds the training modes; a taught mode's only data is its
demonstration, so each taught demonstration is kept with the policy (``BehaviorBank.taught_demos``, by mode)
and saved beside the weights as ``taught_demonstrations.safetensors``: a later ``teach`` rehearses it at its
taught latent(s) together with the training data. Its arrays are the demonstration as the steering API reads
it (unnormalised vectors, float64; camera frames as uint8, a 1/255 step in [0, 1]) with its phase segments.
What each teaching was (the base, the demonstration, the rehearsal data, the settings, the loss: ``teaching.json``,
``BehaviorBank.teachings``, by mode) goes along the same way, so a checkpoint saved from Python after ``teach`` says
where its modes came from as one ``lerobot-pdp teach`` writes does.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .demonstration import Demonstration
from .taught_rehearsal import rehearse_taught_modes

logger = logging.getLogger(__name__)

TAUGHT_DEMOS = "taught_demonstrations.safetensors"
# the last teaching's record, the ones before it as "earlier_teachings" (oldest first)
TEACHING_INFO = "teaching.json"
_SEGMENTS = "segments"  # [M, 2] int64 frame ranges of the demonstration's phases
_PER_PHASE = "per_phase"


def demos_to_tensors(demos: dict[int, Demonstration], image_keys: set[str]) -> dict[str, Tensor]:
    """``mode<m>/<feature key>`` per array (cameras as uint8), ``mode<m>/segments``, ``mode<m>/per_phase``."""
    out: dict[str, Tensor] = {}
    for mode, demo in sorted(demos.items()):
        for key, v in demo.arrays.items():
            a = np.rint(np.clip(v, 0, 1) * 255).astype(np.uint8) if key in image_keys else np.asarray(v, np.float64)
            out[f"mode{mode}/{key}"] = torch.from_numpy(np.ascontiguousarray(a))
        out[f"mode{mode}/{_SEGMENTS}"] = torch.tensor(demo.segments, dtype=torch.long).reshape(-1, 2)
        out[f"mode{mode}/{_PER_PHASE}"] = torch.tensor([demo.per_phase])
    return out


def tensors_to_demos(tensors: dict[str, Tensor], where: str) -> dict[int, Demonstration]:
    """The inverse of :func:`demos_to_tensors`; a tensor of another form is an error naming ``where``."""
    grouped: dict[int, dict[str, Tensor]] = {}
    for name, t in tensors.items():
        head, _, key = name.partition("/")
        if not head.startswith("mode") or not head[4:].isdigit() or not key:
            raise ValueError(f"{where}: tensor {name!r} is not 'mode<id>/<key>'")
        grouped.setdefault(int(head[4:]), {})[key] = t
    demos = {}
    for mode, group in sorted(grouped.items()):
        if _SEGMENTS not in group:
            raise ValueError(f"{where}: mode {mode} has no '{_SEGMENTS}' tensor")
        segments = [(int(a), int(b)) for a, b in group.pop(_SEGMENTS).tolist()]
        per_phase = bool(group.pop(_PER_PHASE, torch.tensor([len(segments) > 1])).item())
        arrays = {k: (v.numpy().astype(np.float32) / 255 if v.dtype == torch.uint8 else v.numpy().astype(np.float64))
                  for k, v in group.items()}
        demos[mode] = Demonstration(arrays, segments, per_phase)
    return demos


def write_taught_demos(bank: Any, image_keys: set[str], directory: Path) -> bool:
    """``bank``'s taught demonstrations as :data:`TAUGHT_DEMOS` in ``directory`` (nothing, and False, if none)."""
    from safetensors.torch import save_file

    demos = getattr(bank, "taught_demos", None)
    if not demos:
        return False
    save_file(demos_to_tensors(demos, image_keys), str(directory / TAUGHT_DEMOS))
    return True


def write_teachings(bank: Any, directory: Path) -> bool:
    """The records of ``bank``'s taught modes as :data:`TEACHING_INFO` in ``directory`` (nothing, and False, if
    none): the last teaching at the top, the ones before as ``earlier_teachings``."""
    taught = set(bank.taught_modes())
    records = [r for m, r in sorted(getattr(bank, "teachings", {}).items()) if m in taught]
    if not records:
        return False
    info = {**records[-1], "earlier_teachings": records[:-1]} if len(records) > 1 else records[-1]
    (directory / TEACHING_INFO).write_text(json.dumps(info, indent=2) + "\n")
    return True


def read_taught_demos(policy: Any, pretrained: str | Path, **hub: Any) -> None:
    """Give ``policy``'s behaviour bank the taught demonstrations and teaching records its checkpoint
    ``pretrained`` keeps, if any (a local folder or a Hub repo); a mode the bank does not hold as taught, or a
    damaged file, is left out with a warning. Loaded to train on (lerobot-train), they are then rehearsed in every
    batch."""
    _read_taught_demos(policy, pretrained, **hub)
    _read_teachings(policy.model.bank, pretrained, **hub)
    if policy.model.bank.taught_in_training:
        rehearse_taught_modes(policy)


def _read_taught_demos(policy: Any, pretrained: str | Path, **hub: Any) -> None:
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    from .checkpoint_files import optional_checkpoint_file

    path = optional_checkpoint_file(pretrained, TAUGHT_DEMOS, **hub)
    if path is None:
        return
    try:
        demos = tensors_to_demos(load_file(str(path)), str(path))
    except (SafetensorError, OSError, ValueError) as e:  # acting does not need them: said, and the policy loads
        logger.warning("%s is damaged (%s): the taught modes act as saved, but teaching this checkpoint again will "
                       "not rehearse them", path, e)
        return
    bank = policy.model.bank
    taught = set(bank.taught_modes())
    unknown = sorted(set(demos) - taught)
    if unknown:
        logger.warning("%s keeps demonstrations of modes %s, which this checkpoint's behaviour bank does not hold as "
                       "taught modes: ignored", path, unknown)
    bank.taught_demos = {m: d for m, d in demos.items() if m in taught}


def _read_teachings(bank: Any, pretrained: str | Path, **hub: Any) -> None:
    from .checkpoint_files import optional_checkpoint_file

    path = optional_checkpoint_file(pretrained, TEACHING_INFO, **hub)
    if path is None:
        return
    try:
        info = json.loads(path.read_text())
        records = [*info.pop("earlier_teachings", []), info]
        by_mode = {int(r["mode"]): r for r in records}
    except (OSError, ValueError, TypeError, KeyError, AttributeError) as e:  # provenance only: the policy acts
        logger.warning("%s is damaged (%s): this checkpoint's taught modes act as saved, but a folder it is saved "
                       "to will not say where they came from", path, e)
        return
    taught = set(bank.taught_modes())
    bank.teachings = {m: r for m, r in by_mode.items() if m in taught}
