"""New-chunk latency of ``select_action``: PDP vs LeRobot ``diffusion`` (matched and default), side by side.

Every timed call generates a whole new action chunk: the action queue is cleared before it (the
observation history stays filled, as mid-episode). The timed call is ``policy.select_action(batch)`` on an
already normalised batch of one observation (B = 1), i.e. what ``lerobot-eval`` spends per new chunk minus
the pre/post-processors (reported separately as ``pipeline_median_ms``). Policies:

- ``pdp``: default ``PDPConfig`` (trace_dims [0, 1, 2]) built on a small generated reach-around dataset;
  ``--inference-steps`` DDIM steps (default: PDPConfig's, 5) of the FiLM 1-D U-Net (32, 64, 128);
- ``dp_matched``: LeRobot ``diffusion`` with ``dp_config_matching`` (same U-Net sizes, horizon, K = 20,
  the same DDIM steps) -- the benchmark's DP baseline;
- ``dp_default``: LeRobot ``diffusion`` with its default config (248 M parameters, horizon 64, 100 DDPM
  steps), ~20 s per chunk here, so only ``--default-dp-calls`` calls are timed.

``--device cuda`` times the same calls on a GPU (each call waits for the GPU before the clock stops) and adds
``pdp_eager``: PDP with its CUDA-graph replay switched off, i.e. the kernels launched one by one.
``--profile`` (CUDA) adds, per policy, the kernels one new chunk launches and the summed time they run
(``torch.profiler`` over 20 calls): a chunk far longer than its kernels waits on launches, not arithmetic.
``--compile`` adds ``pdp_compiled`` and ``dp_compiled``: each policy with its ``compile_model`` on (PDP: the
denoiser's step fused by torch.compile, still replayed from PDP's graph on CUDA; DP: LeRobot's own
``torch.compile(unet, mode="reduce-overhead")``). Compilation happens in the warm-up calls.

Weights are freshly initialised: latency does not depend on their values. The small policies are timed in
interleaved rounds so that load changes on the machine hit them equally. One JSON line per policy on
stdout, then a ratio line.

    .venv/bin/python benchmarks/bench_select_action.py [--threads 1] [--calls 200] [--default-dp-calls 3]
        [--inference-steps 20]   # the benchmark's sampler (protocol.TrainSettings.inference_steps)
        [--device cuda] [--compile]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np


def _stats(times_s: list[float]) -> dict:
    t = np.asarray(times_s) * 1e3
    return {"median_ms": round(float(np.median(t)), 3), "p90_ms": round(float(np.percentile(t, 90)), 3),
            "mean_ms": round(float(t.mean()), 3), "calls": len(t)}


def _observation(root: Path) -> dict:
    import torch

    from lerobot_pdp.episodes import read_episodes

    ep = read_episodes(root, ["observation.state", "observation.environment_state"], [0])[0]
    return {k: torch.as_tensor(ep[k][10:11], dtype=torch.float32)
            for k in ("observation.state", "observation.environment_state")}


def _build(cfg, meta):
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    policy = make_policy(cfg, ds_meta=meta)
    policy.eval()
    pre, post = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    return policy, pre, post


def _sync(device: str) -> None:
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _new_chunk_call(policy, batch):
    import torch

    policy._queues["action"].clear()
    device = str(policy.config.device)
    _sync(device)
    t = time.perf_counter()
    with torch.inference_mode():
        policy.select_action(batch)
    _sync(device)
    return time.perf_counter() - t


def _kernel_profile(policy, batch, calls: int = 20) -> dict:
    """GPU operations (kernels, copies) per new chunk and their summed GPU time (ms), from ``torch.profiler`` over ``calls`` chunks."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(calls):
            _new_chunk_call(policy, batch)
    gpu = [e for e in prof.events() if e.device_type.name == "CUDA"]  # kernels, copies and memsets
    return {"gpu_ops_per_chunk": round(len(gpu) / calls, 1),
            "gpu_busy_ms_per_chunk": round(sum(e.device_time_total for e in gpu) / calls / 1e3, 3)}


