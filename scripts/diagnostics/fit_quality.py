"""Does the fit itself tell when steering will fail? L_fit at the fitted latent, next to the training episodes'.

For a benchmark run (state-only PDP), computes L_fit, the fitting objective, on every window of each shifted
scene's demonstration at the latent the benchmark fitted (``eval.json``; ``--noise-draws`` (k, eps) draws
per window, the same draws everywhere), and the same quantity for ``--train-episodes`` training episodes at
their own encoder latents (what a demonstration the policy was trained on scores). Prints one JSON line per
scene (with its success from ``eval.json``) and one for the training episodes. A demonstration that no latent
reproduces scores well above the training episodes.

    python scripts/diagnostics/fit_quality.py runs/kitchen_val/runs/pdp/seed100 --env kitchen-microwave
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np
import torch

os.environ.setdefault("HF_HUB_OFFLINE", "1")


def main() -> None:
    from run_args import add_run_args, eval_record

    from lerobot_pdp.benchmark.data import demo_episode, demo_root, scene0_root
    from lerobot_pdp.benchmark.training import load_run
    from lerobot_pdp.envs.suite import get_suite_env
    from lerobot_pdp.episodes import read_episodes
    from lerobot_pdp.latent_fitting import demonstration_error

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_run_args(ap, scene=False)
    ap.add_argument("--train-episodes", type=int, default=10, help="training episodes scored at their own latents")
    ap.add_argument("--noise-draws", type=int, default=16, help="(k, eps) draws per window")
    args = ap.parse_args()
    if args.train_episodes < 1 or args.noise_draws < 1:
        ap.error(f"--train-episodes and --noise-draws must be >= 1, got {args.train_episodes}, {args.noise_draws}")
    meta = eval_record(ap, args.run, "its fitted latents are read from there")
    suite = get_suite_env(args.env)
    out = args.run.parents[2]
    policy, _, _ = load_run(args.run)
    policy.eval()

    def score(episode: dict, z: torch.Tensor) -> float:
        """What fit_latent reports as FitResult.fit_error, with --noise-draws draws per window."""
        windows = policy.demo_windows(episode)
        return demonstration_error(policy.model.denoiser, policy.model.noise_schedule, windows,
                                   z.reshape(windows.n_segments, -1), chunks=args.noise_draws * len(windows.segment))

    train_root = scene0_root(suite, out)
    keys = ["observation.state", "observation.environment_state", "action"]
    n_eps = json.loads((train_root / "meta" / "info.json").read_text())["total_episodes"]
    ids = np.linspace(0, n_eps - 1, min(args.train_episodes, n_eps)).round().astype(int).tolist()
    train = []
    for ep in read_episodes(train_root, keys, ids).values():
        ep = {k: v for k, v in ep.items() if isinstance(v, np.ndarray)}
        train.append(score(ep, policy.encode(ep)))
    ref = {"training episodes": len(train), "L_fit mean": round(float(np.mean(train)), 5),
           "L_fit max": round(float(np.max(train)), 5)}
    print(json.dumps(ref), flush=True)
    for scene, entry in meta["scenes"].items():
        if entry is None or entry.get("z") is None:
            continue
        demo = demo_episode(demo_root(suite, out, int(scene) if scene.isdigit() else scene))
        value = score(demo, torch.tensor(entry["z"], dtype=torch.float32))
        print(json.dumps({"scene": scene, "L_fit": round(value, 5), "ratio to training mean": round(value / ref["L_fit mean"], 2),
                          "success": entry.get("success", entry.get("mean"))}), flush=True)


if __name__ == "__main__":
    main()
