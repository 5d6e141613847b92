"""``lerobot-rollout`` on the simulated robot: does the control loop keep its ``--fps`` from the start, with and
without an adaptation at start-up, with LeRobot's synchronous and real-time chunking engines, on a quiet machine
and beside one other CPU job? And does a trained PDP act as well under each engine?

By default a PDP checkpoint with reach-around's features (default network, untrained: timing does not depend on
the weights) drives ``pdp_sim`` in scene 0 for ``--episodes`` episodes at ``--fps``. With
``--policy.steer_dataset_root`` PDP fits z to a recorded episode when the policy is built, before LeRobot's loop
starts. ``--inference sync rtc`` runs each variant under ``--inference.type=sync`` (a chunk inside the step that
needs it) and ``--inference.type=rtc`` (chunks generated in a background thread, LeRobot's RTC defaults;
``rtc_lerobot_queue``: with LeRobot's own rule for the actions a new chunk drops). The
robot's outcome lines give each episode's pace (actions per second, the longest pause between two actions) and
its outcome (success, collision, the mode driven) and how smoothly chunks hand over (``action_step_median``,
``action_step_p90``, ``action_step_max``: the median over episodes of each episode's median, 90th percentile and
largest step of the commanded action, the gripper left out); the start-up is the time from the process's start to its first
action; ``cpu_s`` is the CPU time the ``lerobot-rollout`` process used, start-up included (``cores_busy``: per
second of its wall time). The other job is a ``lerobot-train`` of PDP as a user runs it (no thread variable, LeRobot's loader
workers), already stepping.

``--checkpoint`` takes a trained checkpoint instead (``--env``, ``--scene``, ``--dataset`` for the fit variant);
``--modes 0 1 ...`` adds one variant per steered mode (``--policy.steer_mode``), run on the quiet machine only.

    .venv/bin/python benchmarks/bench_rollout_loop.py [--fps 50] [--episodes 2] [--noise | --only-noise] [--inference sync rtc]
        [--rtc-queue-threshold N [N ...]] [--rtc-execution-horizon N [N ...]] [--checkpoint DIR --env reach-around --scene 0 [--dataset DIR] [--policy-flag=--policy.X=Y] [--modes 0 1 2 [--only-modes]]] [--no-beside] [--out DIR]

One JSON line per run on stdout (and DIR/rollout_loop.jsonl with --out).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from statistics import median

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


def rollout(ckpt: Path, work: Path, tag: str, fps: float, episodes: int, steer: list[str], env: str = "reach-around",
            scene: str = "0") -> dict:
    outcomes = work / f"{tag}.jsonl"
    cmd = [str(BIN / "lerobot-rollout"), "--strategy.type=base", f"--policy.path={ckpt}", "--policy.device=cpu",
           *steer, "--robot.type=pdp_sim", f"--robot.env={env}", f"--robot.scene={scene}",
           f"--robot.episodes={episodes}", f"--robot.outcomes={outcomes}", f"--robot.calibration_dir={work / 'cal'}",
           f"--fps={fps}", "--duration=1800", "--return_to_initial_position=false", "--play_sounds=false"]
    t0 = time.time()
    cpu0 = _children_cpu_s()
    log = open(work / f"{tag}.log", "w")
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=_env())
    first_line_at = None
    while proc.poll() is None:
        if first_line_at is None and outcomes.is_file() and outcomes.read_text().strip():
            first_line_at = time.time()
        time.sleep(0.02)
    wall, cpu = time.time() - t0, _children_cpu_s() - cpu0  # the other job is reaped later: this process only
    lines = [json.loads(x) for x in outcomes.read_text().splitlines()] if outcomes.is_file() else []
    if proc.returncode != 0 or len(lines) < episodes:  # LeRobot's RTC engine exits 0 after its thread failed
        raise RuntimeError(f"lerobot-rollout failed ({proc.returncode}, {len(lines)} of {episodes} episodes); "
                           f"see {work / f'{tag}.log'}")
    first = lines[0]
    first_action = (first_line_at or time.time()) - t0 - (first["steps"] - 1) / first["actions_per_s"]
    n = len(lines)
    step_keys = ("action_step_median", "action_step_p90", "action_step_max")
    return {"episodes": [{k: d[k] for k in ("steps", "actions_per_s", "median_gap_s", "max_gap_s", *step_keys)
                          if k in d}
                         for d in lines],
            "actions_per_s": round(sum(d["actions_per_s"] for d in lines) / n, 2),
            "max_gap_s": max(d["max_gap_s"] for d in lines),
            "success": sum(d["success"] for d in lines) / n, "collided": sum(d["collided"] for d in lines) / n,
            "modes": [d["mode"] for d in lines], "startup_s": round(first_action, 1), "wall_s": round(wall, 1),
            "cpu_s": round(cpu, 1), "cores_busy": round(cpu / wall, 2),
            **{k: round(median(d[k] for d in lines), 5) for k in step_keys if all(k in d for d in lines)}}


def _children_cpu_s() -> float:
    """CPU seconds (user + system) of this process's waited-for children."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


