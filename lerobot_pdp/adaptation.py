"""Adapting a trained PDP to one demonstration with every weight frozen (paper Alg. 3 / Eq. 11, Eq. 12).

What ``PDPPolicy.fit_latent`` runs between reading the demonstration (``demonstration.py``) and activating the
result (``steering_state.py``): the warm start z0 (the encoder's latent of each segment, or random / zero),
gradient steps on z (``latent_fitting.fit_latent``; the one-hot ablation chooses a code instead), the
fit-quality report against the training error, and optionally one sampler noise per executed chunk.
"""

from __future__ import annotations

import dataclasses
import datetime
import logging
import math

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor

from .behavior import make_trace
from .configuration_pdp import PDPConfig
from .demonstration import Demonstration, demonstration_source
from .latent_fitting import (
    DemoWindows,
    FitResult,
    demonstration_error,
    fit_chunk_noise,
    fit_latent,
    select_code,
)
from .pdp_model import PDPModel
from .steer_requests import mode_key
from .steering_state import as_latent_tensor

logger = logging.getLogger(__name__)

INITS = ("encoder", "random", "zero")


def demonstration_traces(config: PDPConfig, demo: Demonstration) -> np.ndarray:
    """The behaviour trace X(tau) of each segment of ``demo``, [M, L, d], as the training behaviours' are made."""
    cfg = config
    return np.stack([make_trace(demo.arrays[cfg.trace_key][a:b], cfg.trace_dims, cfg.trace_length,
                                cfg.trace_normalize) for a, b in demo.segments])


def encode_demonstration(model: PDPModel, config: PDPConfig, demo: Demonstration) -> Tensor:
    """mu_phi of each segment's trace, [M, d_z] on the CPU (one-hot ablation: the nearest training behavior's
    mode code, as it has no encoder)."""
    cfg = config
    traces = demonstration_traces(cfg, demo)
    with torch.no_grad():
        if cfg.latent_type == "onehot":
            t = torch.as_tensor(traces, dtype=torch.float32, device=model.bank.traces.device)
            d = (t[:, None] - model.bank.traces[None]).pow(2).flatten(2).sum(-1)
            z = F.one_hot(model.bank.mode[d.argmin(1)], cfg.latent_dim).float()
        else:
            z = model.vae.encode(torch.as_tensor(traces, dtype=torch.float32, device=model.device))[0]
    return z.cpu()


def initial_latent(model: PDPModel, config: PDPConfig, demo: Demonstration, init: str | Tensor,
                   seed: int | None) -> Tensor:
    """The warm start z0, [M, d_z] (one per segment)."""
    n, d = len(demo.segments), config.latent_dim
    init = mode_key(init)  # "3": mode id 3, whose latent is meant
    if not isinstance(init, (str, Tensor)):  # a list or an array (a mode id or name: named as such)
        init = as_latent_tensor(init)
    if isinstance(init, Tensor):
        if init.numel() != n * d:
            shape = f"[{d}] or [1, {d}]" if n == 1 else f"[{n}, {d}]"
            raise ValueError(f"init has shape {tuple(init.shape)} ({init.numel()} values); expected shape {shape}: "
                             f"one latent of latent_dim {d} per segment, and this demonstration has {n} segment(s)")
        return init.float().reshape(n, d)
    if init == "encoder":
        return encode_demonstration(model, config, demo)
    if init == "random":
        return torch.randn(n, d, generator=torch.Generator().manual_seed(seed if seed is not None else 0))
    if init == "zero":
        return torch.zeros(n, d)
    raise ValueError(f"init must be one of {', '.join(map(repr, INITS))} or a latent (a tensor, array or list), got {init!r}"
                     + (f"; a mode's latent: init=policy.mode_latents()[{init!r}]"
                        if init in (config.mode_names or {}).values() else ""))


def fit_to_demonstration(model: PDPModel, config: PDPConfig, demo: Demonstration, windows: DemoWindows,
                         init: str | Tensor = "encoder", steps: int | None = None, lr: float | None = None,
                         lam: float | None = None, seed: int | None = 0, progress: bool = False,
                         objective: str | None = None, noise: str | None = None,
                         optimizer: str | None = None) -> FitResult:
    """Fit z to one demonstration with every weight frozen (paper Alg. 3 / Eq. 11, Eq. 12 with segments): the
    warm start, then the fit; what ``PDPPolicy.fit_latent`` runs between reading the demonstration and
    activating the result.

    Args:
        demo, windows: the demonstration (read, validated and split into segments: one z per segment, used in
            order during the rollout) and its training-style windows (``PDPPolicy.demo_windows``).
        init: ``"encoder"`` (z0 = mu_phi(X(tau)), the semantic warm start), ``"random"`` (N(0, I)),
            ``"zero"``, or a tensor.
        steps: gradient steps S (default ``config.fit_steps``); 0 returns the warm start.
        lr, lam: the step size on z and the weight of lambda |z|^2.
        seed: the fit's random draws (windows, noise); also the ``"random"`` warm start's.
        objective: "denoise" or "sample" (default ``config.fit_objective``, which documents both).
        noise: "chunks" or "none" (default ``config.fit_noise``, which documents both): also fit one
            initial sampler noise per executed chunk, z fixed (``FitResult.noise``).
        optimizer: "adam" or "gradient" (default ``config.fit_optimizer``, which documents both).

    Returns:
        :class:`FitResult` with ``z`` ([d_z], or [M, d_z] for a demonstration split into M segments), the
        initial z and the loss history.
    """
    z0 = initial_latent(model, config, demo, init, seed)
    return fit_demonstration(model, config, demo, windows, z0, steps, lr, lam, seed, progress, objective, noise,
                             optimizer)


