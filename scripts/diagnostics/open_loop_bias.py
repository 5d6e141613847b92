"""Can any latent near the fitted one reproduce a demonstration's actions? Open-loop action bias on a grid.

On the demonstration's own observation windows (frames ``--frames A:B``), samples the policy's first
executed action for the benchmark's fitted z and for a grid of latents around it (one phase's latent
moved, the others kept), and prints the summed action error per dimension (policy - demonstration, in
action units: a summed velocity error is a position drift if the policy replayed the demonstration's
states). Separates "the fit found a poor z" (some grid latent has a far smaller bias) from "no nearby z
makes this route" (every latent trades one dimension's error for another's):

    python scripts/diagnostics/open_loop_bias.py runs/pick_place_centre/runs/pdp/seed1 \\
        --env pick-place --scene 3 --frames 78:123 --phase 1
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np
import torch

os.environ.setdefault("HF_HUB_OFFLINE", "1")


def main() -> None:
    from lerobot_pdp.benchmark.data import demo_episode, demo_root
    from lerobot_pdp.benchmark.training import load_run
    from lerobot_pdp.envs.suite import get_suite_env

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a benchmark run directory (<out>/runs/pdp/seed<S>)")
    ap.add_argument("--env", required=True)
    ap.add_argument("--scene", type=int, required=True)
    ap.add_argument("--frames", required=True, metavar="A:B", help="demonstration frames to score")
    ap.add_argument("--phase", type=int, default=0, help="which phase's latent the grid moves")
    ap.add_argument("--radius", type=float, default=1.0, help="grid half-width around the fitted latent")
    ap.add_argument("-n", type=int, default=9, help="grid points per latent axis")
    ap.add_argument("--samples", type=int, default=4, help="sampled chunks per frame and latent")
    args = ap.parse_args()

    policy, _, _ = load_run(args.run)
    cfg = policy.config
    if cfg.latent_dim != 2:
        ap.error(f"the grid is 2-D; this policy has latent_dim {cfg.latent_dim}")
    suite = get_suite_env(args.env)
    demo = demo_episode(demo_root(suite, args.run.parents[2], args.scene))
    win = policy.demo_windows(demo)  # the windows fit_latent scores, phases as the policy was trained
    a, _, b = args.frames.partition(":")
    if not (a.isdigit() and b.isdigit()):
        ap.error(f"--frames must be A:B with frame indices, got {args.frames!r}")
    frames = torch.arange(int(a), int(b))
    if len(frames) == 0 or frames[-1] >= len(demo["action"]):
        ap.error(f"--frames {args.frames} must be a non-empty range within the demonstration's {len(demo['action'])}")
    z_fit = torch.tensor(json.loads((args.run / "eval.json").read_text())["scenes"][str(args.scene)]["z"]).reshape(
        win.n_segments, cfg.latent_dim)
    if not 0 <= args.phase < win.n_segments:
        ap.error(f"--phase must be in 0..{win.n_segments - 1}")
    target = demo["action"][frames.numpy()]
    start = cfg.n_obs_steps - 1
    obs = win.obs_cond[frames].repeat(args.samples, 1)

    def bias(z: torch.Tensor) -> np.ndarray:
        chunk = policy.generate(obs, z[win.segment[frames]].repeat(args.samples, 1),
                                generator=torch.Generator().manual_seed(0))
        act = policy.stats.unnormalize("action", chunk[:, start]).numpy().reshape(args.samples, len(frames), -1)
        return (act.mean(0) - target).sum(0)

    print(json.dumps({"latent": "fitted", "z": z_fit[args.phase].tolist(), "bias": bias(z_fit).round(2).tolist(),
                      "demo_sum": target.sum(0).round(2).tolist()}))
    rows = []
    offsets = np.linspace(-args.radius, args.radius, args.n)
    for dx in offsets:
        for dy in offsets:
            z = z_fit.clone()
            z[args.phase] += torch.tensor([dx, dy], dtype=z.dtype)
            e = bias(z)
            rows.append((float(np.abs(e).sum()), z[args.phase].tolist(), e))
    for err, z, e in sorted(rows, key=lambda r: r[0])[:5]:
        print(json.dumps({"latent": "grid", "z": np.round(z, 2).tolist(), "abs_bias_sum": round(err, 2),
                          "bias": e.round(2).tolist()}))


if __name__ == "__main__":
    main()
