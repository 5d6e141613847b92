"""Does PDP gain from DP's adaptation on top of its own? Fit z, then one sampler noise per executed chunk.

DP's validated camera adaptation optimises one initial DDIM noise per executed chunk so that its sampler
reproduces the demonstration (``baselines.adapt_dp_noise(per_chunk=True)``). This applies the same to PDP
after its own fit: z as the benchmark fits it (the checkpoint's settings, the run's seed), then, z fixed,
one noise x_j per chunk of the demonstration optimised through PDP's own DDIM chain (Adam, DP's defaults:
100 steps at 0.05, 32 windows per step), rolled out with the noises in order (``FixedNoisePolicy``).
One JSON line per scene: success with z alone and with z + noises, the protocol's rollout seeds.

    python scripts/diagnostics/pdp_chunk_noise.py runs/ra_camera_val_pdp/runs/pdp/seed100 --env reach-around \\
        --camera oblique --sampler 5 trailing --scene val2 --rollouts 20
"""

from __future__ import annotations

import argparse
import json
import os

import torch

os.environ.setdefault("HF_HUB_OFFLINE", "1")


def fit_chunk_noise(policy, windows, z: torch.Tensor, steps: int, lr: float, batch_size: int, seed: int) -> torch.Tensor:
    """One initial noise per executed chunk [C, horizon, A] whose DDIM chains under ``z`` [M, d_z] reproduce
    the demonstration's chunks (masked MSE, as PDP's sampled-chunk objective); weights untouched."""
    cfg, den, sched = policy.config, policy.model.denoiser, policy.model.noise_schedule
    consts = den.weight_constants(list(range(sched.num_train_timesteps)))
    n = len(windows.segment)
    chunk_of = torch.arange(n) // cfg.n_action_steps
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(int(chunk_of.max()) + 1, cfg.horizon, windows.actions.shape[-1], generator=g).requires_grad_(True)
    with torch.no_grad():
        obs_mod = den.obs_modulation(consts, windows.obs_cond)
        gain, shift = den.latent_terms(consts, z.reshape(windows.n_segments, -1).float())
    is_pad = windows.is_pad if cfg.do_mask_loss_for_padding else torch.zeros_like(windows.is_pad)
    opt = torch.optim.Adam([x], lr=lr)
    for _ in range(steps):
        idx = torch.randperm(n, generator=g)[:batch_size]
        seg, base, xx = windows.segment[idx], obs_mod[idx], x[chunk_of[idx]]
        for k, k_prev in sched.steps(cfg.num_inference_steps):
            mod = consts["step"][k] + base
            if shift is not None:
                mod = mod + shift[seg] if gain is None else torch.addcmul(shift[seg], gain[seg], mod)
            eps = den.forward_cached(xx, den.split_modulation(consts, mod), fast_conv=False)
            xx = sched.ddim_step(eps, k, k_prev, xx)
        mask = (~is_pad[idx]).unsqueeze(-1).float()
        loss = ((xx - windows.actions[idx]).pow(2) * mask).sum() / (mask.sum() * xx.shape[-1]).clamp_min(1)
        (x.grad,) = torch.autograd.grad(loss, x)
        opt.step()
    return x.detach()


def main() -> None:
    from run_args import add_run_args, eval_record, scene_demo

    from lerobot_pdp.benchmark.baselines import FixedNoisePolicy
    from lerobot_pdp.benchmark.rollouts import run_rollouts
    from lerobot_pdp.benchmark.settings import scene_seed_offset
    from lerobot_pdp.benchmark.training import load_policy, load_run
    from lerobot_pdp.envs.suite import get_suite_env

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_run_args(ap)
    ap.add_argument("--camera", default=None, help="the camera of a camera-variant run (e.g. oblique)")
    ap.add_argument("--image-size", type=int, default=64)
    ap.add_argument("--rollouts", type=int, default=20)
    ap.add_argument("--noise-steps", type=int, default=100)
    ap.add_argument("--noise-lr", type=float, default=0.05)
    ap.add_argument("--latent", choices=("fit", "zero"), default="fit",
                    help="z under the noises: the benchmark's fit, or the prior's centre (is z needed at all?)")
    ap.add_argument("--sampler", nargs=2, metavar=("STEPS", "GRID"), default=None,
                    help="DDIM steps and grid (e.g. 5 trailing; default: as the run's eval.json)")
    args = ap.parse_args()
    if args.rollouts < 1 or args.noise_steps < 1:
        ap.error(f"--rollouts and --noise-steps must be >= 1, got {args.rollouts}, {args.noise_steps}")
    seed = eval_record(ap, args.run, "its seed is read from there")["seed"]
    suite = get_suite_env(args.env)
    if args.camera:
        suite = suite.with_camera(args.camera, args.image_size)
    policy, pre, post = (load_run(args.run) if args.sampler is None else
                         load_policy(args.run / "pretrained_model", int(args.sampler[0]), timestep_spacing=args.sampler[1]))
    policy.eval()
    demo = scene_demo(ap, suite, args.run, args.scene)
    rollout_seed = seed * 10_000 + scene_seed_offset(args.scene)

    res = policy.fit_latent(demo, init="encoder", seed=seed)  # the benchmark's adaptation; z now active
    if args.latent == "zero":
        res.z = torch.zeros_like(res.z)
        policy.set_latent(res.z)
    z_only = run_rollouts(suite, args.scene, policy, pre, post, args.rollouts, rollout_seed)
    windows = policy.demo_windows(demo)
    with torch.enable_grad():
        noise = fit_chunk_noise(policy, windows, res.z, args.noise_steps, args.noise_lr, 32, seed)
    both = run_rollouts(suite, args.scene, FixedNoisePolicy(policy, noise), pre, post, args.rollouts, rollout_seed)
    policy.set_latent(None)
    print(json.dumps({"scene": str(args.scene), "latent": args.latent, "chunks": len(noise), "z success": z_only.success_rate,
                      "z + chunk noise success": both.success_rate, "z + chunk noise collision": both.collision_rate,
                      "rollouts": args.rollouts}), flush=True)


if __name__ == "__main__":
    main()