def fit_demonstration(model: PDPModel, config: PDPConfig, demo: Demonstration, windows: DemoWindows,
                      z0: Tensor, steps: int | None = None, lr: float | None = None, lam: float | None = None,
                      seed: int | None = 0, progress: bool = False, objective: str | None = None,
                      noise: str | None = None, optimizer: str | None = None) -> FitResult:
    """z (and, with ``noise="chunks"``, one sampler noise per chunk) fitted to ``demo``'s ``windows`` from
    ``z0``; ``None`` arguments take the config's ``fit_*`` defaults. The model is put in eval mode meanwhile."""
    cfg = config
    if objective not in (None, "denoise", "sample"):
        raise ValueError(f"objective must be 'denoise' or 'sample', got {objective!r}")
    if noise not in (None, "none", "chunks"):
        raise ValueError(f"noise must be 'none' or 'chunks', got {noise!r}")
    if optimizer not in (None, "adam", "gradient"):
        raise ValueError(f"optimizer must be 'adam' or 'gradient', got {optimizer!r}")
    if not cfg.do_mask_loss_for_padding:  # fit on the same loss the denoiser was trained with
        windows = dataclasses.replace(windows, is_pad=torch.zeros_like(windows.is_pad))
    device = model.device
    steps = cfg.fit_steps if steps is None else steps
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 0:
        raise ValueError(f"steps must be an integer >= 0 (gradient steps on z; 0: the warm start alone), got {steps!r}")
    if lr is not None and not (math.isfinite(lr) and lr > 0):
        raise ValueError(f"lr must be a finite number > 0 (the step size on z), got {lr!r}")
    if lam is not None and not (math.isfinite(lam) and lam >= 0):
        raise ValueError(f"lam must be a finite number >= 0 (the weight of lambda |z|^2), got {lam!r}")
    sample_steps = cfg.num_inference_steps if (objective or cfg.fit_objective) == "sample" else None
    was_training = model.training
    model.eval()
    try:
        if cfg.latent_type == "onehot" and steps > 0:
            # the discrete ablation adapts by choosing one of its M codes per phase (it cannot interpolate
            # between them): the code that scores best on the fit objective over `steps` batches
            codes, mean = select_code(model.denoiser, model.noise_schedule, windows,
                                      torch.eye(cfg.latent_dim, device=device), steps, cfg.fit_batch_size,
                                      cfg.fit_noise_samples, seed, sample_steps)
            result = FitResult(z=codes.cpu(), z_init=z0.detach().cpu(), losses=[float(mean.min(0).values.sum())],
                               steps=steps)
        else:
            result = fit_latent(
                model.denoiser, model.noise_schedule, windows, z0.to(device), steps=steps,
                lr=cfg.fit_lr if lr is None else lr, lam=cfg.fit_lambda if lam is None else lam,
                batch_size=cfg.fit_batch_size, noise_samples=cfg.fit_noise_samples, seed=seed,
                progress=progress, gradient=cfg.fit_gradient, sample_steps=sample_steps,
                optimizer=optimizer or cfg.fit_optimizer,
            )
        chunks = (noise or cfg.fit_noise) == "chunks"
        judge_fit(model, config, result, windows, seed, chunks)
        if chunks:
            result.noise = fit_chunk_noise(
                model.denoiser, model.noise_schedule, windows, result.z.to(device), cfg.n_action_steps,
                cfg.num_inference_steps, cfg.fit_noise_steps, cfg.fit_noise_lr, seed=seed if seed is not None else 0,
                progress=progress)
    finally:
        model.train(was_training)
    if not demo.per_phase:
        result.z, result.z_init = result.z[0], result.z_init[0]
    return result


