"""Writes ``tests/data/pdp_checkpoint_v1``: a small PDP checkpoint plus the actions, mode latents and fitted
latent it produced when it was written. ``test_policy.py`` loads it with the current code and expects the
same numbers, so a change that breaks old checkpoints (state-dict keys, buffers, config fields,
normalisation) fails. Regenerate it only when the checkpoint format is changed on purpose.

    .venv/bin/python tests/data/make_pdp_checkpoint_v1.py
"""

from __future__ import annotations

import json
import shutil
import sys
import tempfile
from pathlib import Path

import torch

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE.parent))


def main() -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy

    from lerobot_pdp import PDPConfig
    from lerobot_pdp.episodes import read_episodes

    from synthetic import write_dataset

    out = HERE / "pdp_checkpoint_v1"
    with tempfile.TemporaryDirectory() as tmp:
        root = write_dataset(Path(tmp) / "synthetic", episodes_per_mode=3, seed=0)
        meta = LeRobotDatasetMetadata("local/synthetic", root=root)
        torch.manual_seed(0)
        policy = make_policy(PDPConfig(device="cpu", push_to_hub=False, down_dims=(16, 32),
                                              vae_hidden_dims=(64,), diffusion_step_embed_dim=32), ds_meta=meta)
        with torch.no_grad():  # weights that are not the initial ones, so a mix-up of tensors shows
            for p in policy.parameters():
                p.add_(0.05 * torch.randn_like(p))
        policy.eval()
        demo = {k: v.tolist() for k, v in read_episodes(root, ["observation.state", "observation.environment_state",
                                                              "action"], [5])[5].items() if k != "task"
                and not isinstance(v, int)}
        g = torch.Generator().manual_seed(1)
        obs_cond = torch.randn(2, policy.model.denoiser.obs_cond_dim, generator=g)
        z = torch.randn(2, policy.config.latent_dim, generator=g)
        noise = torch.randn(2, policy.config.horizon, policy.action_dim, generator=g)
        chunk = policy.generate(obs_cond, z, noise=noise)
        means = policy.mode_latents()
        fit = policy.fit_latent({k: torch.tensor(v) for k, v in demo.items()}, steps=3, seed=0)
        if out.exists():
            shutil.rmtree(out)
        policy.save_pretrained(out)
    expected = {"obs_cond": obs_cond.tolist(), "z": z.tolist(), "noise": noise.tolist(), "chunk": chunk.tolist(),
                "mode_latents": {str(k): v.tolist() for k, v in means.items()}, "demo": demo,
                "fit_z": fit.z.tolist(), "fit_z_init": fit.z_init.tolist()}
    (out / "expected.json").write_text(json.dumps(expected))
    print(f"wrote {out}: {sorted(p.name for p in out.iterdir())}")


if __name__ == "__main__":
    main()
