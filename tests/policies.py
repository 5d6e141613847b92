"""Small PDP policies built on the synthetic dataset, and training batches from it, for in-process tests."""

from __future__ import annotations

from pathlib import Path

import torch
from lerobot.policies.factory import make_policy, make_pre_post_processors
from lerobot.utils.constants import ACTION

from lerobot_pdp import PDPConfig


def small_policy(meta, device: str = "cpu", seed: int = 0, **kw):
    """A PDP with a small U-Net, built as ``lerobot-train`` builds it (behaviors read from ``meta.root``). Its
    weights come from ``seed`` whatever ran before in this worker, and the global random state is left as it was."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return make_policy(PDPConfig(device=device, push_to_hub=False, down_dims=(16, 32), **kw), ds_meta=meta)


def training_batch(meta, policy, n: int = 8, seed: int = 0, episodes: list[int] | None = None) -> dict:
    """``n`` training windows (of ``episodes``, default all) as LeRobot's loader and preprocessor hand them over (on
    the policy's device)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    cfg = policy.config
    fps = meta.fps
    ds = LeRobotDataset("local/synthetic", root=meta.root, episodes=episodes, video_backend="pyav", delta_timestamps={
        **{k: [i / fps for i in cfg.observation_delta_indices] for k in cfg.input_features},
        ACTION: [i / fps for i in cfg.action_delta_indices],
    })
    pre, _ = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    g = torch.Generator().manual_seed(seed)
    return pre(torch.utils.data.default_collate([ds[int(i)] for i in torch.randint(0, len(ds), (n,), generator=g)]))


def saved_steerable_checkpoint(root: Path, camera: str | None = None) -> tuple[Path, Path]:
    """A reach-around dataset (one demonstration per mode) and a small untrained PDP on it, with random FiLM
    layers, saved as lerobot-train saves one (weights, processors, model card)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    from lerobot_pdp.denoiser import LatentFiLM
    from lerobot_pdp.envs.recording import make_dataset

    data = make_dataset("reach-around", root / "data", scene=0, episodes_per_mode=1, progress=False, camera=camera,
                        image_size=40)
    meta = LeRobotDatasetMetadata("local/ra", root=data)
    extra = {"spatial_softmax_num_keypoints": 8} if camera else {}
    cfg = PDPConfig(device="cpu", push_to_hub=False, down_dims=(16, 32), trace_dims=[0, 1, 2], num_inference_steps=4,
                    fit_steps=2, **extra)
    with torch.random.fork_rng(devices=[]):  # the same weights whatever ran before; the global state untouched
        torch.manual_seed(0)
        policy = make_policy(cfg, ds_meta=meta)
        for m in policy.modules():
            if isinstance(m, LatentFiLM):
                torch.nn.init.normal_(m.mlp[-1].weight, std=2.0)
    out = root / "ckpt"
    policy.save_pretrained(out)
    pre, post = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    (out / "README.md").write_text("# A model card\n")
    return out, data
