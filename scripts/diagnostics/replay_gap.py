"""How closely does the adaptation replay the demonstration, and where does it leave it?

For a benchmark run (``runs/pdp/seed<k>``) and a scene that ships a demonstration route, adapts PDP exactly as
the benchmark does (its frozen adaptation: z, then one sampler noise per chunk where validation chose it) and
rolls out in the scene with the protocol's evaluation seeds. For each rollout it reports success, collision,
the first step where the end effector is more than ``--tol`` from the demonstration's position at the same step
and both positions there, and the trace's extent per axis (min / max) beside the demonstration's: a replay that
*shrinks* a wide excursion toward the training routes shows up as a smaller extent, and a window it clips as a
collision just inside the demonstration's widest point.

    python scripts/diagnostics/replay_gap.py runs/pp_val_pdp/runs/pdp/seed100 --env pick-place --scene val4 \\
        --rollouts 10 --out replay_val4.jsonl
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np

os.environ.setdefault("HF_HUB_OFFLINE", "1")


def main() -> None:
    from run_args import add_run_args, eval_record, scene_demo

    from lerobot_pdp.benchmark.evaluation import adapt
    from lerobot_pdp.benchmark.rollouts import run_rollouts
    from lerobot_pdp.benchmark.search_curves import evaluation_seed, is_quick_run
    from lerobot_pdp.benchmark.settings import Method, frozen_for
    from lerobot_pdp.benchmark.training import load_run
    from lerobot_pdp.envs.suite import get_suite_env

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_run_args(ap)
    ap.add_argument("--rollouts", type=int, default=10)
    ap.add_argument("--tol", type=float, default=0.05, help="distance (m) that counts as leaving the demonstration")
    ap.add_argument("--out", type=Path, help="JSON lines file (default: print only)")
    args = ap.parse_args()
    if args.rollouts < 1:
        ap.error(f"--rollouts must be >= 1, got {args.rollouts}")
    seed = eval_record(ap, args.run, "its seed is read from there")["seed"]
    suite = get_suite_env(args.env)
    policy, pre, post = load_run(args.run)
    policy.eval()
    demo = scene_demo(ap, suite, args.run, args.scene)
    kwargs = dict(frozen_for(suite.name, is_quick_run(args.run.parents[2]), "pdp").get("adapt", {}))
    actor, info = adapt(Method("pdp", "pdp"), policy, pre, demo, seed, **kwargs)
    batch = run_rollouts(suite, args.scene, actor, pre, post, args.rollouts, evaluation_seed(seed, args.scene))
    dims = list(suite.trace_dims)[:3]
    ref = demo["observation.state"][:, dims]
    rows = [{"what": "demonstration", "steps": len(ref), "min": ref.min(0).round(4).tolist(),
             "max": ref.max(0).round(4).tolist(), "adaptation": kwargs, "fit_error_ratio": info.get("fit_error_ratio")}]
    for i, r in enumerate(batch.results):
        tr = r.trace[:, : len(dims)]
        n = min(len(tr), len(ref))
        gap = np.linalg.norm(tr[:n] - ref[:n], axis=1)
        off = int(np.argmax(gap > args.tol)) if (gap > args.tol).any() else None
        rows.append({"what": f"rollout {i}", "success": r.success, "collided": r.collided, "steps": len(tr),
                     "min": tr.min(0).round(4).tolist(), "max": tr.max(0).round(4).tolist(),
                     "leaves_at_step": off, "at": None if off is None else tr[off].round(4).tolist(),
                     "demonstration_there": None if off is None else ref[off].round(4).tolist(),
                     "end": tr[-1].round(4).tolist()})
    text = "".join(json.dumps(row) + "\n" for row in rows)
    print(text, end="")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)


if __name__ == "__main__":
    main()