def _pipeline_call(policy, pre, post, obs):
    import torch

    policy._queues["action"].clear()
    t = time.perf_counter()
    with torch.inference_mode():
        post(policy.select_action(pre(dict(obs))))  # the postprocessor returns the action on the CPU
    return time.perf_counter() - t


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1,
                    help="torch intra-op threads for every policy (default 1, as in our rollouts/CI)")
    ap.add_argument("--calls", type=int, default=200, help="timed new-chunk calls per small policy")
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--default-dp-calls", type=int, default=3,
                    help="timed calls of the default 248 M-parameter DP (~20 s each); 0 = skip it")
    ap.add_argument("--dataset", type=Path, default=None,
                    help="existing reach-around LeRobotDataset (default: generate 2 demos/mode in a temp dir)")
    ap.add_argument("--inference-steps", type=int, default=5,
                    help="DDIM steps of pdp and dp_matched (default 5, the latency target's setting; "
                         "PDPConfig's default is 20)")
    ap.add_argument("--device", default="cpu", help="torch device of every policy (cpu, cuda)")
    ap.add_argument("--compile", action="store_true",
                    help="also time pdp_compiled and dp_compiled (compile_model=True; compiles for ~1 min)")
    ap.add_argument("--profile", action="store_true",
                    help="CUDA: also count each policy's kernels per new chunk and their summed GPU time")
    args = ap.parse_args(argv)

    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    warnings.filterwarnings("ignore")
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

    from lerobot_pdp import PDPConfig
    from lerobot_pdp.benchmark.baselines import dp_config_kwargs
    from lerobot_pdp.benchmark.machine import cpu_model
    from lerobot_pdp.envs.recording import make_dataset

    torch.set_num_threads(args.threads)
    tmp = None
    root = args.dataset
    if root is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench-select-")
        root = make_dataset(env="reach-around", out=Path(tmp.name) / "reach", scene=0, episodes_per_mode=2,
                            seed=0, progress=False)
    meta = LeRobotDatasetMetadata("local/reach", root=root)
    obs = _observation(root)
    torch.manual_seed(0)

    common = {"device": args.device, "push_to_hub": False}
    sampler = {} if args.inference_steps is None else {"num_inference_steps": args.inference_steps}
    small = {
        "pdp": _build(PDPConfig(trace_dims=[0, 1, 2], **sampler, **common), meta),
        "dp_matched": _build(DiffusionConfig(**dp_config_kwargs(sampler), **common), meta),
    }
    if args.device.startswith("cuda"):
        small["pdp_eager"] = _build(PDPConfig(trace_dims=[0, 1, 2], **sampler, **common), meta)
        small["pdp_eager"][0].model._cuda_graphs = False
    if args.compile:
        small["pdp_compiled"] = _build(PDPConfig(trace_dims=[0, 1, 2], compile_model=True, **sampler, **common), meta)
        small["dp_compiled"] = _build(DiffusionConfig(**dp_config_kwargs(sampler), compile_model=True, **common), meta)
    for name in ("pdp", "pdp_eager", "pdp_compiled"):
        if name in small:
            pdp = small[name][0]
            pdp.set_latent(pdp.behavior_latents()[0].detach())  # fixed latent: no per-episode latent draw

    env = {"host": platform.machine(), "cpu": cpu_model(), "cpus": os.cpu_count(), "threads": torch.get_num_threads(),
           "torch": torch.__version__, "load_1min": round(os.getloadavg()[0], 2), "device": args.device,
           "gpu": torch.cuda.get_device_name() if args.device.startswith("cuda") else None}
    results: dict[str, dict] = {}
    batches = {}
    for name, (policy, pre, _) in small.items():
        policy.reset()
        batches[name] = pre(dict(obs))
        for _ in range(args.warmup):  # also fills the observation history
            _new_chunk_call(policy, batches[name])
    times = {name: [] for name in small}
    pipe = {name: [] for name in small}
    for _ in range(args.calls):  # interleaved rounds
        for name, (policy, pre, post) in small.items():
            times[name].append(_new_chunk_call(policy, batches[name]))
            pipe[name].append(_pipeline_call(policy, pre, post, obs))
    for name, (policy, _, _) in small.items():
        cfg = policy.config
        results[name] = {
            "bench": "select_action_new_chunk", "policy": name, **_stats(times[name]),
            "pipeline_median_ms": _stats(pipe[name])["median_ms"],
            "params": sum(p.numel() for p in policy.parameters()),
            "inference_steps": cfg.num_inference_steps, "horizon": cfg.horizon,
            "sampler": "DDIM" if name.startswith("pdp") else cfg.noise_scheduler_type, **env,
        }

    if args.profile and args.device.startswith("cuda"):
        for name, (policy, _, _) in small.items():
            results[name].update(_kernel_profile(policy, batches[name]))

    if args.default_dp_calls > 0:
        policy, pre, _ = _build(DiffusionConfig(**common), meta)
        policy.reset()
        batch = pre(dict(obs))
        _new_chunk_call(policy, batch)  # warm-up, fills the history
        t = [_new_chunk_call(policy, batch) for _ in range(args.default_dp_calls)]
        cfg = policy.config
        results["dp_default"] = {
            "bench": "select_action_new_chunk", "policy": "dp_default", **_stats(t),
            "params": sum(p.numel() for p in policy.parameters()),
            "inference_steps": cfg.num_inference_steps or cfg.num_train_timesteps, "horizon": cfg.horizon,
            "sampler": cfg.noise_scheduler_type, **env,
        }
        del policy

    for r in results.values():
        print(json.dumps(r), flush=True)
    base = results["pdp"]["median_ms"]
    target_ms = 2.0 if args.device.startswith("cuda") else 5.0  # docs/performance.md
    ratio = {"bench": "select_action_new_chunk_ratio", "reference": "pdp", "device": args.device,
             **{f"{k}_over_pdp": round(v["median_ms"] / base, 2) for k, v in results.items() if k != "pdp"},
             f"pdp_target_{target_ms:g}ms_met": bool(base <= target_ms)}
    if "pdp_compiled" in results:
        ratio[f"pdp_compiled_target_{target_ms:g}ms_met"] = bool(results["pdp_compiled"]["median_ms"] <= target_ms)
        ratio["pdp_compiled_over_dp_compiled"] = round(
            results["pdp_compiled"]["median_ms"] / results["dp_compiled"]["median_ms"], 2)
    print(json.dumps(ratio), flush=True)
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
