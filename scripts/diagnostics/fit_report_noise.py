"""How noisy is the fit report? ``FitResult.fit_error``'s spread over seeds, uniform vs stratified steps.

For a benchmark run (state-only PDP), scores each shifted scene's demonstration at the latent the benchmark
fitted (``eval.json``) with ``latent_fitting.demonstration_error`` for ``--seeds`` seeds at each ``--chunks``
budget, with uniform and with stratified diffusion steps, and prints one JSON line per scene: the spread
(std over seeds) relative to a precise reference (``--reference-draws`` draws per window). The default
``PDPConfig.fit_report_chunks`` was chosen from these lines on the validation runs.

    python scripts/diagnostics/fit_report_noise.py runs/kitchen_val/runs/pdp/seed100 --env kitchen-microwave
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np
import torch

os.environ.setdefault("HF_HUB_OFFLINE", "1")


def main() -> None:
    from run_args import add_run_args, eval_record, scene_demo

    from lerobot_pdp.benchmark.training import load_run
    from lerobot_pdp.envs.suite import get_suite_env
    from lerobot_pdp.latent_fitting import demonstration_error

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_run_args(ap, scene=False)
    ap.add_argument("--chunks", type=int, nargs="+", default=[64, 128, 256, 512], help="report budgets compared")
    ap.add_argument("--seeds", type=int, default=12, help="seeds per budget and step scheme")
    ap.add_argument("--reference-draws", type=int, default=64, help="draws per window of the precise reference")
    args = ap.parse_args()
    if args.seeds < 2 or args.reference_draws < 1 or min(args.chunks) < 1:
        ap.error(f"--seeds must be >= 2, --reference-draws and --chunks >= 1, got {args.seeds}, "
                 f"{args.reference_draws}, {args.chunks}")
    meta = eval_record(ap, args.run, "its fitted latents are read from there")
    suite = get_suite_env(args.env)
    policy, _, _ = load_run(args.run)
    policy.eval()
    denoiser, schedule = policy.model.denoiser, policy.model.noise_schedule
    for scene, entry in meta["scenes"].items():
        if entry is None or entry.get("z") is None:
            continue
        windows = policy.demo_windows(scene_demo(ap, suite, args.run, int(scene) if scene.isdigit() else scene))
        z = torch.tensor(entry["z"], dtype=torch.float32).reshape(windows.n_segments, -1)
        n = len(windows.segment)
        ref = demonstration_error(denoiser, schedule, windows, z, chunks=args.reference_draws * n, seed=10_000)
        row = {"scene": scene, "windows": n, "reference": round(ref, 5)}
        for spread in (False, True):
            for chunks in args.chunks:
                values = [demonstration_error(denoiser, schedule, windows, z, chunks, seed=s, spread_steps=spread)
                          for s in range(args.seeds)]
                row[f"{'stratified' if spread else 'uniform'} {chunks}"] = round(float(np.std(values) / ref), 3)
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
