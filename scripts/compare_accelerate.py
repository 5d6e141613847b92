"""One-process against two-process (accelerate) training of PDP at the same steps: do the checkpoints steer alike?

Trains PDP twice on an env's scene-0 benchmark dataset with the benchmark's own ``lerobot-train`` arguments
(``training.train_args``, the quick budget unless ``--steps``): once as one process, once under
``accelerate launch --multi_gpu --num_processes 2`` with ``--policy.device=cpu`` (gloo on the CPU; accelerate's
``--cpu`` launcher would start a single process) and half the batch per process, so that both runs take the
same optimizer steps over the same number of samples per step and the same lr schedule. Then scene 0 for
both checkpoints, each mode steered by its mean latent as in the benchmark: success and steer accuracy,
written to one JSON file. Nothing is chosen from the result.

    .venv/bin/python scripts/compare_accelerate.py --env reach-around --out runs/accelerate_compare
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from lerobot_pdp import column_views
from lerobot_pdp.atomic import write_text_atomic
from lerobot_pdp.benchmark.data import ensure_dataset
from lerobot_pdp.benchmark.evaluation import evaluate_scene0, summarize_rollouts
from lerobot_pdp.benchmark.settings import SETTINGS, methods_for
from lerobot_pdp.benchmark.training import TRAIN_THREADS_ENV, load_policy, train_args
from lerobot_pdp.envs.suite import get_suite_env


def _train(args: list[str], out: Path, log: Path) -> tuple[Path, float]:
    """Train into a temporary folder beside ``out``, renamed to ``out`` only when a checkpoint was written
    (a failed or interrupted run leaves its log, never half a run folder); the checkpoint and the wall time."""
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}-", dir=out.parent))
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "TQDM_DISABLE": "1", **TRAIN_THREADS_ENV, **column_views.child_env()}
    print(f"[accelerate-compare] training -> {out} (log {log})", flush=True)
    t0 = time.time()
    try:
        with log.open("w") as f:
            rc = subprocess.run([*args, f"--output_dir={tmp / 'train'}"], stdout=f, stderr=subprocess.STDOUT,
                                env=env).returncode
        if rc != 0:
            raise SystemExit(f"training failed with exit code {rc}; see {log}")
        if not (tmp / "train" / "checkpoints" / "last" / "pretrained_model" / "model.safetensors").is_file():
            raise SystemExit(f"training finished without a checkpoint; see {log}")
        os.replace(tmp / "train", out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out / "checkpoints" / "last" / "pretrained_model", time.time() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--env", default="reach-around", choices=sorted(SETTINGS))
    ap.add_argument("--steps", type=int, default=None, help="training steps (default: the env's quick budget)")
    ap.add_argument("--rollouts", type=int, default=40, help="scene-0 rollouts per checkpoint")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)

    suite = get_suite_env(a.env)
    settings = SETTINGS[suite.name][1]
    steps = a.steps or settings.steps
    dirs = (a.out / "one_process", a.out / "two_processes")
    taken = [str(d) for d in dirs if d.exists()]
    if taken:  # before anything runs: the script never replaces a run folder
        raise SystemExit(f"{', '.join(taken)} exist (an earlier run of this script?): remove them or choose "
                         "another --out")
    a.out.mkdir(parents=True, exist_ok=True)
    data = ensure_dataset(suite, a.out, settings)  # the benchmark's scene-0 dataset, whatever the training seed
    method = methods_for(suite)["pdp"]
    one = train_args(method, data, a.seed, settings, steps)
    half = train_args(method, data, a.seed, replace(settings, batch_size=settings.batch_size // 2), steps)
    accelerate = str(Path(sys.executable).with_name("accelerate"))
    two = [accelerate, "launch", "--multi_gpu", "--num_processes=2", "--num_machines=1", "--mixed_precision=no",
           "--dynamo_backend=no", "--main_process_port=0", *half]
    runs = {"1 process": (one, dirs[0]), "2 processes": (two, dirs[1])}
    result: dict = {"env": suite.name, "steps": steps, "seed": a.seed, "rollouts": a.rollouts,
                    "batch_per_step": settings.batch_size, "runs": {}}
    for name, (args, out) in runs.items():
        ckpt, seconds = _train(args, out, a.out / f"{out.name}.log")
        policy, pre, post = load_policy(ckpt)
        batch = evaluate_scene0(suite, method, policy, pre, post, a.rollouts, a.seed * 10_000)
        summary = summarize_rollouts(batch, suite.n_modes, with_modes=True)
        result["runs"][name] = {"train_seconds": round(seconds, 1), **summary,
                                "checkpoint": str(ckpt.relative_to(a.out))}
        print(f"[accelerate-compare] {name}: success {summary['success']:.0%}, steer accuracy "
              f"{summary.get('steer_accuracy', float('nan')):.0%}, coverage {summary.get('coverage')}", flush=True)
    write_text_atomic(a.out / "accelerate_compare.json", json.dumps(result, indent=1))
    print(f"[accelerate-compare] {a.out / 'accelerate_compare.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
