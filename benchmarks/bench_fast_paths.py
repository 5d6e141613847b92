"""The denoiser's fast paths (``lerobot_pdp/fast_inference.py``) against its reference forward, side by side.

Times, interleaved round by round in one process (so load changes on the machine hit every variant alike):

- a new chunk at B = 1 (the policy's sampler, ``--steps`` DDIM steps each), denoiser calls by
  ``reference``: ``FiLMUnet1d.forward`` per step; ``precomputed``: ``FrozenDenoiser`` (modulation computed once
  per chunk), eager, PyTorch's convolutions; ``precomputed_unfold``: the same with unfolded convolutions;
  ``traced_unfold``: the TorchScript trace the policy runs (``FastDenoiser.run``, unfolded convolutions);
  ``traced``: a trace of the path with PyTorch's convolutions; ``frozen_traced_unfold``: the policy's trace with its
  weights folded in by ``torch.jit.freeze`` (not used by the policy: a weight update would need a new freeze). Plus ``latent_terms``: z's FiLM terms alone (B = 1), the
  work a per-z cache would save per chunk;
- a 10-step ``fit_latent`` on one ~150-frame demonstration, with the default gradient (finite differences
  at d_z = 2: batches of 96 chunks without autograd) and with autograd, the denoiser called as
  ``reference`` (``FiLMUnet1d.forward`` on each chunk's observations and latent), ``precomputed`` (PyTorch's
  convolutions) or ``precomputed_unfold`` (the policy unfolds without autograd, i.e. with finite
  differences); the fit-quality report is off (it is not a fitting step).

Weights are freshly initialised (timing does not depend on them). One JSON line per figure, ``ref_over``: the
reference's median over the variant's (> 1: the variant is faster).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_fast_paths.py [--calls 60] [--fit-reps 12]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
import warnings
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
warnings.filterwarnings("ignore")


def _emit(record: dict) -> None:
    print(json.dumps(record), flush=True)


def _interleaved(fns: dict, rounds: int, warmup: int = 3) -> dict[str, float]:
    """Median seconds per call of each function, timed round by round."""
    for fn in fns.values():
        for _ in range(warmup):
            fn()
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(rounds):
        for name, fn in fns.items():
            t = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t)
    return {name: statistics.median(t) for name, t in times.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--calls", type=int, default=60, help="timed chunks per variant and step count")
    ap.add_argument("--fit-reps", type=int, default=12, help="timed 10-step fits per variant and gradient")
    args = ap.parse_args()

    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy

    from lerobot_pdp import PDPConfig, latent_fitting
    from lerobot_pdp import fast_inference as fi
    from lerobot_pdp.benchmark.machine import cpu_model
    from lerobot_pdp.envs.recording import make_dataset
    from lerobot_pdp.episodes import read_episodes

    torch.set_num_threads(args.threads)
    env = {"cpu": cpu_model(), "threads": torch.get_num_threads(), "torch": torch.__version__,
           "load_1min": round(os.getloadavg()[0], 2)}
    root = Path(tempfile.mkdtemp()) / "ra"
    make_dataset("reach-around", root, scene=0, episodes_per_mode=2, seed=0, progress=False)
    meta = LeRobotDatasetMetadata("local/ra", root=root)
    pdp = make_policy(PDPConfig(device="cpu", push_to_hub=False, trace_dims=[0, 1, 2]), ds_meta=meta).eval()
    model, net, schedule = pdp.model, pdp.model.denoiser, pdp.model.noise_schedule
    fast = model.fast_denoiser
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(1, net.obs_cond_dim, generator=g)
    z = model.behavior_latents()[:1].detach()
    noise = torch.randn(1, pdp.config.horizon, pdp.action_dim, generator=g)

    frozen = fast.frozen()
    ctx0 = fast.contexts(obs, z, [schedule.num_train_timesteps - 1])[0]
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")

        class _Conv(torch.nn.Module):
            def __init__(self):
                super().__init__()
                self.net = net

            def forward(self, x, *ctx):
                return fi.modulated_forward(self.net, x, list(ctx), False)

        traced_conv = torch.jit.trace(_Conv(), (noise, *ctx0), check_trace=False)
        # the policy's own trace with its weights folded in as constants (``torch.jit.freeze``; a weight update
        # would need a new freeze)
        frozen_unfold = torch.jit.freeze(fast._trace(noise, list(ctx0)).eval())

    def chunk(variant: str, n: int):
        steps = schedule.timesteps(n)
        with torch.inference_mode():
            if variant == "reference":
                return schedule.sample(lambda x, i, k: net(x, torch.full((1,), k), obs, z), noise, n)
            ctx = fast.contexts(obs, z, steps)
            call = {"precomputed": lambda x, c: fi.modulated_forward(net, x, c, False),
                    "precomputed_unfold": lambda x, c: fi.modulated_forward(net, x, c, True),
                    "traced": lambda x, c: traced_conv(x, *c),
                    "traced_unfold": fast.run,
                    "frozen_traced_unfold": lambda x, c: frozen_unfold(x, *c)}[variant]
            return schedule.sample(lambda x, i, k: call(x, ctx[i]), noise, n)

    variants = ["reference", "precomputed", "precomputed_unfold", "traced", "traced_unfold", "frozen_traced_unfold"]
    for n in (5, 20):
        med = _interleaved({v: (lambda v=v, n=n: chunk(v, n)) for v in variants}, args.calls)
        for v in variants:
            _emit({"bench": "new_chunk_b1", "ddim_steps": n, "variant": v, "median_ms": round(1e3 * med[v], 3),
                   "ref_over": round(med["reference"] / med[v], 3), **env})
        if n == 5:
            with torch.inference_mode():
                lt = _interleaved({"latent_terms": lambda: frozen.latent_terms(z)}, args.calls * 10)
            _emit({"bench": "latent_terms_b1", "median_ms": round(1e3 * lt["latent_terms"], 4),
                   "share_of_traced_chunk": round(lt["latent_terms"] / med["traced_unfold"], 4), **env})

    # fitting: the same FrozenDenoiser interface, its eps computed three ways
    class Reference(fi.FrozenDenoiser):
        """eps by the reference forward; the 'observations' are obs_cond, a context the chunks' (obs, z)."""

        def observations(self, obs_cond):
            return obs_cond

        def context(self, observations, z, rows=None):
            return fi.Context(observations, z if rows is None else z[rows])

        def eps(self, sample, k, ctx, unfold=False):
            k = torch.full((sample.shape[0],), k) if isinstance(k, int) else k
            return self.net(sample, k, ctx.base, ctx.gain)

    class Unfolded(fi.FrozenDenoiser):
        def eps(self, sample, k, ctx, unfold=True):
            return super().eps(sample, k, ctx, True)

    class Conv(fi.FrozenDenoiser):
        def eps(self, sample, k, ctx, unfold=False):
            return super().eps(sample, k, ctx, False)

    eps_ = read_episodes(root, ["observation.state", "observation.environment_state", "action"])
    ep = max(eps_, key=lambda e: len(eps_[e]["action"]))
    demo = {k: v for k, v in eps_[ep].items() if k in ("observation.state", "observation.environment_state", "action")}
    pdp.config.fit_report_chunks = 0
    real = latent_fitting.frozen_denoiser
    kinds = {"reference": Reference, "precomputed": Conv, "precomputed_unfold": Unfolded}

    def fit(kind):
        latent_fitting.frozen_denoiser = (  # built once per fit, then passed on as it is
            lambda d, s: d if isinstance(d, fi.FrozenDenoiser) else kinds[kind](d, s.num_train_timesteps))
        try:
            pdp.fit_latent(demo, steps=10, activate=False)
        finally:
            latent_fitting.frozen_denoiser = real

    for gradient in ("auto", "autograd"):
        pdp.config.fit_gradient = gradient
        med = _interleaved({k: (lambda k=k: fit(k)) for k in kinds}, args.fit_reps, warmup=1)
        for k in kinds:
            _emit({"bench": "fit_latent_10_steps", "gradient": gradient, "variant": k,
                   "demo_frames": len(demo["action"]), "batch": pdp.config.fit_batch_size,
                   "median_ms": round(1e3 * med[k], 1), "ref_over": round(med["reference"] / med[k], 3), **env})


if __name__ == "__main__":
    main()
