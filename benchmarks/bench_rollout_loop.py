"""``lerobot-rollout`` on the simulated robot: does the control loop keep its ``--fps`` from the start, with and
without an adaptation at start-up, on a quiet machine and beside one other CPU job?

A PDP checkpoint with reach-around's features (default network, untrained: timing does not depend on the
weights) drives ``pdp_sim`` in scene 0 for ``--episodes`` episodes at ``--fps``. With ``--policy.steer_dataset_root``
PDP fits z to a recorded episode when the policy is built, before LeRobot's loop starts. The robot's outcome
lines give each episode's pace (actions per second, the longest pause between two actions); the start-up is
the time from the process's start to its first action. The other job is a ``lerobot-train`` of PDP as a user
runs it (no thread variable, LeRobot's loader workers), already stepping.

    .venv/bin/python benchmarks/bench_rollout_loop.py [--fps 50] [--episodes 2] [--noise] [--out DIR]

One JSON line per run on stdout (and DIR/rollout_loop.jsonl with --out).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BIN = Path(sys.executable).parent


def _env() -> dict[str, str]:
    """A user's shell: no thread choice, offline, no display."""
    drop = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "DISPLAY", "WAYLAND_DISPLAY")
    return {**{k: v for k, v in os.environ.items() if k not in drop}, "HF_HUB_OFFLINE": "1", "TQDM_DISABLE": "1"}


def make_checkpoint(work: Path) -> tuple[Path, Path]:
    """(checkpoint, dataset): an untrained default PDP saved as lerobot-train saves one."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    from lerobot_pdp import PDPConfig
    from lerobot_pdp.envs.recording import make_dataset

    data = make_dataset("reach-around", work / "data", scene=0, episodes_per_mode=2, seed=0, progress=False)
    meta = LeRobotDatasetMetadata("local/ra", root=data)
    cfg = PDPConfig(device="cpu", push_to_hub=False, trace_dims=[0, 1, 2])
    policy = make_policy(cfg, ds_meta=meta)
    out = work / "ckpt"
    policy.save_pretrained(out)
    pre, post = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    return out, data


def rollout(ckpt: Path, work: Path, tag: str, fps: float, episodes: int, steer: list[str]) -> dict:
    outcomes = work / f"{tag}.jsonl"
    cmd = [str(BIN / "lerobot-rollout"), "--strategy.type=base", f"--policy.path={ckpt}", "--policy.device=cpu",
           *steer, "--robot.type=pdp_sim", "--robot.env=reach-around", "--robot.scene=0",
           f"--robot.episodes={episodes}", f"--robot.outcomes={outcomes}", f"--robot.calibration_dir={work / 'cal'}",
           f"--fps={fps}", "--duration=600", "--return_to_initial_position=false", "--play_sounds=false"]
    t0 = time.time()
    log = open(work / f"{tag}.log", "w")
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=_env())
    first_line_at = None
    while proc.poll() is None:
        if first_line_at is None and outcomes.is_file() and outcomes.read_text().strip():
            first_line_at = time.time()
        time.sleep(0.02)
    if proc.returncode != 0:
        raise RuntimeError(f"lerobot-rollout failed ({proc.returncode}); see {work / f'{tag}.log'}")
    lines = [json.loads(x) for x in outcomes.read_text().splitlines()]
    first = lines[0]
    first_action = (first_line_at or time.time()) - t0 - (first["steps"] - 1) / first["actions_per_s"]
    return {"episodes": [{k: d[k] for k in ("steps", "actions_per_s", "median_gap_s", "max_gap_s")} for d in lines],
            "startup_s": round(first_action, 1), "wall_s": round(time.time() - t0, 1)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fps", type=float, default=50)
    ap.add_argument("--episodes", type=int, default=2)
    ap.add_argument("--noise", action="store_true", help="also a start-up fit with one sampler noise per chunk")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)

    from lerobot_pdp import console
    from lerobot_pdp.benchmark.machine import cpu_model
    from lerobot_pdp.benchmark.settings import TrainSettings, methods_for
    from lerobot_pdp.benchmark.training import train_args
    from lerobot_pdp.envs import get_suite_env

    console.install()
    tmp = tempfile.TemporaryDirectory(prefix="bench-rollout-")
    work = Path(tmp.name)
    ckpt, data = make_checkpoint(work)
    variants = {"no adaptation": [],
                "fit at start-up": [f"--policy.steer_dataset_root={data}", "--policy.steer_episode_index=0"]}
    if args.noise:
        variants["fit + chunk noises at start-up"] = [*variants["fit at start-up"], "--policy.fit_noise=chunks"]
    other_cmd = [a for a in train_args(methods_for(get_suite_env("reach-around"))["pdp"], data, 0,
                                       TrainSettings(steps=10**6), 10**6) if not a.startswith("--num_workers")]
    records = []
    for beside in (False, True):
        other = None
        if beside:
            other_log = work / "other.log"
            other = subprocess.Popen([*other_cmd, f"--output_dir={work / 'other'}", "--log_freq=5"],
                                     stdout=open(other_log, "w"), stderr=subprocess.STDOUT, env=_env())
            while "step:" not in other_log.read_text():
                if other.poll() is not None:
                    raise RuntimeError(f"the other job failed; see {other_log}")
                time.sleep(1)
        try:
            for name, steer in variants.items():
                tag = f"{name.replace(' ', '_').replace('+', '')}_{'beside' if beside else 'quiet'}"
                rec = {"bench": "rollout_loop", "adaptation": name, "beside_other_job": beside, "fps": args.fps,
                       **rollout(ckpt, work, tag, args.fps, args.episodes, steer), "cpu": cpu_model()}
                records.append(rec)
                print(json.dumps(rec), flush=True)
        finally:
            if other is not None:
                other.kill()
                other.wait()
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "rollout_loop.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
