"""Can any carry latent take pick-place's object through scene 3's window? A grid sweep over the latent map.

Keeps the reach latent the benchmark fitted for scene 3 and sweeps the carry latent over an n x n grid
spanning the training carry clusters (+30 %), one rollout each, printing where each carry crosses
y = 0.18 (just before the wall at y = 0.25; the window's centre is x = 0.19, z = 0.59).

    python scripts/diagnostics/pick_place_carry_sweep.py runs/pick_place_full3/runs/pdp/seed0 -n 8

``--fitted N`` instead rolls out the benchmark's own fitted latent N times (the protocol's rollout seeds)
and prints each crossing next to the scene-3 demonstration's.
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
    from lerobot_pdp.benchmark.rollouts import run_rollouts
    from lerobot_pdp.benchmark.training import load_run
    from lerobot_pdp.envs.suite import get_suite_env

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a benchmark run directory holding pretrained_model/ and eval.json")
    ap.add_argument("-n", type=int, default=8, help="grid points per latent axis")
    ap.add_argument("--fitted", type=int, default=0, metavar="N", help="roll out the fitted latent N times instead")
    args = ap.parse_args()

    policy, pre, post = load_run(args.run)
    z3 = np.asarray(json.loads((args.run / "eval.json").read_text())["scenes"]["3"]["z"], dtype=np.float32)
    carry = np.stack([np.asarray(m)[1] for m in policy.mode_latents().values()])
    lo, hi = carry.min(0), carry.max(0)
    lo, hi = lo - 0.3 * (hi - lo), hi + 0.3 * (hi - lo)
    suite = get_suite_env("pick-place")
    if args.fitted:
        _fitted_crossings(args.run, suite, policy, pre, post, z3, args.fitted)
        return
    wins = 0
    for a in tqdm(np.linspace(lo[0], hi[0], args.n)):
        for b in np.linspace(lo[1], hi[1], args.n):
            z = z3.copy()
            z[1] = [a, b]
            policy.set_latent(torch.tensor(z))
            r = run_rollouts(suite, 3, policy, pre, post, 1, 7, batch_size=1).results[0]
            x, _, h = _crossing(np.asarray(r.trace))
            wins += r.success
            tqdm.write(f"carry z ({a:+.2f}, {b:+.2f}): x, z at y=0.18 = ({x:+.3f}, {h:.3f}) "
                       f"{'success' if r.success else 'collision' if r.collided else 'failure'}")
    print(f"{wins} successes of {args.n ** 2}; fitted scene-3 carry z = {z3[1].round(2).tolist()}")


def _crossing(trace: np.ndarray) -> np.ndarray:
    """The trace's first point past y = 0.18 (its last point if it never gets there)."""
    past = trace[:, 1] > 0.18
    return trace[int(np.argmax(past)) if past.any() else len(trace) - 1, :3]


def _fitted_crossings(run: Path, suite, policy, pre, post, z3: np.ndarray, n: int) -> None:
    from lerobot_pdp.benchmark.data import demo_episode, demo_root
    from lerobot_pdp.benchmark.rollouts import run_rollouts

    demo = demo_episode(demo_root(suite, run.parents[2], 3))
    x, _, h = _crossing(demo["observation.state"][:, :3])
    print(f"demonstration: x, z at y=0.18 = ({x:+.3f}, {h:.3f})")
    policy.set_latent(torch.tensor(z3))
    seed = int(run.name.removeprefix("seed"))
    for r in run_rollouts(suite, 3, policy, pre, post, n, seed * 10_000 + 3).results:
        x, _, h = _crossing(np.asarray(r.trace))
        print(f"fitted z: x, z at y=0.18 = ({x:+.3f}, {h:.3f}) "
              f"{'success' if r.success else 'collision' if r.collided else 'failure'}")


if __name__ == "__main__":
    main()
