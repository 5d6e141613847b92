"""Can any carry latent take pick-place's object through scene 3's window? A grid sweep over the latent map.

Keeps the reach latent the benchmark fitted for scene 3 and sweeps the carry latent over an n x n grid
spanning the training carry clusters (+30 %), one rollout each, printing where each carry crosses
y = 0.18 (just before the wall at y = 0.25; the window's centre is x = 0.19, z = 0.59).

    python examples/diagnostics/pick_place_carry_sweep.py /work/runs/pick_place_full3/runs/pdp/seed0 -n 8
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

os.environ.setdefault("HF_HUB_OFFLINE", "1")


def main() -> None:
    from lerobot_pdp.benchmark.evaluation import run_rollouts
    from lerobot_pdp.benchmark.protocol import load_policy
    from lerobot_pdp.envs.suite import get_suite_env

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a benchmark run directory holding pretrained_model/ and eval.json")
    ap.add_argument("-n", type=int, default=8, help="grid points per latent axis")
    args = ap.parse_args()

    policy, pre, post = load_policy(args.run / "pretrained_model")
    z3 = np.asarray(json.loads((args.run / "eval.json").read_text())["scenes"]["3"]["z"], dtype=np.float32)
    carry = np.stack([np.asarray(m)[1] for m in policy.mode_latents().values()])
    lo, hi = carry.min(0), carry.max(0)
    lo, hi = lo - 0.3 * (hi - lo), hi + 0.3 * (hi - lo)
    suite = get_suite_env("pick-place")
    wins = 0
    for a in tqdm(np.linspace(lo[0], hi[0], args.n)):
        for b in np.linspace(lo[1], hi[1], args.n):
            z = z3.copy()
            z[1] = [a, b]
            policy.set_latent(torch.tensor(z))
            r = run_rollouts(suite, 3, policy, pre, post, 1, 7, batch_size=1).results[0]
            t = np.asarray(r.trace)
            k = int(np.argmax(t[:, 1] > 0.18)) if (t[:, 1] > 0.18).any() else len(t) - 1
            wins += r.success
            tqdm.write(f"carry z ({a:+.2f}, {b:+.2f}): x, z at y=0.18 = ({t[k, 0]:+.3f}, {t[k, 2]:.3f}) "
                       f"{'success' if r.success else 'collision' if r.collided else 'failure'}")
    print(f"{wins} successes of {args.n ** 2}; fitted scene-3 carry z = {z3[1].round(2).tolist()}")


if __name__ == "__main__":
    main()
