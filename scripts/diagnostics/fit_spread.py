"""How much does a shifted scene's success depend on the fit's randomness? Refit z with several fit seeds.

For each fitting setting (config fields such as fit_steps / fit_batch_size / fit_lr) and each fit seed,
fits z to the scene's demonstration exactly as the benchmark does (warm start from the encoder, weights
frozen), then rolls out with the benchmark's rollout seeds. One JSON line per (setting, fit seed), then a
summary line per setting (mean +- std of success over fit seeds):

    python scripts/diagnostics/fit_spread.py runs/pick_place_centre/runs/pdp/seed1 \\
        --env pick-place --scenes 3 --fit-seeds 5 --set fit_steps=100 fit_steps=300,fit_batch_size=64
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np

os.environ.setdefault("HF_HUB_OFFLINE", "1")


def _parse(setting: str) -> dict[str, float]:
    """'fit_steps=300,fit_batch_size=64' -> {field: number}."""
    out = {}
    for item in filter(None, setting.split(",")):
        field, _, value = item.partition("=")
        try:
            out[field] = float(value)
        except ValueError:
            raise SystemExit(f"--set {setting!r}: {field} needs a number, got {value!r}") from None
    return out


def main() -> None:
    from lerobot_pdp.benchmark.data import demo_episode, demo_root
    from lerobot_pdp.benchmark.rollouts import run_rollouts
    from lerobot_pdp.benchmark.training import load_run
    from lerobot_pdp.envs.suite import get_suite_env

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a benchmark run directory (<out>/runs/pdp/seed<S>)")
    ap.add_argument("--env", required=True)
    ap.add_argument("--scenes", nargs="+", type=int, default=[1, 2, 3])
    ap.add_argument("--fit-seeds", type=int, default=5, help="fit seeds 0..N-1 (the benchmark uses the run seed)")
    ap.add_argument("--set", nargs="+", default=[""], metavar="FIELD=V[,FIELD=V]",
                    help="fitting settings to compare (config fields); '' = the checkpoint's own")
    ap.add_argument("--rollouts", type=int, default=20)
    args = ap.parse_args()

    run_seed = int(args.run.name.removeprefix("seed"))
    suite = get_suite_env(args.env)
    policy, pre, post = load_run(args.run)
    defaults = {f: getattr(policy.config, f) for f in ("fit_steps", "fit_lr", "fit_batch_size", "fit_noise_samples")}
    for setting in args.set:
        fields = _parse(setting)
        for f, v in {**defaults, **fields}.items():
            if not hasattr(policy.config, f):
                ap.error(f"{f!r} is not a PDPConfig field")
            setattr(policy.config, f, type(defaults.get(f, v))(v))
        for scene in args.scenes:
            root = demo_root(suite, args.run.parents[2], scene)
            if not root.is_dir():
                ap.error(f"no scene-{scene} demonstration at {root}")
            demo = demo_episode(root)
            rates = []
            for fit_seed in range(args.fit_seeds):
                res = policy.fit_latent(demo, seed=fit_seed)
                batch = run_rollouts(suite, scene, policy, pre, post, args.rollouts, run_seed * 10_000 + scene)
                policy.set_latent(None)
                rates.append(batch.success_rate)
                print(json.dumps({"setting": setting or "default", "scene": scene, "fit_seed": fit_seed,
                                  "z": np.round(res.z.numpy(), 3).tolist(), "fit_loss": round(res.losses[-1], 4),
                                  "success": batch.success_rate, "collision": batch.collision_rate}), flush=True)
            print(json.dumps({"setting": setting or "default", "scene": scene, "summary": True,
                              "success_mean": float(np.mean(rates)), "success_std": float(np.std(rates))}),
                  flush=True)


if __name__ == "__main__":
    main()
