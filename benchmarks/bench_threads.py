"""Torch's CPU threads and PDP: a ``lerobot-train`` step rate and a ``fit_latent`` wall time, alone and beside
one other CPU job, with torch's default threads (``--policy.cpu_threads=0``, what PDP did before choosing)
and with PDP's default (``cpu_threads`` unset: half the usable cores).

Everything runs as a user would run it: no ``OMP_NUM_THREADS`` in the environment, LeRobot's default loader
workers (4), the reach-around dataset (10 demonstrations per mode) with the benchmark's PDP command line. The
other job is a second ``lerobot-train`` of PDP under the same setting, started first and already stepping.
The step rate is measured from the wall-clock arrival of LeRobot's log lines (start-up excluded) over at
most ``--seconds``; the fit is one ``fit_latent`` of ``--fit-steps`` steps on demonstration 0 (weights
untrained: timing does not depend on them), timed in-process after a one-step warm-up.

    .venv/bin/python benchmarks/bench_threads.py [--seconds 60] [--fit-steps 100] [--out DIR]

One JSON line per measurement on stdout (and in DIR/threads.jsonl with --out), then the ratio lines.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

LINE = re.compile(r"step:(\d+)(K?)\b")
SETTINGS = {"torch_default": "0", "pdp_default": None}  # --policy.cpu_threads (None: not given)

FIT = """
import sys, time, torch
from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
from lerobot.policies.factory import make_policy
from lerobot_pdp import PDPConfig
root, threads, steps = sys.argv[1], sys.argv[2], int(sys.argv[3])
meta = LeRobotDatasetMetadata("local/reach", root=root)
kw = {} if threads == "none" else {"cpu_threads": int(threads)}
policy = make_policy(PDPConfig(device="cpu", push_to_hub=False, **kw), ds_meta=meta)
policy.fit_latent((root, 0), steps=1)
t = time.perf_counter()
policy.fit_latent((root, 0), steps=steps)
print("FIT", time.perf_counter() - t, torch.get_num_threads())
"""


def _user_env() -> dict[str, str]:
    """This environment without any thread choice, as a user's shell."""
    return {**{k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")},
            "HF_HUB_OFFLINE": "1", "TQDM_DISABLE": "1"}


def _train_cmd(root: Path, out: Path, threads: str | None, steps: int) -> list[str]:
    from lerobot_pdp.benchmark.settings import TrainSettings, methods_for
    from lerobot_pdp.benchmark.training import train_args
    from lerobot_pdp.envs import get_suite_env

    method = methods_for(get_suite_env("reach-around"))["pdp"]
    keep = ("--num_workers", "--log_freq", "--save_freq", "--steps")
    args = [a for a in train_args(method, root, 0, TrainSettings(steps=steps), steps)
            if a.partition("=")[0] not in keep]
    args += [f"--steps={steps}", "--log_freq=5", f"--save_freq={10**9}", "--num_workers=4", f"--output_dir={out}"]
    return args + ([f"--policy.cpu_threads={threads}"] if threads is not None else [])


def _start(cmd: list[str], log: Path) -> subprocess.Popen:
    return subprocess.Popen(cmd, stdout=open(log, "w"), stderr=subprocess.STDOUT, env=_user_env(), text=True)


def _wait_for_steps(log: Path, proc: subprocess.Popen, timeout: float = 600) -> None:
    """Until the other job has logged two steps (it is past start-up and stepping)."""
    t0 = time.time()
    while len(LINE.findall(log.read_text())) < 2:
        if proc.poll() is not None or time.time() - t0 > timeout:
            raise RuntimeError(f"the other job did not start stepping; see {log}")
        time.sleep(1)


def measure_train(cmd: list[str], log: Path, seconds: float) -> dict:
    """Steps/s of one lerobot-train between its first log line and the last within ``seconds`` of it."""
    points: list[tuple[float, int]] = []
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=_user_env(), text=True)
        assert proc.stdout is not None
        for line in proc.stdout:
            fh.write(line)
            m = LINE.search(line)
            if m:
                points.append((time.perf_counter(), int(m.group(1)) * (1000 if m.group(2) else 1)))
                if points[-1][0] - points[0][0] >= seconds:
                    proc.kill()
                    break
        proc.wait()
    if len(points) < 2:
        raise RuntimeError(f"lerobot-train logged < 2 steps; see {log}")
    (ta, sa), (tb, sb) = points[0], points[-1]
    return {"steps_per_s": round((sb - sa) / (tb - ta), 3), "measured_steps": sb - sa,
            "measured_s": round(tb - ta, 1), "wall_s": round(time.perf_counter() - t0, 1)}