# rtc_lerobot_queue: LeRobot's own queue rule (drops ceil(latency * fps) actions per new chunk), for comparison
ENGINES = {"sync": [], "rtc": ["--inference.type=rtc"],
           "rtc_lerobot_queue": ["--inference.type=rtc", "--policy.rtc_consumed_delay=false"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fps", type=float, default=50)
    ap.add_argument("--episodes", type=int, default=2)
    ap.add_argument("--noise", action="store_true", help="also a start-up fit with one sampler noise per chunk")
    ap.add_argument("--only-noise", action="store_true",
                    help="with --dataset: only the start-up fit with chunk noises (no unadapted or z-only run)")
    ap.add_argument("--inference", nargs="+", choices=sorted(ENGINES), default=["sync"])
    ap.add_argument("--rtc-queue-threshold", type=int, nargs="+", default=None,
                    help="rtc: generate a new chunk when this many actions are left (LeRobot's default: 30); "
                         "several values run one variant each, interleaved")
    ap.add_argument("--rtc-execution-horizon", type=int, nargs="+", default=None,
                    help="rtc: how far the previous chunk's actions guide a new one (LeRobot's default: 10; 0: not "
                         "at all, the queue still replaced); several values run one variant each, interleaved")
    ap.add_argument("--checkpoint", type=Path, default=None, help="a trained checkpoint (default: an untrained one)")
    ap.add_argument("--env", default="reach-around")
    ap.add_argument("--scene", default="0")
    ap.add_argument("--dataset", type=Path, default=None, help="with --checkpoint: the fit variant's recording")
    ap.add_argument("--policy-flag", action="append", default=[],
                    help="a --policy.* flag added to every run (repeatable), e.g. --policy-flag=--policy.fit_objective=sample")
    ap.add_argument("--modes", type=int, nargs="*", default=[], help="steered modes, quiet only")
    ap.add_argument("--only-modes", action="store_true", help="run the steered modes only")
    ap.add_argument("--no-beside", action="store_true", help="skip the runs beside a training")
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
    if args.checkpoint is None:
        ckpt, data = make_checkpoint(work)
        args.env, args.scene = "reach-around", "0"
    else:
        ckpt, data = args.checkpoint, args.dataset
    variants = {"no adaptation": []}
    if data is not None:
        variants["fit at start-up"] = [f"--policy.steer_dataset_root={data}", "--policy.steer_episode_index=0"]
        if args.noise or args.only_noise:
            variants["fit + chunk noises at start-up"] = [*variants["fit at start-up"], "--policy.fit_noise=chunks"]
        if args.only_noise:
            variants = {"fit + chunk noises at start-up": variants["fit + chunk noises at start-up"]}
    # name: (flags, queue threshold, execution horizon; None = LeRobot's)
    engines: dict[str, tuple[list[str], int | None, int | None]] = {}
    for e in args.inference:
        if not e.startswith("rtc"):
            engines[e] = (ENGINES[e], None, None)
            continue
        for t in args.rtc_queue_threshold or [None]:
            for h in args.rtc_execution_horizon or [None]:
                name = e
                if t is not None and len(args.rtc_queue_threshold) > 1:
                    name += f"_t{t}"
                if h is not None and len(args.rtc_execution_horizon) > 1:
                    name += f"_h{h}"
                flags = [*ENGINES[e], *([] if t is None else [f"--inference.queue_threshold={t}"]),
                         *([] if h is None else [f"--inference.rtc.execution_horizon={h}"])]
                engines[name] = (flags, t, h)
    weights_sha = hashlib.sha256((Path(ckpt) / "model.safetensors").read_bytes()).hexdigest()[:16]
    steered = {f"mode {m}": [f"--policy.steer_mode={m}"] for m in args.modes}
    if args.only_modes:
        variants, args.no_beside = {}, True
    other_data = data if args.checkpoint is None else None
    records = []
    for beside in (False,) if args.no_beside else (False, True):
        other = None
        if beside:
            if other_data is None:
                from lerobot_pdp.envs.recording import make_dataset

                other_data = make_dataset("reach-around", work / "other_data", scene=0, episodes_per_mode=2, seed=0,
                                          progress=False)
            other_cmd = [a for a in train_args(methods_for(get_suite_env("reach-around"))["pdp"], other_data, 0,
                                               TrainSettings(steps=10**6), 10**6) if not a.startswith("--num_workers")]
            other_log = work / "other.log"
            other = subprocess.Popen([*other_cmd, f"--output_dir={work / 'other'}", "--log_freq=5"],
                                     stdout=open(other_log, "w"), stderr=subprocess.STDOUT, env=_env())
            while "step:" not in other_log.read_text():
                if other.poll() is not None:
                    raise RuntimeError(f"the other job failed; see {other_log}")
                time.sleep(1)
        try:
            for name, steer in {**variants, **({} if beside else steered)}.items():
                for engine, (engine_args, threshold, horizon) in engines.items():
                    tag = f"{name.replace(' ', '_').replace('+', '')}_{engine}_{'beside' if beside else 'quiet'}"
                    rec = {"bench": "rollout_loop", "adaptation": name, "inference": engine,
                           "inference_args": engine_args, "queue_threshold": threshold,
                           "execution_horizon": horizon,
                           "policy_flags": args.policy_flag,
                           "beside_other_job": beside, "fps": args.fps, "env": args.env, "scene": args.scene,
                           "checkpoint": "untrained" if args.checkpoint is None else weights_sha,
                           **rollout(ckpt, work, tag, args.fps, args.episodes,
                                     [*args.policy_flag, *steer, *engine_args], args.env, args.scene),
                           "cpu": cpu_model()}
                    records.append(rec)
                    print(json.dumps(rec), flush=True)
                    if args.out:  # every finished run kept, in case a later one fails
                        args.out.mkdir(parents=True, exist_ok=True)
                        (args.out / "rollout_loop.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
        finally:
            if other is not None:
                other.kill()
                other.wait()
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
