"""Re-evaluate a trained PDP benchmark run with inference-time config fields changed (no retraining).

Scene 0 rolls out each mode's mean latent as the benchmark does; scenes 1-3 reuse the latent the benchmark
fitted there (``eval.json``). One JSON line per setting, e.g. denoising steps or executed actions per chunk:

    python scripts/diagnostics/reevaluate_with.py runs/pick_place_full3/runs/pdp/seed0 \\
        --env pick-place --set num_inference_steps=5 num_inference_steps=10 num_inference_steps=20
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import torch

os.environ.setdefault("HF_HUB_OFFLINE", "1")


def main() -> None:
    from lerobot_pdp.benchmark.evaluation import evaluate_scene0
    from lerobot_pdp.benchmark.rollouts import run_rollouts
    from lerobot_pdp.benchmark.settings import methods_for
    from lerobot_pdp.benchmark.training import load_run
    from lerobot_pdp.envs.suite import get_suite_env

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a benchmark run directory holding pretrained_model/ and eval.json")
    ap.add_argument("--env", required=True)
    ap.add_argument("--set", nargs="+", required=True, metavar="FIELD=INT", help="one evaluation per setting")
    ap.add_argument("--scenes", nargs="+", type=int, default=[0, 1, 3])
    ap.add_argument("--rollouts", type=int, nargs=2, default=[40, 20], metavar=("SCENE0", "SHIFTED"))
    args = ap.parse_args()

    policy, pre, post = load_run(args.run)
    fitted = json.loads((args.run / "eval.json").read_text())["scenes"]
    suite = get_suite_env(args.env)
    for setting in args.set:
        field, _, value = setting.partition("=")
        if not hasattr(policy.config, field) or not value.lstrip("-").isdigit():
            raise SystemExit(f"--set {setting!r}: expected FIELD=INT with FIELD a PDPConfig field "
                             f"(e.g. n_action_steps=4, num_inference_steps=10)")
        setattr(policy.config, field, int(value))
        policy.reset()  # queues are sized by n_action_steps
        out: dict[str, float | str] = {"set": setting}
        for scene in args.scenes:
            if scene == 0:
                batch = evaluate_scene0(suite, methods_for(suite)["pdp"], policy, pre, post, args.rollouts[0], 0)
            else:
                policy.set_latent(torch.tensor(fitted[str(scene)]["z"], dtype=torch.float32))
                batch = run_rollouts(suite, scene, policy, pre, post, args.rollouts[1], 5)
            out[f"scene{scene}"] = batch.success_rate
        policy.set_latent(None)
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
