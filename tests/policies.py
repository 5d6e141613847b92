"""Small PDP policies built on the synthetic dataset, and training batches from it, for in-process tests."""

from __future__ import annotations

import torch
from lerobot.policies.factory import make_policy, make_pre_post_processors
from lerobot.utils.constants import ACTION

from lerobot_pdp import PDPConfig


def small_policy(meta, device: str = "cpu", **kw):
    """A PDP with a small U-Net, built as ``lerobot-train`` builds it (behaviors read from ``meta.root``)."""
    return make_policy(PDPConfig(device=device, push_to_hub=False, down_dims=(16, 32), **kw), ds_meta=meta)


def training_batch(meta, policy, n: int = 8, seed: int = 0) -> dict:
    """``n`` training windows as LeRobot's loader and preprocessor hand them over (on the policy's device)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    cfg = policy.config
    fps = meta.fps
    ds = LeRobotDataset("local/synthetic", root=meta.root, video_backend="pyav", delta_timestamps={
        **{k: [i / fps for i in cfg.observation_delta_indices] for k in cfg.input_features},
        ACTION: [i / fps for i in cfg.action_delta_indices],
    })
    pre, _ = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    g = torch.Generator().manual_seed(seed)
    return pre(torch.utils.data.default_collate([ds[int(i)] for i in torch.randint(0, len(ds), (n,), generator=g)]))