def measure_fit(root: Path, threads: str | None, steps: int) -> dict:
    proc = subprocess.run([sys.executable, "-c", FIT, str(root), threads or "none", str(steps)],
                          capture_output=True, text=True, env=_user_env(), timeout=3600)
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("FIT ")]
    if proc.returncode != 0 or not line:
        raise RuntimeError(f"fit failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    _, secs, n = line[-1].split()
    return {"fit_s": round(float(secs), 2), "fit_steps": steps, "torch_threads": int(n)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60, help="measuring window of each training")
    ap.add_argument("--fit-steps", type=int, default=100)
    ap.add_argument("--out", type=Path, default=None, help="also write threads.jsonl and the logs here")
    args = ap.parse_args(argv)

    import torch

    from lerobot_pdp import console
    from lerobot_pdp.benchmark.machine import cpu_model
    from lerobot_pdp.cpu_threads import usable_cores
    from lerobot_pdp.envs.recording import make_dataset

    console.install()  # LeRobot's torchcodec fallback in one line
    tmp = tempfile.TemporaryDirectory(prefix="bench-threads-")
    work = Path(tmp.name)
    logs = args.out or work
    logs.mkdir(parents=True, exist_ok=True)
    root = make_dataset("reach-around", work / "reach", scene=0, episodes_per_mode=10, seed=0, progress=False)
    machine = {"cpu": cpu_model(), "usable_cores": usable_cores(), "torch": torch.__version__}
    records: list[dict] = []

    def emit(rec: dict) -> None:
        records.append(rec)
        print(json.dumps({**rec, **machine}), flush=True)

    for name, threads in SETTINGS.items():
        for beside in (False, True):
            other = None
            tag = f"{name}_{'beside' if beside else 'alone'}"
            try:
                if beside:
                    other_log = logs / f"other_{tag}.log"
                    other = _start(_train_cmd(root, work / f"other_{tag}", threads, 10**6), other_log)
                    _wait_for_steps(other_log, other)
                r = measure_train(_train_cmd(root, work / f"train_{tag}", threads, 10**6),
                                  logs / f"train_{tag}.log", args.seconds)
                emit({"bench": "lerobot_train", "setting": name, "beside_other_job": beside, **r})
                emit({"bench": "fit_latent", "setting": name, "beside_other_job": beside,
                      **measure_fit(root, threads, args.fit_steps)})
            finally:
                if other is not None:
                    other.kill()
                    other.wait()
    rate = {(r["bench"], r["setting"], r["beside_other_job"]): r.get("steps_per_s") or r.get("fit_s")
            for r in records}
    for beside in (False, True):
        emit({"bench": "ratio", "beside_other_job": beside,
              "train_pdp_default_over_torch_default": round(rate["lerobot_train", "pdp_default", beside]
                                                            / rate["lerobot_train", "torch_default", beside], 2),
              "fit_torch_default_over_pdp_default": round(rate["fit_latent", "torch_default", beside]
                                                          / rate["fit_latent", "pdp_default", beside], 2)})
    if args.out:
        (args.out / "threads.jsonl").write_text("".join(json.dumps({**r, **machine}) + "\n" for r in records))
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
