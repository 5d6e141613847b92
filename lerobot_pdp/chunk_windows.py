"""The (observation history, action chunk) windows of an episode, at every frame, as LeRobotDataset cuts them for
training with a policy's delta indices: what latent fitting scores, teaching rehearses and DP's adaptation batches."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class DemoWindows:
    """All training-style windows of one (normalised) demonstration."""

    obs_cond: Tensor  # [N, n_obs_steps * frame_dim] flattened observation-feature history
    actions: Tensor  # [N, horizon, A]
    is_pad: Tensor  # [N, horizon] True where the chunk ran past the episode end (copy-padded)
    segment: Tensor  # [N] phase index of each window
    n_segments: int

    @staticmethod
    def concat(parts: list[DemoWindows]) -> DemoWindows:
        """The windows of several demonstrations as one set (on the CPU; their phase indices kept as they are)."""
        return DemoWindows(*(torch.cat([getattr(w, f).cpu() for w in parts]) for f in ("obs_cond", "actions",
                                                                                       "is_pad", "segment")),
                           max(w.n_segments for w in parts))


def window_indices(T: int, n_obs_steps: int, horizon: int) -> tuple[Tensor, Tensor, Tensor]:
    """For the window at each frame t of a T-frame episode: its observation frames t-n_obs+1..t [T, n_obs], its
    action frames t-n_obs+1..t-n_obs+horizon [T, horizon], both clamped into the episode (copy padding, as
    LeRobotDataset pads), and which action frames ran past it [T, horizon]."""
    t = torch.arange(T)
    obs_idx = (t[:, None] + torch.arange(1 - n_obs_steps, 1)[None]).clamp(0, T - 1)
    act_raw = t[:, None] + torch.arange(1 - n_obs_steps, 1 - n_obs_steps + horizon)[None]
    return obs_idx, act_raw.clamp(0, T - 1), (act_raw < 0) | (act_raw > T - 1)


def frame_windows(frame_cond: Tensor, actions: Tensor, n_obs_steps: int, horizon: int,
                  segments: list[tuple[int, int]]) -> DemoWindows:
    """Windows at every frame t of per-frame condition features ``frame_cond`` [T, F] and ``actions`` [T, A]:
    features t-n_obs+1..t and actions t-n_obs+1..t-n_obs+horizon.

    Indices outside the episode are clamped (copy padding), as LeRobotDataset does for training. Taking
    per-frame features (not raw observations) lets a camera frame be encoded once, not once per window.
    """
    T = frame_cond.shape[0]
    obs_idx, act_idx, is_pad = window_indices(T, n_obs_steps, horizon)
    obs_cond = frame_cond[obs_idx.to(frame_cond.device)].flatten(1)
    seg = torch.zeros(T, dtype=torch.long)
    for m, (a, b) in enumerate(segments):
        seg[a:b] = m
    return DemoWindows(obs_cond.float(), actions[act_idx.to(actions.device)].float(), is_pad, seg, len(segments))


def episode_windows(norm: dict[str, Tensor], n_obs_steps: int, horizon: int, state_key: str,
                    env_key: str | None, segments: list[tuple[int, int]]) -> DemoWindows:
    """:func:`frame_windows` of a state-only demonstration: the features are ``[state | env state]``."""
    feats = [norm[state_key]] + ([norm[env_key]] if env_key is not None else [])
    return frame_windows(torch.cat(feats, dim=-1), norm["action"], n_obs_steps, horizon, segments)