def judge_fit(model: PDPModel, config: PDPConfig, result: FitResult, windows: DemoWindows, seed: int | None,
              chunks: bool = False) -> None:
    """Fill ``result.fit_error`` / ``error_ratio`` (of the fitted z alone) and warn when the fitted latent
    reproduces the demonstration much worse than the policy reproduces its training demonstrations: on the
    validation scenes that is where steering failed (``config.fit_warn_ratio``). ``chunks``: chunk noises are
    fitted next, which the warning then says instead of advising them."""
    if config.fit_report_chunks == 0:
        return
    result.fit_error = demonstration_error(model.denoiser, model.noise_schedule, windows,
                                           result.z.to(model.device), config.fit_report_chunks,
                                           seed=seed if seed is not None else 0)
    reference = float(model.train_loss_dp)
    if not math.isfinite(reference) or reference <= 0:
        return  # a checkpoint saved before the reference was tracked
    result.error_ratio = result.fit_error / reference
    if result.error_ratio >= config.fit_warn_ratio:
        logger.warning(
            "fit_latent: the fitted latent reproduces this demonstration %.1fx worse than the policy reproduces "
            "its training demonstrations (L_fit %.4f against %.4f; warning from fit_warn_ratio=%g). Steering "
            "to a route this far from the training behaviors often fails: on the benchmark's validation scenes "
            "fits above 2x succeeded in 0-35 %% of the rollouts, on an unseen test scene in 2.5-92.5 %% by "
            "training seed. Try it before relying on it; demonstrations of this route in the training data are "
            "what helps, and %s (docs/experiments.md, \"Does the fit tell when steering will "
            "fail?\", \"z plus one sampler noise per chunk\"). Where neither reaches the route, teach it as a new "
            "mode: policy.teach(demo, training_dataset) or `lerobot-pdp teach CKPT --demo DATASET --out TAUGHT`.",
            result.error_ratio, result.fit_error, reference, config.fit_warn_ratio,
            "the sampler noises per chunk fitted next (this ratio is of z alone) reached such routes on validation "
            "scenes" if chunks else "also fitting the sampler's noise per chunk (fit_latent(noise='chunks'), "
            "--policy.fit_noise=chunks, lerobot-pdp adapt --noise chunks) reached such routes on validation scenes")


# how far (in normalised action units, the training actions spanning [-1, 1]) a demonstration's action may pass the
# sampler's clip before fit_latent warns: on reach-around val3 a demonstration 0.15 past it failed every rollout
# (the rollout lagged it 6 cm into the wall), demonstrations up to 0.08 past it succeeded in all of theirs
UNREACHABLE_ACTION_MARGIN = 0.1


def warn_unreachable_actions(config: PDPConfig, stats, demo: Demonstration, margin: float = UNREACHABLE_ACTION_MARGIN,
                             what: str = "fit_latent") -> list[int]:
    """Warn when ``demo`` commands actions the sampler cannot produce: each chunk is clipped to
    ``clip_sample_range`` in normalised units (the training actions' range), so no latent, chunk noise or taught
    mode makes the policy act past it, and a rollout of velocity-like actions falls behind the demonstration.
    ``what``: who warns (``fit_latent``, ``teach``). Returns the offending action dims."""
    from lerobot.utils.constants import ACTION

    if not config.clip_sample or ACTION not in demo.arrays:
        return []
    raw = torch.as_tensor(demo.arrays[ACTION], dtype=torch.float32)
    norm = stats.normalize_episode({ACTION: raw.numpy()})[ACTION]
    bound = float(config.clip_sample_range)
    excess = norm.abs() - bound
    dims = [d for d in range(norm.shape[1]) if float(excess[:, d].max()) > margin]
    if not dims:
        return []
    edge = stats.unnormalize(ACTION, torch.tensor([[-bound] * norm.shape[1], [bound] * norm.shape[1]])).cpu()
    names = ((config.dataset_feature_names or {}).get(ACTION) or [])
    parts = []
    for d in dims:
        name = f"{d} ({names[d]})" if d < len(names) else f"{d}"
        parts.append(f"dim {name}: {int((excess[:, d] > 0).sum())} of {len(norm)} frames past it, up to "
                     f"{float(raw[:, d].min()):.3g}..{float(raw[:, d].max()):.3g} against the producible "
                     f"{float(edge[0, d]):.3g}..{float(edge[1, d]):.3g} ({float(norm[:, d].abs().max()):.2f} normalised)")
    logger.warning(
        "%s: the demonstration commands actions this policy cannot produce: its sampler clips every chunk to the "
        "training actions' range (clip_sample_range=%g in normalised units); %s. No latent, chunk noise or taught "
        "mode gets past the clip, so a rollout acts slower or shorter than the demonstration there and falls behind "
        "its route. Record the demonstration within the training actions' range (slower, for velocity actions)",
        what, bound, "; ".join(parts))
    return dims


def fit_provenance(episode: object, result: FitResult, config: PDPConfig, **settings: object) -> dict:
    """Where a fitted latent came from, as an adapted checkpoint keeps it (``adaptation.json``): the
    demonstration, the fit settings (``None`` = the config's default, filled in), the fit error and its
    ratio to the training error, and the date."""
    source = demonstration_source(episode)
    defaults = {"steps": config.fit_steps, "lr": config.fit_lr, "lam": config.fit_lambda,
                "objective": config.fit_objective, "noise": config.fit_noise, "optimizer": config.fit_optimizer}
    fit = {k: (defaults.get(k) if v is None else v) for k, v in settings.items()}
    fit = {k: (v.tolist() if isinstance(v, Tensor) else v if isinstance(v, (int, float, str, bool, list)) or v is None
               else str(v)) for k, v in fit.items()}
    return {"source": "fit_latent", "demonstration": source, "fit": fit, "fit_error": result.fit_error,
            "error_ratio": result.error_ratio, "noise_fitted": result.noise is not None,
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")}
