"""Does PDP gain from DP's adaptation on top of its own? Fit z, then one sampler noise per executed chunk.

DP's validated camera adaptation optimises one initial DDIM noise per executed chunk so that its sampler
reproduces the demonstration (``baselines.adapt_dp_noise(per_chunk=True)``). This applies the same to PDP
after its own fit: z as the benchmark fits it (the checkpoint's settings, the run's seed), then, z fixed,
one noise x_j per chunk of the demonstration optimised through PDP's own DDIM chain (Adam, DP's defaults:
100 steps at 0.05, 32 windows per step), rolled out with the noises in order: ``fit_latent(noise="chunks")``.
One JSON line per scene: success with z alone and with z + noises, the protocol's rollout seeds.

    python scripts/diagnostics/pdp_chunk_noise.py runs/ra_camera_val_pdp/runs/pdp/seed100 --env reach-around \\
        --camera oblique --sampler 5 trailing --scene val2 --rollouts 20
"""

from __future__ import annotations

import argparse
import json
import os

os.environ.setdefault("HF_HUB_OFFLINE", "1")


def main() -> None:
    from run_args import add_run_args, eval_record, scene_demo

    from lerobot_pdp.benchmark.rollouts import run_rollouts
    from lerobot_pdp.benchmark.settings import scene_seed_offset
    from lerobot_pdp.benchmark.training import load_policy, load_run
    from lerobot_pdp.envs.suite import get_suite_env

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_run_args(ap)
    ap.add_argument("--camera", default=None, help="the camera of a camera-variant run (e.g. oblique)")
    ap.add_argument("--image-size", type=int, default=64)
    ap.add_argument("--rollouts", type=int, default=20)
    ap.add_argument("--latent", choices=("fit", "zero"), default="fit",
                    help="z under the noises: the benchmark's fit, or the prior's centre (is z needed at all?)")
    ap.add_argument("--sampler", nargs=2, metavar=("STEPS", "GRID"), default=None,
                    help="DDIM steps and grid (e.g. 5 trailing; default: as the run's eval.json)")
    args = ap.parse_args()
    if args.rollouts < 1:
        ap.error(f"--rollouts must be >= 1, got {args.rollouts}")
    seed = eval_record(ap, args.run, "its seed is read from there")["seed"]
    suite = get_suite_env(args.env)
    if args.camera:
        suite = suite.with_camera(args.camera, args.image_size)
    policy, pre, post = (load_run(args.run) if args.sampler is None else
                         load_policy(args.run / "pretrained_model", int(args.sampler[0]), timestep_spacing=args.sampler[1]))
    policy.eval()
    demo = scene_demo(ap, suite, args.run, args.scene)
    rollout_seed = seed * 10_000 + scene_seed_offset(args.scene)

    # the product's option: z as the benchmark fits it (or z = 0), then the noises; both active after the fit
    steps, init = (None, "encoder") if args.latent == "fit" else (0, "zero")
    res = policy.fit_latent(demo, steps=steps, init=init, seed=seed, noise="chunks")
    both = run_rollouts(suite, args.scene, policy, pre, post, args.rollouts, rollout_seed)
    policy.set_latent(res.z)  # z alone (set_latent drops the noises)
    z_only = run_rollouts(suite, args.scene, policy, pre, post, args.rollouts, rollout_seed)
    policy.set_latent(None)
    print(json.dumps({"scene": str(args.scene), "latent": args.latent, "chunks": len(res.noise), "z success": z_only.success_rate,
                      "z + chunk noise success": both.success_rate, "z + chunk noise collision": both.collision_rate,
                      "rollouts": args.rollouts}), flush=True)


if __name__ == "__main__":
    main()
