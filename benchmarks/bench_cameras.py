"""PDP with cameras next to LeRobot ``diffusion`` with the same cameras and vision backbone, side by side.

Three timings, one and two 96x96 cameras (``--cameras``), in one process on one device:

- ``select_action`` new-chunk latency (B = 1, action queue cleared before each call, the observation
  history filled, as mid-episode; weights fixed, as in a rollout);
- one training step (forward, backward, AdamW step) on a batch of ``--batch`` windows;
- PDP's ``fit_latent`` on a camera demonstration of ``--demo-frames`` frames (``--fit-steps`` steps), which
  encodes every frame once and then fits z on the windows' features.

Both policies get the same vision settings: torchvision ResNet-18 without pretrained weights, GroupNorm,
32 spatial-softmax keypoints, one encoder shared by the cameras, no crop; and the same 1-D U-Net, windows and
DDIM steps (``benchmark.baselines.dp_config_kwargs``, the benchmark's matched DP). The behavior bank comes
from a small generated reach-around dataset (state only); camera frames are random: the time of a step does
not depend on pixel values or weight values. One JSON line per (policy, cameras, timing), then ratio lines.

``--compile`` adds ``pdp_compiled`` and ``dp_compiled``, each policy with its own ``compile_model`` on
(PDP: the denoiser through torch.compile; DP: LeRobot's ``torch.compile(unet, mode="reduce-overhead")``),
compiled during the warm-up calls, and their ratio.

    .venv/bin/python benchmarks/bench_cameras.py [--device cpu|cuda] [--threads 2] [--cameras 1 2]
        [--batch 8] [--calls 20] [--compile [--pdp-compile-mode reduce-overhead]] [--vqbet]

``--vqbet`` adds LeRobot's ``vqbet`` with one camera (what ``benchmark --obs images`` trains as the third
camera method), past its VQ-VAE phase; no ratio line (it is a baseline's cost, not ours against a peer).

``--eager-pdp`` adds ``pdp_eager``: PDP's weights with its CUDA-graph training step off
(``train_cuda_graphs=False``: forward and backward launched kernel by kernel), and PDP over it.

``--count-ops`` counts instead of timing: the aten operators one training step's forward and backward
dispatch (each non-view operator is at least one kernel launch on a GPU, where a small model's step is
launch-bound), and the parameter tensors (one optimizer update each unless fused), for PDP and matched DP;
``--cameras 0`` is the state-only policy. The counts do not depend on the machine's load or the batch size.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import os
import platform
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

VISION = {"vision_backbone": "resnet18", "pretrained_backbone_weights": None, "use_group_norm": True,
          "spatial_softmax_num_keypoints": 32, "use_separate_rgb_encoder_per_camera": False, "crop_shape": None}


def _stats(times_s: list[float]) -> dict:
    t = np.asarray(times_s) * 1e3
    return {"median_ms": round(float(np.median(t)), 2), "p90_ms": round(float(np.percentile(t, 90)), 2),
            "calls": len(t)}


def _sync(device: str) -> None:
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _timed(device: str, fn) -> float:
    _sync(device)
    t = time.perf_counter()
    fn()
    _sync(device)
    return time.perf_counter() - t


def _features(meta, cameras: list[str], size: int):
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.utils.feature_utils import dataset_to_policy_features

    feats = dataset_to_policy_features(meta.features)
    inputs = {k: ft for k, ft in feats.items() if ft.type is not FeatureType.ACTION}
    inputs.update({c: PolicyFeature(type=FeatureType.VISUAL, shape=(3, size, size)) for c in cameras})
    return inputs, {k: ft for k, ft in feats.items() if ft.type is FeatureType.ACTION}


def _vqbet(meta, cameras, size, device):
    """LeRobot's VQ-BeT as the camera benchmark trains it (settings.VQBET_FLAGS: the same vision settings, two
    observation frames), past its VQ-VAE phase so that a training step is a GPT step."""
    import torch
    from lerobot.policies.factory import make_policy
    from lerobot.policies.vqbet.configuration_vqbet import VQBeTConfig

    inputs, outputs = _features(meta, cameras, size)
    vision = {k: v for k, v in VISION.items() if k != "use_separate_rgb_encoder_per_camera"}
    # LeRobot's VQ-BeT prints progress to stdout: keep stdout JSON lines only
    with contextlib.redirect_stdout(sys.stderr):
        policy = make_policy(VQBeTConfig(device=device, push_to_hub=False, input_features=inputs,
                                         output_features=outputs, n_obs_steps=2, n_vqvae_training_steps=1, **vision),
                             ds_meta=meta)
        policy.train()
        with torch.no_grad():
            policy.forward(_training_batch(meta, policy, cameras, size, 2, device))  # the one VQ-VAE step
    return policy


def _policies(meta, cameras, size, device, steps, compiled: bool = False, pdp_mode: str | None = None,
              eager_pdp: bool = False):
    """PDP and matched DP with the same cameras, on ``device`` (and their compiled twins)."""
    import torch
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.factory import make_policy

    from lerobot_pdp import PDPConfig
    from lerobot_pdp.benchmark.baselines import dp_config_kwargs

    inputs, outputs = _features(meta, cameras, size)
    common = {"device": device, "push_to_hub": False, "input_features": inputs, "output_features": outputs}
    sampler = {} if steps is None else {"num_inference_steps": steps}
    torch.manual_seed(0)
    out = {}
    for sfx, comp in (("", {}), ("_compiled", {"compile_model": True}))[: 2 if compiled else 1]:
        mode = {"compile_mode": pdp_mode} if comp and pdp_mode else {}
        pdp = make_policy(PDPConfig(trace_dims=[0, 1, 2], **sampler, **VISION, **comp, **mode, **common),
                          ds_meta=meta)
        dp = make_policy(DiffusionConfig(**dp_config_kwargs(sampler), **VISION, **comp, **common), ds_meta=meta)
        pdp.set_latent(pdp.behavior_latents()[0].detach())  # fixed latent: no per-episode latent draw
        out.update({f"pdp{sfx}": pdp, f"dp{sfx or '_matched'}": dp})
    if eager_pdp:
        out["pdp_eager"] = copy.deepcopy(out["pdp"])
        out["pdp_eager"].config.train_cuda_graphs = False
        assert out["pdp_eager"].model.config is out["pdp_eager"].config
    return out


def _training_batch(meta, policy, cameras, size, n, device):
    """``n`` real (normalised) state windows of the dataset with random camera histories added."""
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.factory import make_pre_post_processors

    cfg = policy.config
    vectors = [k for k in cfg.input_features if k not in cameras]
    dt = {k: [i / meta.fps for i in cfg.observation_delta_indices] for k in vectors}
    dt["action"] = [i / meta.fps for i in cfg.action_delta_indices]
    ds = LeRobotDataset("local/reach", root=meta.root, delta_timestamps=dt)
    pre, _ = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    g = torch.Generator().manual_seed(0)
    items = [ds[int(i)] for i in torch.randint(0, len(ds), (n,), generator=g)]
    batch = pre(torch.utils.data.default_collate(items))
    for c in cameras:
        batch[c] = torch.rand(n, cfg.n_obs_steps, 3, size, size, generator=g).to(device)
        batch[f"{c}_is_pad"] = torch.zeros(n, cfg.n_obs_steps, dtype=torch.bool, device=device)
    return batch


def _run(args, meta, n_cam: int, env: dict) -> None:
    """All three timings with ``n_cam`` cameras; prints their JSON lines."""
    import torch

    dev, size = args.device, args.image_size
    cameras = [f"observation.images.cam{i}" for i in range(n_cam)]
    policies = _policies(meta, cameras, size, dev, args.inference_steps, args.compile, args.pdp_compile_mode,
                         args.eager_pdp)
    if args.vqbet and n_cam == 1:  # LeRobot's vqbet takes exactly one camera
        policies["vqbet"] = _vqbet(meta, cameras, size, dev)
    obs = {k: v[:1, -1] for k, v in _training_batch(meta, policies["pdp"], cameras, size, 1, dev).items()
           if k.startswith("observation.") and not k.endswith("_is_pad")}
    batches = {n: _training_batch(meta, p, cameras, size, args.batch, dev) for n, p in policies.items()}
    optims = {n: torch.optim.AdamW(p.get_optim_params(), lr=1e-4) for n, p in policies.items()}

    def act(name: str) -> None:
        policies[name]._queues["action"].clear()
        with torch.inference_mode():
            policies[name].select_action(dict(obs))

    def train(name: str) -> None:
        loss, _ = policies[name].forward(batches[name])
        loss.backward()
        optims[name].step()
        optims[name].zero_grad(set_to_none=True)

    times = {(n, t): [] for n in policies for t in ("select_action_new_chunk", "train_step")}
    # Acting first, with the weights fixed as in a rollout (an optimizer step in between would make PDP
    # recapture its CUDA graph every call), then training; interleaved rounds inside each, so that load
    # changes on the machine hit both policies alike.
    for p in policies.values():
        p.eval()
        p.reset()
    for name in policies:
        for _ in range(args.warmup):
            act(name)
    for _ in range(args.calls):
        for name in policies:
            times[(name, "select_action_new_chunk")].append(_timed(dev, lambda n=name: act(n)))
    for p in policies.values():
        p.train()
    for name in policies:
        for _ in range(args.warmup):
            train(name)
    for _ in range(args.calls):
        for name in policies:
            times[(name, "train_step")].append(_timed(dev, lambda n=name: train(n)))
    res = {}
    for (name, bench), t in times.items():
        cfg = policies[name].config
        res[(name, bench)] = {"bench": bench, "policy": name, "cameras": n_cam, **_stats(t),
                              "batch": args.batch if bench == "train_step" else 1,
                              "inference_steps": getattr(cfg, "num_inference_steps", None),
                              "compile_mode": cfg.compile_mode if getattr(cfg, "compile_model", False) else None,
                              "params": sum(q.numel() for q in policies[name].parameters()), **env}
        print(json.dumps(res[(name, bench)]), flush=True)
    pairs = ([("pdp", "dp_matched", "")] + ([("pdp_compiled", "dp_compiled", "compiled")] if args.compile else [])
             + ([("pdp_eager", "dp_matched", "pdp_eager")] if args.eager_pdp else []))
    for bench in ("select_action_new_chunk", "train_step"):
        for a, b, label in pairs:
            r = round(res[(a, bench)]["median_ms"] / res[(b, bench)]["median_ms"], 3)
            ratio = {"pdp_over_dp": r, "target_1.1_met": bool(r <= 1.1)}
            print(json.dumps({"bench": f"{bench}_ratio", "cameras": n_cam, "pair": label or "eager", **ratio,
                              "device": dev}), flush=True)

    pdp = policies["pdp"]
    pdp.eval()
    g = torch.Generator().manual_seed(1)
    T = args.demo_frames
    demo = {k: torch.randn(T, *ft.shape, generator=g) for k, ft in pdp.config.input_features.items()
            if k not in cameras}
    demo["action"] = torch.rand(T, pdp.action_dim, generator=g) * 2 - 1
    demo.update({c: torch.randint(0, 256, (T, 3, size, size), dtype=torch.uint8, generator=g) for c in cameras})
    fit = [_timed(dev, lambda: pdp.fit_latent(demo, steps=args.fit_steps)) for _ in range(args.fit_calls + 1)][1:]
    print(json.dumps({"bench": "fit_latent_camera_demo", "policy": "pdp", "cameras": n_cam, **_stats(fit),
                      "demo_frames": T, "fit_steps": args.fit_steps, **env}), flush=True)


def _count_ops(args, meta, n_cam: int, env: dict) -> None:
    """Aten operators of one training step's forward and backward, per policy; prints their JSON lines."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class Count(TorchDispatchMode):  # sees every operator below autograd, backward's included
        def __init__(self):
            super().__init__()
            self.ops: dict[str, int] = {}

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if not func.is_view:
                self.ops[func.__name__] = self.ops.get(func.__name__, 0) + 1
            return func(*args, **(kwargs or {}))

    cameras = [f"observation.images.cam{i}" for i in range(n_cam)]
    policies = _policies(meta, cameras, args.image_size, args.device, args.inference_steps)
    res = {}
    for name, policy in policies.items():
        policy.train()
        batch = _training_batch(meta, policy, cameras, args.image_size, args.batch, args.device)
        policy.forward(batch)[0].backward()  # warm-up: lazily built buffers are not counted
        policy.zero_grad(set_to_none=True)
        with Count() as forward:
            loss, _ = policy.forward(batch)
        with Count() as backward:
            loss.backward()
        top = sorted(forward.ops.items(), key=lambda kv: -kv[1])[: args.top_ops]
        res[name] = {"bench": "train_step_ops", "policy": name, "cameras": n_cam,
                     "forward_ops": sum(forward.ops.values()), "backward_ops": sum(backward.ops.values()),
                     "param_tensors": sum(1 for q in policy.parameters() if q.requires_grad),
                     "params": sum(q.numel() for q in policy.parameters()), "top_forward_ops": dict(top), **env}
        res[name]["ops"] = res[name]["forward_ops"] + res[name]["backward_ops"]
        print(json.dumps(res[name]), flush=True)
    ratios = {"pdp_over_dp": round(res["pdp"]["ops"] / res["dp_matched"]["ops"], 3)}
    print(json.dumps({"bench": "train_step_ops_ratio", "cameras": n_cam, **ratios}), flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads (default 2)")
    ap.add_argument("--cameras", type=int, nargs="+", default=[1, 2], help="camera counts to time")
    ap.add_argument("--image-size", type=int, default=96)
    ap.add_argument("--batch", type=int, default=8, help="training windows per step (default 8)")
    ap.add_argument("--calls", type=int, default=20, help="timed calls per policy and timing")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--inference-steps", type=int, default=5,
                    help="DDIM steps of both policies (default 5, as the documented figures; PDPConfig's is 20)")
    ap.add_argument("--demo-frames", type=int, default=100, help="frames of the fitted camera demonstration")
    ap.add_argument("--fit-steps", type=int, default=100, help="fit_latent steps (default: PDPConfig's 100)")
    ap.add_argument("--fit-calls", type=int, default=3)
    ap.add_argument("--compile", action="store_true", help="also time both policies with compile_model on")
    ap.add_argument("--vqbet", action="store_true",
                    help="also time LeRobot's vqbet as the camera benchmark trains it (one camera only)")
    ap.add_argument("--pdp-compile-mode", default=None,
                    help="PDP's compile_mode with --compile (default PDP's 'default'; DP keeps 'reduce-overhead')")
    ap.add_argument("--count-ops", action="store_true",
                    help="count a training step's aten operators and parameter tensors instead of timing")
    ap.add_argument("--eager-pdp", action="store_true",
                    help="also PDP with its CUDA-graph training step off (pdp_eager: train_cuda_graphs=False)")
    ap.add_argument("--top-ops", type=int, default=8, help="with --count-ops: the most frequent forward operators listed")
    args = ap.parse_args(argv)

    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    warnings.filterwarnings("ignore")
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    from lerobot_pdp.benchmark.machine import cpu_model
    from lerobot_pdp.envs.recording import make_dataset

    torch.set_num_threads(args.threads)
    tmp = tempfile.TemporaryDirectory(prefix="bench-cameras-")
    root = make_dataset(env="reach-around", out=Path(tmp.name) / "reach", scene=0, episodes_per_mode=2, seed=0,
                        progress=False)
    meta = LeRobotDatasetMetadata("local/reach", root=root)
    dev = args.device
    env = {"host": platform.machine(), "cpu": cpu_model(), "cpus": os.cpu_count(), "threads": torch.get_num_threads(),
           "torch": torch.__version__, "device": dev, "image_size": args.image_size,
           "gpu": torch.cuda.get_device_name() if dev.startswith("cuda") else None}
    for n_cam in args.cameras:
        (_count_ops if args.count_ops else _run)(args, meta, n_cam, env)
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
