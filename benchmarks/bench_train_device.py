"""``lerobot-train`` step rate per device: PDP next to LeRobot ``diffusion`` (the benchmark's matched DP).

Each (policy, device) pair is one real ``lerobot-train`` process on the same generated reach-around dataset
(10 demonstrations per mode), built with the benchmark's own command line (``protocol.train_args``: same
batch, lr, backbone, sampler) with ``--policy.device`` set. The rate is measured from the wall-clock
arrival of LeRobot's own log lines, between the first and the last one, so start-up (imports, the
behavior bank, CUDA context) is excluded; LeRobot's ``updt_s`` / ``data_s`` averages are reported beside it.
Also reported: the median of the rates between consecutive log lines (``median_steps_per_s``), which a
one-off pause (a recompile for the epoch's last, smaller batch) does not move. A policy name ending in
``_compiled`` (``pdp_compiled``, ``dp_compiled``) trains that method with ``--policy.compile_model=true``
(and ``--compile-mode``); ``pdp_eager`` trains PDP with its CUDA-graph training step off
(``--policy.train_cuda_graphs=false``). Each run is repeated per ``--batch-sizes`` (samples/s = steps/s x
batch). One JSON line per run on stdout, then a ratio line per batch size.

    .venv/bin/python benchmarks/bench_train_device.py [--devices cpu cuda] [--steps 600] [--num-workers 4]
        [--policies pdp pdp_eager@cuda pdp_compiled@cuda dp dp_compiled] [--compile-mode reduce-overhead]
        [--batch-sizes 64 256]
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

LINE = re.compile(r"step:(\d+)(K?)\b.*?updt_s:([\d.]+).*?data_s:([\d.]+)")


def _replace(args: list[str], **flags: object) -> list[str]:
    """``args`` with ``--name=value`` flags set (replacing the benchmark's values)."""
    keys = {f"--{k.replace('__', '.')}" for k in flags}
    out = [a for a in args if a.partition("=")[0] not in keys]
    return out + [f"--{k.replace('__', '.')}={v}" for k, v in flags.items()]


def run_one(args: list[str], out_dir: Path, threads: int, log: Path) -> dict:
    from lerobot_pdp import column_views

    env = {**os.environ, "HF_HUB_OFFLINE": "1", "TQDM_DISABLE": "1", "OMP_NUM_THREADS": str(threads),
           "MKL_NUM_THREADS": str(threads), **column_views.child_env()}  # as the benchmark's trainings
    points: list[tuple[float, int, float, float]] = []
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        proc = subprocess.Popen([*args, f"--output_dir={out_dir}"], stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, env=env)
        assert proc.stdout is not None
        for line in proc.stdout:
            fh.write(line)
            m = LINE.search(line)
            if m:
                step = int(m.group(1)) * (1000 if m.group(2) else 1)
                points.append((time.perf_counter(), step, float(m.group(3)), float(m.group(4))))
        rc = proc.wait()
    if rc != 0 or len(points) < 2:
        tail = "".join(log.read_text().splitlines(keepends=True)[-30:])
        raise RuntimeError(f"lerobot-train failed ({rc}) or logged < 2 steps; see {log}\n{tail}")
    (ta, sa, _, _), (tb, sb, _, _) = points[0], points[-1]
    later = points[1:]  # the first window holds the warm-up
    gaps = sorted((b[1] - a[1]) / (b[0] - a[0]) for a, b in zip(points, later, strict=False) if b[0] > a[0])
    return {"steps_per_s": round((sb - sa) / (tb - ta), 2), "measured_steps": sb - sa,
            "median_steps_per_s": round(gaps[len(gaps) // 2], 2),
            "updt_s": round(sum(p[2] for p in later) / len(later), 4),
            "data_s": round(sum(p[3] for p in later) / len(later), 4),
            "wall_s": round(time.perf_counter() - t0, 1)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", nargs="+", default=["cpu"], help="torch devices, e.g. cpu cuda")
    ap.add_argument("--policies", nargs="+", default=["pdp", "dp"],
                    help="benchmark methods to train; NAME_compiled = NAME with compile_model on; NAME@DEVICE "
                         "trains NAME on that one of --devices only (e.g. pdp_compiled@cuda)")
    ap.add_argument("--compile-mode", default=None, help="--policy.compile_mode of the _compiled runs "
                    "(default: each policy's own, PDP 'default', LeRobot diffusion 'reduce-overhead')")
    ap.add_argument("--steps", type=int, default=600, help="training steps per run (< 1000: exact log counters)")
    ap.add_argument("--batch-sizes", type=int, nargs="+", default=None,
                    help="lerobot-train batch sizes, each a run (default: the benchmark's training batch)")
    ap.add_argument("--log-freq", type=int, default=50)
    ap.add_argument("--num-workers", type=int, default=4, help="LeRobot loader workers (all runs)")
    ap.add_argument("--cpu-threads", type=int, default=None,
                    help="torch threads of a CPU run (default: cores minus loader workers); GPU runs use 1")
    ap.add_argument("--dataset", type=Path, default=None, help="existing reach-around dataset (default: generate)")
    ap.add_argument("--logs", type=Path, default=None, help="keep each run's lerobot-train log in this folder")
    args = ap.parse_args(argv)
    only = {p.partition("@")[0]: p.partition("@")[2] for p in args.policies}
    stray = [f"{n}@{d}" for n, d in only.items() if d and d not in args.devices]
    if stray or len(only) != len(args.policies):
        ap.error(f"--policies {' '.join(args.policies)}: each policy once, and NAME@DEVICE needs DEVICE among "
                 f"--devices {' '.join(args.devices)}" + (f" ({stray[0]} is not)" if stray else ""))
    args.policies = list(only)

    import torch

    from lerobot_pdp.benchmark.machine import cpu_model
    from lerobot_pdp.benchmark.settings import TrainSettings, methods_for
    from lerobot_pdp.envs import get_suite_env
    from lerobot_pdp.envs.recording import make_dataset

    tmp = tempfile.TemporaryDirectory(prefix="bench-train-")
    work = Path(tmp.name)
    root = args.dataset or make_dataset("reach-around", work / "reach", scene=0, episodes_per_mode=10, seed=0,
                                        progress=False)
    logs = args.logs or work / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    cpus = os.cpu_count() or 1
    cpu_threads = args.cpu_threads or max(1, cpus - args.num_workers)
    methods = methods_for(get_suite_env("reach-around"))
    settings = TrainSettings(steps=args.steps)
    batch_sizes = args.batch_sizes or [settings.batch_size]
    env = {"cpu": cpu_model(), "cpus": cpus, "torch": torch.__version__, "num_workers": args.num_workers,
           "gpu": torch.cuda.get_device_name() if torch.cuda.is_available() else None}
    for bs in batch_sizes:
        _run_batch_size(args, only, methods, root, settings, bs, cpu_threads, work, logs, env)
    tmp.cleanup()
    return 0


def _run_batch_size(args, only, methods, root, settings, bs, cpu_threads, work, logs, env) -> None:
    """Every (policy, device) run at batch size ``bs``: one JSON line each, then their ratio line."""
    from lerobot_pdp.benchmark.training import train_args

    rates: dict[tuple[str, str], float] = {}
    for name in args.policies:  # policy by policy: a cut-short run still has each policy's device ratio
        for device in args.devices:
            if only[name] and device != only[name]:
                continue
            base, compiled, eager = name.removesuffix("_compiled").removesuffix("_eager"), \
                name.endswith("_compiled"), name.endswith("_eager")
            flags = {"policy__compile_model": "true"} if compiled else {}
            if compiled and args.compile_mode:
                flags["policy__compile_mode"] = args.compile_mode
            if eager:
                flags["policy__train_cuda_graphs"] = "false"
            cmd = _replace(train_args(methods[base], root, 0, settings, args.steps, device),
                           log_freq=args.log_freq, num_workers=args.num_workers, save_freq=10**9, batch_size=bs,
                           **flags)
            threads = cpu_threads if device == "cpu" else 1
            r = run_one(cmd, work / f"run_{name}_{device}_b{bs}", threads, logs / f"{name}_{device}_b{bs}.log")
            rates[(name, device)] = r["steps_per_s"]
            print(json.dumps({"bench": "lerobot_train_steps", "policy": name, "device": device,
                              "compile_mode": (args.compile_mode or "policy default") if compiled else None,
                              "torch_threads": threads, "batch_size": bs,
                              "samples_per_s": round(r["steps_per_s"] * bs, 1), **r, **env}), flush=True)
    ratio: dict[str, object] = {"bench": "lerobot_train_steps_ratio", "batch_size": bs}
    for name in args.policies:
        for device in args.devices:
            if device != "cpu" and (name, "cpu") in rates:
                ratio[f"{name}_{device}_over_cpu"] = round(rates[(name, device)] / rates[(name, "cpu")], 2)
    for device in args.devices:
        for sfx in ("", "_compiled"):
            if (f"pdp{sfx}", device) in rates and (f"dp{sfx}", device) in rates:
                ratio[f"pdp{sfx}_over_dp{sfx}_{device}"] = round(rates[(f"pdp{sfx}", device)]
                                                               / rates[(f"dp{sfx}", device)], 2)
        for variant in ("pdp_compiled", "pdp_eager"):
            if (variant, device) in rates and ("pdp", "cpu") in rates:
                ratio[f"{variant}_{device}_over_pdp_cpu"] = round(rates[(variant, device)] / rates[("pdp", "cpu")], 2)
        if ("pdp", device) in rates and ("pdp_eager", device) in rates:
            ratio[f"pdp_over_pdp_eager_{device}"] = round(rates[("pdp", device)] / rates[("pdp_eager", device)], 2)
    print(json.dumps(ratio), flush=True)


if __name__ == "__main__":
    sys.exit(main())
