"""Is a benchmark training that was killed and resumed the same run as one that ran through?

For each method, two trainings with the same arguments on one small reach-around dataset: one runs through;
the other is killed (SIGKILL, the whole process group) as soon as its first checkpoint is written and
called again, so that ``lerobot-train --resume`` goes on from that checkpoint; a third runs through again
(the control: is training deterministic at all?). The outcome is one JSON file with the largest absolute
weight difference between the final checkpoints per method (0.0: bit-identical). Nothing is chosen from it.

    .venv/bin/python scripts/check_resume.py --out runs/resume_check [--methods bc pdp] [--steps 40]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from lerobot_pdp.atomic import write_text_atomic


def _train_code(method: str, data: Path, run_dir: Path, steps: int, every: int) -> str:
    """One benchmark training (``training.train_method``) with checkpoints every ``every`` steps."""
    return ("from pathlib import Path\nfrom lerobot_pdp.benchmark import training\n"
            "from lerobot_pdp.benchmark.settings import TrainSettings, methods_for\n"
            "from lerobot_pdp.envs import get_suite_env\n"
            f"training.RESUME_EVERY = {every}\n"
            f"training.train_method(methods_for(get_suite_env('reach-around'))[{method!r}], Path({str(data)!r}), "
            f"Path({str(run_dir)!r}), 0, TrainSettings(steps={steps}, batch_size=8), {steps})\n")


def _max_weight_difference(a: Path, b: Path) -> float:
    from safetensors.torch import load_file

    wa, wb = (load_file(str(d / "pretrained_model" / "model.safetensors")) for d in (a, b))
    if wa.keys() != wb.keys():
        raise ValueError(f"{a} and {b} hold different tensors")
    return max((wa[k].double() - wb[k].double()).abs().max().item() for k in wa)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--methods", nargs="+", default=["bc", "pdp"])
    parser.add_argument("--steps", type=int, default=40, help="training steps; killed after the first half")
    args = parser.parse_args()
    from lerobot_pdp.envs.recording import make_dataset

    data = args.out / "data"
    if not data.exists():
        make_dataset("reach-around", data, scene=0, episodes_per_mode=1, seed=0, progress=False)
    env = {**os.environ, "LEROBOT_PDP_TRAIN_WORKERS": "0", "HF_HUB_OFFLINE": "1"}
    every = args.steps // 2
    result: dict = {"env": "reach-around", "episodes_per_mode": 1, "steps": args.steps, "batch_size": 8,
                    "killed_after_step": every, "methods": {}}
    for method in args.methods:
        straight, again, resumed = (args.out / f"{method}_{k}" for k in ("straight", "again", "resumed"))
        for d in (straight, again, resumed):
            shutil.rmtree(d, ignore_errors=True)
        for d in (straight, again):
            print(f"[resume] {method}: training straight through ({d.name})", flush=True)
            subprocess.run([sys.executable, "-c", _train_code(method, data, d, args.steps, every)], env=env,
                           check=True)
        print(f"[resume] {method}: training, killed after step {every}, resumed", flush=True)
        proc = subprocess.Popen([sys.executable, "-c", _train_code(method, data, resumed, args.steps, every)],
                                env=env, start_new_session=True)
        step_file = resumed / ".train-partial" / "out" / "checkpoints" / "last" / "training_state" / "training_step.json"
        while proc.poll() is None and not step_file.exists():
            time.sleep(0.02)
        if proc.poll() is not None:
            raise RuntimeError(f"{method}: the training to be killed ended (code {proc.returncode}) before its first "
                               f"checkpoint ({step_file})")
        os.killpg(proc.pid, signal.SIGKILL)  # the trainer and its lerobot-train process
        proc.wait()
        subprocess.run([sys.executable, "-c", _train_code(method, data, resumed, args.steps, every)], env=env,
                       check=True)
        info = json.loads((resumed / "train_info.json").read_text())
        diff, control = _max_weight_difference(straight, resumed), _max_weight_difference(straight, again)
        result["methods"][method] = {"resumed_from_step": info.get("resumed_from_step"),
                                     "max_abs_weight_difference": diff,
                                     "max_abs_weight_difference_two_straight_runs": control}
        print(f"[resume] {method}: resumed from step {info.get('resumed_from_step')}, largest weight difference "
              f"{diff:.3g} (two straight runs: {control:.3g})", flush=True)
    write_text_atomic(args.out / "resume_check.json", json.dumps(result, indent=1))
    print(f"[resume] wrote {args.out / 'resume_check.json'}")


if __name__ == "__main__":
    main()
