"""Steer a trained PDP checkpoint in the reach-around env: per-mode latents, then one-demo adaptation.

Only LeRobot's public API around PDP's steering calls: the checkpoint's own processors, LeRobot's env factory
(``--env.type=pdp_reach_around``, with the checkpoint's cameras for a camera checkpoint) and its evaluation loop,
as ``lerobot-eval`` runs them.

    # 1. data + training (LeRobot's own loop)
    lerobot-pdp make-dataset --env reach-around --scene 0 --episodes-per-mode 10 --out data/ra
    lerobot-train --policy.type=pdp --policy.trace_dims='[0,1,2]' --policy.push_to_hub=false \
        --policy.optimizer_lr=1e-3 --policy.embedding_lr=1e-3 --dataset.repo_id=local/ra \
        --dataset.root=data/ra --output_dir=runs/pdp --steps=3000 --batch_size=64
    # 2. one demonstration in validation scene val3 (a wall whose window no training mode passes through)
    lerobot-pdp make-dataset --env reach-around --scene val3 --waypoints scene --episodes-per-mode 1 --seed 1 \
        --out data/ra_val3
    # 3. this script
    python examples/steer_reach_around.py runs/pdp/checkpoints/last/pretrained_model data/ra_val3
"""

from __future__ import annotations

import sys

from lerobot.envs.factory import make_env, make_env_config, make_env_pre_post_processors
from lerobot.policies.factory import make_pre_post_processors
from lerobot.scripts.lerobot_eval import eval_policy
from lerobot.utils.import_utils import register_third_party_plugins

from lerobot_pdp import PDPPolicy

register_third_party_plugins()  # what LeRobot's CLIs do first: the lab's envs (pdp_*) are a plugin beside PDP


def success(policy: PDPPolicy, processors: tuple, scene: int | str, episodes: int, seed: int) -> float:
    """Success % of ``episodes`` rollouts in ``scene`` under the policy's active latent, as lerobot-eval counts it."""
    env_cfg = make_env_config("pdp_reach_around", scene=scene, **camera_flags(policy))
    envs = make_env(env_cfg, n_envs=episodes)
    env = next(iter(next(iter(envs.values())).values()))  # one suite, one task: one vector env
    env_pre, env_post = make_env_pre_post_processors(env_cfg, policy.config)
    try:
        info = eval_policy(env, policy, env_pre, env_post, *processors, n_episodes=episodes, start_seed=seed)
    finally:
        env.close()
    return info["aggregated"]["pc_success"]


def camera_flags(policy: PDPPolicy) -> dict[str, str]:
    """The env's cameras for a camera checkpoint (``--env.camera=oblique,top --env.image_size=48``): every camera the
    policy was trained on, at its size; none for a state-only one."""
    cams = {key.rsplit(".", 1)[-1]: tuple(ft.shape[-2:]) for key, ft in policy.config.image_features.items()}
    if not cams:
        return {}
    sizes = set(cams.values())
    if len(sizes) > 1:
        raise ValueError(f"the env renders every camera at one size; this checkpoint's cameras differ: {cams}")
    (h, w), = sizes
    return {"camera": ",".join(cams), "image_size": f"{h}x{w}"}


def main(ckpt: str, demo_root: str) -> None:
    policy = PDPPolicy.from_pretrained(ckpt)
    # the checkpoint's own processors: observations normalised in, actions back in the env's units out
    processors = make_pre_post_processors(policy.config, pretrained_path=ckpt)
    modes = policy.mode_latents()
    for mode, z in modes.items():
        policy.set_latent(z)
        print(f"scene 0, mode {mode} ({modes.names.get(mode, '')}): success {success(policy, processors, 0, 5, mode):.0f}%")
    # weights frozen: z, then one sampler noise per chunk of the demonstration (no latent alone makes val3's route)
    res = policy.fit_latent((demo_root, 0), noise="chunks")
    print(f"fitted z = {[round(v, 4) for v in res.z.tolist()]} from warm start "
          f"{[round(v, 4) for v in res.z_init.tolist()]} (L_fit {res.losses[-1]:.4f}), "
          f"{len(res.noise)} chunk noises")
    print(f"scene val3 after fitting: success {success(policy, processors, 'val3', 10, 0):.0f}%")

if __name__ == "__main__":
    main(*sys.argv[1:3])
