"""Steer a trained PDP checkpoint in the reach-around env: per-mode latents, then one-demo adaptation.

    # 1. data + training (LeRobot's own loop)
    lerobot-pdp make-dataset --env reach-around --scene 0 --episodes-per-mode 10 --out data/ra
    lerobot-train --policy.type=pdp --policy.trace_dims='[0,1,2]' --policy.push_to_hub=false \
        --policy.optimizer_lr=1e-3 --policy.embedding_lr=1e-3 --dataset.repo_id=local/ra \
        --dataset.root=data/ra --output_dir=runs/pdp --steps=3000 --batch_size=64
    # 2. one demonstration in scene 3 (a wall with a window no training mode passes through)
    lerobot-pdp make-dataset --env reach-around --scene 3 --waypoints scene --episodes-per-mode 1 --out data/ra_s3
    # 3. this script
    python examples/steer_reach_around.py runs/pdp/checkpoints/last/pretrained_model data/ra_s3
"""

from __future__ import annotations

import sys

from lerobot_pdp.benchmark.rollouts import run_rollouts
from lerobot_pdp.benchmark.training import load_policy
from lerobot_pdp.envs import get_suite_env


def main(ckpt: str, demo_root: str) -> None:
    suite = get_suite_env("reach-around")
    policy, pre, post = load_policy(ckpt)  # policy + its saved LeRobot processors
    for mode, z in policy.mode_latents().items():
        policy.set_latent(z)
        r = run_rollouts(suite, 0, policy, pre, post, n=5, seed=mode)
        print(f"scene 0, mode {mode} ({suite.mode_names[mode]}): success {r.success_rate:.0%}, "
              f"landed in modes {[x.mode for x in r.results]}")
    res = policy.fit_latent((demo_root, 0))  # weights frozen; only z moves
    print(f"fitted z = {res.z.tolist()} from warm start {res.z_init.tolist()} (L_fit {res.losses[-1]:.4f})")
    r = run_rollouts(suite, 3, policy, pre, post, n=10, seed=0)
    print(f"scene 3 after fitting: success {r.success_rate:.0%}")


if __name__ == "__main__":
    main(*sys.argv[1:3])
