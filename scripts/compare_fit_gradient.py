"""Success after fit_latent with the autograd gradient vs the default finite-difference gradient.

    .venv/bin/python scripts/compare_fit_gradient.py --env pick-place --out runs/pick_place_full2

Uses a finished ``lerobot-pdp benchmark`` directory (its PDP seed-0 checkpoint and scene 1-3
demonstrations). For each scene and fitting seed: fit z (default steps) with each gradient, then
``--rollouts`` rollouts. Prints one JSON line per (scene, gradient).
"""

from __future__ import annotations

import argparse
import json
import os
import warnings
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
warnings.filterwarnings("ignore")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--env", required=True)
    ap.add_argument("--out", type=Path, required=True, help="a lerobot-pdp benchmark --out directory")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--rollouts", type=int, default=20)
    args = ap.parse_args()

    from lerobot_pdp.benchmark.data import demo_episode
    from lerobot_pdp.benchmark.rollouts import run_rollouts
    from lerobot_pdp.benchmark.training import load_policy
    from lerobot_pdp.envs.suite import get_suite_env

    suite = get_suite_env(args.env)
    policy, pre, post = load_policy(args.out / "runs" / "pdp" / "seed0" / "pretrained_model")
    for scene in (1, 2, 3):
        demo = demo_episode(args.out / "data" / f"{suite.scene_key}_scene{scene}_demo")
        for grad in ("autograd", "finite_difference"):
            policy.config.fit_gradient = grad
            rates = []
            for s in args.seeds:
                policy.fit_latent(demo, seed=s)
                rates.append(run_rollouts(suite, scene, policy, pre, post, args.rollouts, 1000 + s).success_rate)
            print(json.dumps({"bench": "fit_gradient_success", "env": args.env, "scene": scene, "gradient": grad,
                              "success_per_fit_seed": rates}), flush=True)


if __name__ == "__main__":
    main()
