"""The robot path against the benchmark path on one checkpoint: does steering from a recorded demonstration
reach the goal as often under ``lerobot-rollout`` on the simulated robot as under ``lerobot-eval``?

Three real processes, nothing in-process:

1. ``lerobot-record`` (``pdp_sim`` robot, ``pdp_waypoints`` operator on the scene's own way-points) writes ONE
   demonstration of the scene;
2. ``lerobot-rollout --strategy.type=base`` fits z to it at start-up and runs ``--episodes`` episodes on
   ``pdp_sim`` (one outcome line per episode);
3. ``lerobot-eval --env.type=pdp_<env>`` fits z to the same recording at start-up and runs as many episodes.

Both fit with the checkpoint's own fitting settings plus ``--policy-flag`` overrides (given to both). The
outcome is one JSON file with both success rates; nothing is chosen from it.

    .venv/bin/python scripts/compare_deploy_paths.py --ckpt runs/.../pretrained_model --env reach-around \
        --scene val3 --episodes 20 --out runs/deploy_paths [--teleop-seed 0] [--policy-flag=--policy.fit_noise=chunks]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from lerobot_pdp.atomic import write_text_atomic

ENV_TYPES = {"reach-around": "pdp_reach_around", "avoiding": "pdp_avoiding", "pick-place": "pdp_pick_place",
             "kitchen-microwave": "pdp_kitchen_microwave"}


def _cli(name: str) -> str:
    """The console script next to this interpreter (the venv's), else on PATH."""
    here = Path(sys.executable).with_name(name)
    return str(here) if here.is_file() else name


def _run(args: list[str], log: Path, env: dict[str, str]) -> float:
    t0 = time.time()
    print(f"[deploy-paths] {Path(args[0]).name} ... (log {log})", flush=True)
    with log.open("w") as f:
        proc = subprocess.run(args, stdout=f, stderr=subprocess.STDOUT, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"{Path(args[0]).name} failed with exit code {proc.returncode}; see {log}")
    return time.time() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ckpt", type=Path, required=True, help="a PDP pretrained_model folder")
    ap.add_argument("--env", default="reach-around", choices=sorted(ENV_TYPES))
    ap.add_argument("--scene", default="val3",
                    help="scene index or validation scene name (default val3: a validation scene whose wall blocks "
                         "the training routes; the test scenes 1-3 are the benchmark's)")
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--fps", type=int, default=50)
    ap.add_argument("--teleop-seed", type=int, default=0,
                    help="the pdp_waypoints operator's seed (its speed and jitter along the way-points; default 0, "
                         "the operator's own)")
    ap.add_argument("--out", type=Path, required=True, help="output folder (an earlier output of this script is replaced)")
    ap.add_argument("--policy-flag", action="append", default=[],
                    help="a --policy.* override given to both lerobot-rollout and lerobot-eval (repeatable)")
    args = ap.parse_args(argv)
    if args.episodes < 1:
        raise SystemExit("--episodes must be >= 1")
    if not (args.ckpt / "config.json").is_file():
        raise SystemExit(f"{args.ckpt} has no config.json: expected a PDP pretrained_model folder")
    if args.out.exists() and any(args.out.iterdir()):
        if not (args.out / "record.log").is_file():  # only an earlier run of this script is replaced
            raise SystemExit(f"--out {args.out} exists and is not an earlier output of this script: choose another")
        shutil.rmtree(args.out)
    args.out.mkdir(parents=True, exist_ok=True)
    out = args.out.resolve()
    env = {**os.environ, "HF_LEROBOT_HOME": str(out / "home"), "HF_HUB_OFFLINE": "1", "DISPLAY": "",
           "WAYLAND_DISPLAY": ""}
    robot = [f"--robot.env={args.env}", f"--robot.scene={args.scene}", f"--robot.calibration_dir={out / 'cal'}"]
    demo = out / "demo"
    seconds = {"record": _run(
        [_cli("lerobot-record"), "--robot.type=pdp_sim", *robot, "--teleop.type=pdp_waypoints",
         "--teleop.waypoints=scene", f"--teleop.seed={args.teleop_seed}", f"--teleop.calibration_dir={out / 'cal'}",
         "--dataset.repo_id=local/demo",
         f"--dataset.root={demo}", "--dataset.num_episodes=1", f"--dataset.fps={args.fps}",
         "--dataset.episode_time_s=30", "--dataset.reset_time_s=0.5", "--dataset.video=false",
         "--dataset.push_to_hub=false", "--play_sounds=false", "--display_data=false"], out / "record.log", env)}
    steer = [f"--policy.path={args.ckpt.resolve()}", f"--policy.steer_dataset_root={demo}",
             "--policy.steer_episode_index=0", "--policy.device=cpu", *args.policy_flag]
    outcomes = out / "rollout.jsonl"
    seconds["rollout"] = _run(
        [_cli("lerobot-rollout"), "--strategy.type=base", *steer, "--robot.type=pdp_sim", *robot,
         f"--robot.episodes={args.episodes}", f"--robot.outcomes={outcomes}", f"--fps={args.fps}",
         f"--duration={60 * args.episodes}", "--return_to_initial_position=false", "--play_sounds=false"],
        out / "rollout.log", env)
    lines = [json.loads(x) for x in outcomes.read_text().splitlines() if x.strip()]
    if len(lines) != args.episodes:
        raise SystemExit(f"{outcomes}: {len(lines)} outcome lines, expected {args.episodes}; see {out / 'rollout.log'}")
    eval_dir = out / "eval"
    seconds["eval"] = _run(
        [_cli("lerobot-eval"), *steer, f"--env.type={ENV_TYPES[args.env]}", f"--env.scene={args.scene}",
         f"--eval.n_episodes={args.episodes}", f"--eval.batch_size={min(args.episodes, 10)}",
         f"--output_dir={eval_dir}", "--seed=1000"], out / "eval.log", env)
    info = json.loads((eval_dir / "eval_info.json").read_text())
    rollout_rate = sum(bool(d["success"]) for d in lines) / len(lines)
    eval_rate = float(info["overall"]["pc_success"]) / 100
    res = {"checkpoint": os.path.relpath(args.ckpt.resolve(), Path.cwd()), "env": args.env, "scene": args.scene,
           "episodes": args.episodes, "teleop_seed": args.teleop_seed, "policy_flags": args.policy_flag,
           "lerobot_rollout": {"success": rollout_rate, "collided": sum(bool(d["collided"]) for d in lines) / len(lines)},
           "lerobot_eval": {"success": eval_rate}, "difference_points": round(100 * (rollout_rate - eval_rate), 1),
           "seconds": {k: round(v, 1) for k, v in seconds.items()}}
    write_text_atomic(out / "deploy_paths.json", json.dumps(res, indent=1))
    print(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
