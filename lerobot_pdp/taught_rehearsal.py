"""lerobot-train keeps a taught checkpoint's modes: the demonstrations it keeps join every training batch.

LeRobot's training loop samples the training dataset alone, and a taught mode's only data is the demonstration its
checkpoint keeps (:mod:`.taught_demos`): trained further without it, the denoiser would forget the route. So when
``lerobot-train`` loads a taught checkpoint (``--policy.path`` or ``--resume``) over the dataset it was trained on, or
over another whose modes leave the taught ids free (the same modes, more episodes; labelled, or as clusters discovered
in it), the behaviour bank keeps its taught behaviours (:func:`~lerobot_pdp.checkpoint.keep_training_behaviors`) and
:class:`TaughtRehearsal` appends to each training batch windows of the taught demonstrations, drawn uniformly among
all their windows, at their taught latents: ``config.taught_rehearsal_share`` of the batch it makes (0.25, as
``teach``'s demonstration share). The loss is the same L_DP over the whole batch. The encoder's geometry term trains
on the dataset's behaviours alone, and the taught latents stay where teaching put them.

The windows are cut as LeRobotDataset cuts training windows (copy padding) from the demonstration normalised with the
policy's statistics, and they join the batch before the observation encoder: camera frames get the batch's
augmentation, and the camera encoder's gradient, as the dataset's do.
"""

from __future__ import annotations

import logging
from typing import Any

import torch
from lerobot.utils.constants import ACTION
from torch import Tensor

from .chunk_windows import window_indices

logger = logging.getLogger(__name__)


class TaughtRehearsal:
    """The taught demonstrations' windows, normalised: per-frame features and, per window, where it reads them."""

    def __init__(self, frames: dict[str, Tensor], actions: Tensor, obs_idx: Tensor, act_idx: Tensor, is_pad: Tensor,
                 rows: Tensor, share: float):
        self.frames = frames  # [F, *shape] per condition feature, every demonstration's frames in a row
        self.actions = actions  # [F, A]
        self.obs_idx, self.act_idx, self.is_pad = obs_idx, act_idx, is_pad  # [N, n_obs], [N, horizon], [N, horizon]
        self.rows = rows  # [N] the behaviour-bank row of each window (its mode, and phase)
        self.share = share
        self._device = torch.device("cpu")

    def __len__(self) -> int:
        return len(self.rows)

    @classmethod
    def of(cls, policy: Any) -> TaughtRehearsal | None:
        """The rehearsal of every taught mode ``policy`` keeps the demonstration of (None: none kept)."""
        bank, cfg = policy.model.bank, policy.config
        if not bank.taught_demos:
            return None
        frames: dict[str, list[Tensor]] = {k: [] for k in cfg.condition_features}
        actions, obs_idx, act_idx, is_pad, rows = [], [], [], [], []
        first = 0
        for mode, demo in sorted(bank.taught_demos.items()):
            norm = policy.stats.normalize_episode({k: v for k, v in demo.arrays.items()
                                                   if k in cfg.condition_features or k == ACTION})
            n = len(norm[ACTION])
            o, a, pad = window_indices(n, cfg.n_obs_steps, cfg.horizon)
            phase = torch.zeros(n, dtype=torch.long)
            for m, (start, end) in enumerate(demo.segments):
                phase[start:end] = m
            for k in frames:
                frames[k].append(norm[k].float())
            actions.append(norm[ACTION].float())
            obs_idx.append(o + first)
            act_idx.append(a + first)
            is_pad.append(pad)
            rows.append(torch.nonzero(bank.mode.cpu() == mode).flatten()[phase])  # one behaviour per phase, in order
            first += n
        return cls({k: torch.cat(v) for k, v in frames.items()}, torch.cat(actions), torch.cat(obs_idx),
                   torch.cat(act_idx), torch.cat(is_pad), torch.cat(rows), cfg.taught_rehearsal_share)

    def windows_for(self, batch_size: int) -> int:
        """How many taught windows join a batch of ``batch_size`` dataset windows: ``share`` of the batch they make."""
        return max(1, round(batch_size * self.share / (1 - self.share)))

    def extend(self, batch: dict[str, Tensor]) -> tuple[dict[str, Tensor], Tensor]:
        """``batch`` with taught windows appended to its observation features, actions and padding mask (drawn with
        torch's generator, which lerobot-train seeds), and the bank rows whose latents they take."""
        device = batch[ACTION].device
        if device != self._device:  # once: the policy's device for the whole training
            self.frames = {k: v.to(device) for k, v in self.frames.items()}
            for name in ("actions", "obs_idx", "act_idx", "is_pad", "rows"):
                setattr(self, name, getattr(self, name).to(device))
            self._device = device
        i = torch.randint(0, len(self.rows), (self.windows_for(batch[ACTION].shape[0]),), device=device)
        out = dict(batch)
        for key, f in self.frames.items():
            out[key] = torch.cat([batch[key], f[self.obs_idx[i]].to(batch[key].dtype)])
        out[ACTION] = torch.cat([batch[ACTION], self.actions[self.act_idx[i]].to(batch[ACTION].dtype)])
        if "action_is_pad" in batch:
            out["action_is_pad"] = torch.cat([batch["action_is_pad"], self.is_pad[i]])
        return out, self.rows[i]


def rehearse_taught_modes(policy: Any) -> None:
    """Rehearse, in every training batch, the taught modes whose demonstrations ``policy`` keeps; a taught mode
    without one (taught by a release that kept none, or a damaged file) stays unrehearsed, with a warning."""
    bank = policy.model.bank
    missing = bank.unrehearsable_modes()
    if missing:
        logger.warning("taught mode(s) %s: their checkpoint keeps no demonstration of them, so training does not "
                       "rehearse them and the trained policy may act otherwise under their latents (teach the trained "
                       "checkpoint each route again)", missing)
    policy.model.rehearsal = rehearsal = TaughtRehearsal.of(policy)
    if rehearsal is not None:
        logger.info("training rehearses taught mode(s) %s: %d windows of their demonstrations, %.0f %% of each batch, "
                    "at their taught latents (taught_rehearsal_share)", sorted(bank.taught_demos), len(rehearsal),
                    100 * rehearsal.share)
