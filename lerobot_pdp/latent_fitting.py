"""Test-time latent fitting (paper Sec. 3.3, Alg. 3): adapt to one demonstration by optimising z only.

    L_fit(z) = E_{t,k,eps} |eps - eps_theta(A~_t^k, k, c~_t, z)|^2 + lambda |z|^2

or, with ``fit_objective="sample"``, the error of the chunk the policy itself samples from noise under z
(its DDIM chain, as DP's noise adaptation scores a noise): E_{t,eps} |DDIM_z(eps, c~_t) - A_t|^2 + lambda |z|^2.
The demonstration is cut into the same (observation history, action chunk) windows the denoiser was
trained on. Gradients are taken with ``torch.autograd.grad`` w.r.t. z alone, so no parameter of the
policy is touched (not even its ``.grad``). With segments, each phase m has its own z^(m) and the
objective is the sum of the per-phase losses (paper Eq. 12).
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from .chunk_windows import DemoWindows
from .console import loss_ends_text
from .denoiser import FiLMUnet1d
from .diffusion import NoiseSchedule
from .fast_inference import Context, FrozenDenoiser

FIT_GRADIENTS = ("auto", "autograd", "finite_difference")


@dataclass
class FitResult:
    """Outcome of :func:`fit_latent`."""

    z: Tensor  # fitted latent(s), [M, d_z] (the policy squeezes M = 1)
    z_init: Tensor  # starting point
    losses: list[float] = field(default_factory=list)  # L_fit per step (first entry: at z_init)
    steps: int = 0
    # L_fit (without lambda|z|^2, mean over phases) on every window at the fitted z (alone: before any chunk
    # noises), and its ratio to the training demonstrations' error at their own latents (None for a policy
    # without that reference)
    fit_error: float | None = None
    error_ratio: float | None = None
    # with fit_noise="chunks": one initial sampler noise per executed chunk, [C, horizon, A], played in order
    noise: Tensor | None = None
    # where the fit came from, as adaptation.json keeps it (set by PDPPolicy.fit_latent)
    provenance: dict | None = None

    def __repr__(self) -> str:  # a summary: the dataclass's would print every step's loss and every noise
        def fmt(x: float | None) -> str:
            return "None" if x is None else f"{x:.4g}"

        loss = loss_ends_text(self.losses)
        noise = "None" if self.noise is None else f"<{len(self.noise)} chunk noises {tuple(self.noise.shape)}>"
        def short(t: Tensor) -> str:
            return str(np.round(t.detach().cpu().double().numpy(), 4).tolist())

        return (f"FitResult(z={short(self.z)}, z_init={short(self.z_init)}, steps={self.steps}, L_fit={loss}, "
                f"fit_error={fmt(self.fit_error)}, error_ratio={fmt(self.error_ratio)}, noise={noise})")


class FitCancelled(RuntimeError):
    """A fit stopped between two steps because its thread was told to (:func:`cancellable`)."""


_CANCEL = threading.local()  # per thread: the event that stops the fits it runs
# set when the process ends (a server's Ctrl-C): every cancellable fit, on any thread, stops at its next step; a
# start-up fit a client's connect started on a gRPC worker thread would otherwise hold the exit until it ran out
ENDING = threading.Event()


@contextmanager
def cancellable(stop: threading.Event) -> Iterator[None]:
    """Within the block, on this thread, :func:`fit_latent` and :func:`fit_chunk_noise` raise :class:`FitCancelled`
    at their next step once ``stop`` is set: a live-steering fit superseded by a newer request, or one still
    running when the process exits (a thread left inside torch then aborts the interpreter's exit)."""
    _CANCEL.stop = stop
    try:
        yield
    finally:
        _CANCEL.stop = None


def _check_cancelled() -> None:
    stop = getattr(_CANCEL, "stop", None)
    if stop is not None and (stop.is_set() or ENDING.is_set()):
        raise FitCancelled("the fit was cancelled")


def _stratified_batch(segment: Tensor, n_segments: int, batch_size: int, g: torch.Generator) -> Tensor:
    """Indices of ``batch_size`` windows spread evenly over the segments."""
    per = max(1, batch_size // n_segments)
    idx = []
    for m in range(n_segments):
        pool = torch.nonzero(segment == m).view(-1)
        if len(pool) == 0:
            continue
        idx.append(pool[torch.randint(0, len(pool), (per,), generator=g)])
    return torch.cat(idx)


def _spread_steps(n_windows: int, draws: int, num_steps: int, g: torch.Generator) -> Tensor:
    """Diffusion steps for ``draws`` rounds over ``n_windows`` windows (round-major, as ``idx.repeat(draws)``),
    stratified twice: the n = draws * n_windows steps cover n equal strata of [0, num_steps) once each, and
    each window's draws fall in distinct coarse strata (one per round). Same mean as uniform steps; about half
    the spread at the same budget on the validation scenes, because the error varies mostly with the step."""
    n = n_windows * draws
    rounds = torch.arange(draws)[:, None] * n_windows
    strata = (rounds + torch.argsort(torch.rand(draws, n_windows, generator=g), dim=1)).reshape(-1)
    return ((strata + torch.rand(n, generator=g)) * (num_steps / n)).long().clamp_max(num_steps - 1)


def frozen_denoiser(denoiser: FiLMUnet1d | FrozenDenoiser, schedule: NoiseSchedule) -> FrozenDenoiser:
    """The fitting's view of the denoiser (weights frozen while it runs), built once per fit."""
    if isinstance(denoiser, FrozenDenoiser):
        return denoiser
    return FrozenDenoiser(denoiser, schedule.num_train_timesteps)


def _per_phase(err: Tensor, windows: DemoWindows, idx: Tensor, seg: Tensor, P: int, M: int) -> Tensor:
    """Masked mean error per window [P, n] of ``err`` [P * n, H, A], averaged per phase -> [P, M]."""
    device = err.device
    n = len(idx)
    err = err.view(P, n, *err.shape[1:])
    mask = (~windows.is_pad[idx]).to(device).unsqueeze(-1).to(err.dtype)  # [n, H, 1]
    per_window = (err * mask).sum((2, 3)) / (mask.sum((1, 2)) * err.shape[-1]).clamp_min(1)  # [P, n]
    seg_sum = torch.zeros(P, M, device=device).index_add(1, seg, per_window)
    seg_cnt = torch.zeros(M, device=device).index_add(0, seg, torch.ones(n, device=device))
    return seg_sum / seg_cnt.clamp_min(1)


def _phase_losses(frozen: FrozenDenoiser, schedule, windows: DemoWindows, zs: Tensor, idx: Tensor,
                  noise_samples: int, g: torch.Generator, obs: Tensor, spread_steps: bool = False) -> Tensor:
    """Per-phase mean noise-prediction error for each of P latent sets ``zs`` [P, M, d_z] -> [P, M].

    Every latent set sees the same windows, diffusion steps and noise (common random numbers), so the
    P denoiser passes run as one batch of P * len(idx) chunks. ``obs``: the windows'
    ``frozen.observations``. ``spread_steps``: the steps of :func:`_spread_steps` instead of uniform draws.
    """
    device = zs.device
    P, M = zs.shape[:2]
    n_idx = len(idx)
    idx = idx.repeat(noise_samples)
    n = len(idx)
    actions = windows.actions[idx].to(device)
    eps = torch.randn(actions.shape, generator=g).to(device)
    k = (_spread_steps(n_idx, noise_samples, schedule.num_train_timesteps, g) if spread_steps
         else torch.randint(0, schedule.num_train_timesteps, (n,), generator=g)).to(device)
    noisy = schedule.add_noise(actions, eps, k)
    seg = windows.segment[idx].to(device)
    rows = (torch.arange(P, device=device)[:, None] * M + seg[None]).reshape(-1)  # each chunk's latent
    ctx = frozen.context(obs[idx.to(device)].repeat(P, 1), zs.reshape(P * M, -1), rows)
    pred = frozen.eps(noisy.repeat(P, 1, 1), k.repeat(P), ctx)
    return _per_phase((pred - eps.repeat(P, 1, 1)).pow(2), windows, idx, seg, P, M)


def _ddim_chain(frozen: FrozenDenoiser, schedule, x: Tensor, ctx: Context, sample_steps: int) -> Tensor:
    """The policy's DDIM sampler from ``x`` [n, H, A] under conditioning ``ctx``, differentiable."""
    for k, k_prev in schedule.steps(sample_steps):
        x = schedule.ddim_step(frozen.eps(x, k, ctx), k, k_prev, x)
    return x


def _phase_sample_losses(frozen: FrozenDenoiser, schedule, windows: DemoWindows, zs: Tensor, idx: Tensor,
                         noise_samples: int, g: torch.Generator, obs: Tensor, sample_steps: int) -> Tensor:
    """Per-phase mean error of the *sampled* chunk: each window's chunk denoised from fresh noise in
    ``sample_steps`` DDIM steps (the policy's own sampler) under each latent set ``zs`` [P, M, d_z], against
    the demonstration's chunk -> [P, M]. Common random numbers as in :func:`_phase_losses`."""
    device = zs.device
    P, M = zs.shape[:2]
    idx = idx.repeat(noise_samples)
    actions = windows.actions[idx].to(device)
    x = torch.randn(actions.shape, generator=g).to(device).repeat(P, 1, 1)
    seg = windows.segment[idx].to(device)
    rows = (torch.arange(P, device=device)[:, None] * M + seg[None]).reshape(-1)
    ctx = frozen.context(obs[idx.to(device)].repeat(P, 1), zs.reshape(P * M, -1), rows)
    x = _ddim_chain(frozen, schedule, x, ctx, sample_steps)
    return _per_phase((x - actions.repeat(P, 1, 1)).pow(2), windows, idx, seg, P, M)


def _errors(frozen, schedule, windows, zs, idx, noise_samples, g, obs, sample_steps):
    if sample_steps is None:
        return _phase_losses(frozen, schedule, windows, zs, idx, noise_samples, g, obs)
    return _phase_sample_losses(frozen, schedule, windows, zs, idx, noise_samples, g, obs, sample_steps)


def fit_loss(denoiser: FiLMUnet1d | FrozenDenoiser, schedule, windows: DemoWindows, z: Tensor, idx: Tensor,
             noise_samples: int, lam: float, g: torch.Generator, obs: Tensor | None = None,
             sample_steps: int | None = None) -> Tensor:
    """L_fit on the windows ``idx``: per-phase mean noise-prediction error, summed over phases, + lambda|z|^2.

    The denoiser runs as a :class:`FrozenDenoiser`: the step and observation parts of its conditioning are
    fixed while z is fitted, so only z's FiLM is recomputed (and differentiated) per step. ``obs``: the
    windows' ``observations``, if already computed (a fitting loop computes them once).
    ``sample_steps``: instead of the noise-prediction error, the error of the chunk sampled in that many
    DDIM steps (``fit_objective="sample"``).
    """
    frozen = frozen_denoiser(denoiser, schedule)
    if obs is None:
        with torch.no_grad():
            obs = frozen.observations(windows.obs_cond.to(z.device))
    losses = _errors(frozen, schedule, windows, z[None], idx, noise_samples, g, obs, sample_steps)
    return losses[0].sum() + lam * z.pow(2).sum()


def fit_loss_and_grad_fd(denoiser: FiLMUnet1d | FrozenDenoiser, schedule, windows: DemoWindows, z: Tensor,
                         idx: Tensor, noise_samples: int, lam: float, g: torch.Generator, obs: Tensor | None = None,
                         h: float = 1e-3, sample_steps: int | None = None) -> tuple[Tensor, Tensor]:
    """L_fit and its gradient in z by forward differences: no backward pass, d_z + 1 latent sets per step.

    The error of a phase depends only on that phase's z, so moving coordinate j of every phase's z at
    once gives dL/dz[:, j] for all phases from one extra evaluation. All d_z + 1 latent sets run as one
    no-grad denoiser batch on the same windows, steps and noise (common random numbers, so the
    differences are smooth in z). On CPU a forward + backward costs as much as ~4-5 forward latent sets
    (per-call overhead of ~60 small convolutions), so for d_z <= 3 this is the cheaper gradient. The
    O(h) bias (< 2 % of the gradient at h = 1e-3 on trained reach-around weights, float32 round-off
    still negligible there; tested against autograd) is far below the step's Monte-Carlo noise.
    """
    frozen = frozen_denoiser(denoiser, schedule)
    M, d = z.shape
    dirs = torch.cat([torch.zeros(1, d, device=z.device), torch.eye(d, device=z.device) * h])  # [d + 1, d]
    with torch.no_grad():
        if obs is None:
            obs = frozen.observations(windows.obs_cond.to(z.device))
        losses = _errors(frozen, schedule, windows, z[None] + dirs[:, None], idx, noise_samples, g, obs,
                         sample_steps)  # [d + 1, M]
        grad = (losses[1:] - losses[:1]).T / h + 2 * lam * z
        loss = losses[0].sum() + lam * z.pow(2).sum()
    return loss, grad


def fit_latent(denoiser: FiLMUnet1d | FrozenDenoiser, schedule, windows: DemoWindows, z0: Tensor, steps: int, lr: float, lam: float,
               batch_size: int, noise_samples: int = 1, seed: int | None = 0, progress: bool = False,
               gradient: str = "auto", sample_steps: int | None = None, optimizer: str = "adam") -> FitResult:
    """Gradient steps on z (weights frozen). Each step samples demonstration chunks and noise afresh (Alg. 3).

    ``optimizer``: ``"adam"`` returns the mean of the last 20 % of its iterates, ``"gradient"`` takes the
    paper's plain steps z <- z - lr * grad and returns the last.

    ``gradient``: ``"autograd"`` (backward to z), ``"finite_difference"`` (:func:`fit_loss_and_grad_fd`)
    or ``"auto"`` (finite differences for d_z <= 3 where they are cheaper, on the noise-prediction loss only).
    ``sample_steps``: fit the
    chunks the policy samples in that many DDIM steps instead of its noise predictions (see :func:`fit_loss`).
    """
    if gradient not in FIT_GRADIENTS:
        raise ValueError(f"gradient must be one of {FIT_GRADIENTS}, got {gradient!r}")
    if optimizer not in ("adam", "gradient"):
        raise ValueError(f"optimizer must be 'adam' or 'gradient', got {optimizer!r}")
    # the sampled-chunk loss has kinks where x0 clipping starts to act, which one-sided differences smear
    use_fd = gradient == "finite_difference" or (gradient == "auto" and z0.shape[-1] <= 3 and sample_steps is None)
    g = torch.Generator()
    g.manual_seed(int(seed) if seed is not None else int(np.random.SeedSequence().entropy % 2**63))
    z = z0.detach().clone().float().requires_grad_(True)
    opt = torch.optim.Adam([z], lr=lr) if optimizer == "adam" else torch.optim.SGD([z], lr=lr)
    losses: list[float] = []
    # L_fit is a Monte-Carlo estimate (random chunks, k and eps each step), so Adam's last iterates jitter
    # around the optimum; averaging the final 20 % of them (Polyak averaging) returns its centre. The
    # paper's plain steps return the last iterate.
    tail_start = steps - max(1, steps // 5) if optimizer == "adam" else steps - 1
    z_sum = torch.zeros_like(z)
    iterator = range(steps)
    if progress:
        from tqdm.auto import tqdm

        iterator = tqdm(iterator, desc="fit_latent", leave=False)
    frozen = frozen_denoiser(denoiser, schedule)
    with torch.no_grad():
        obs = frozen.observations(windows.obs_cond.to(z.device))
    for i in iterator:
        _check_cancelled()
        idx = _stratified_batch(windows.segment, windows.n_segments, batch_size, g)
        if use_fd:
            loss, grad = fit_loss_and_grad_fd(frozen, schedule, windows, z.detach(), idx, noise_samples, lam, g,
                                              obs, sample_steps=sample_steps)
        else:
            loss = fit_loss(frozen, schedule, windows, z, idx, noise_samples, lam, g, obs, sample_steps)
            (grad,) = torch.autograd.grad(loss, z)
        z.grad = grad
        opt.step()
        losses.append(float(loss.detach()))
        if i >= tail_start:
            z_sum += z.detach()
    z_final = z_sum / (steps - tail_start) if steps > 0 else z.detach()
    return FitResult(z=z_final.cpu(), z_init=z0.detach().cpu(), losses=losses, steps=steps)


def demonstration_error(denoiser: FiLMUnet1d | FrozenDenoiser, schedule, windows: DemoWindows, z: Tensor, chunks: int = 256, seed: int = 0,
                        spread_steps: bool = True) -> float:
    """L_fit without lambda|z|^2 on every window of the demonstration at ``z`` [M, d_z], as a mean over phases:
    the noise-prediction error that ``train_loss_dp`` measures for the training demonstrations at their own
    latents, so the two compare. Each window gets ``ceil(chunks / windows)`` noise draws, their diffusion steps
    stratified (:func:`_spread_steps`; ``spread_steps=False``: uniform draws, the same mean, noisier)."""
    g = torch.Generator().manual_seed(seed)
    frozen = frozen_denoiser(denoiser, schedule)
    n = len(windows.segment)
    with torch.no_grad():
        obs = frozen.observations(windows.obs_cond.to(z.device))
        per_phase = _phase_losses(frozen, schedule, windows, z[None].float(), torch.arange(n), -(-chunks // n), g,
                                  obs, spread_steps)[0]
    return float(per_phase.mean())


def fit_chunk_noise(denoiser: FiLMUnet1d | FrozenDenoiser, schedule, windows: DemoWindows, z: Tensor, chunk_frames: int, sample_steps: int,
                    steps: int = 100, lr: float = 0.05, batch_size: int = 32, seed: int = 0,
                    progress: bool = False) -> Tensor:
    """One initial sampler noise per executed chunk of the demonstration, z [M, d_z] fixed: noise x_j is
    optimised (Adam) so that the ``sample_steps``-step DDIM chain from it, under z and each window's
    observations, reproduces the chunks of the windows at frames ``j * chunk_frames ...`` (masked MSE, as
    :func:`_phase_sample_losses`), every weight frozen. Returns [C, horizon, A], detached, on z's device.

    The same adaptation as DP's noise per chunk (``benchmark.baselines.adapt_dp_noise``), on top of PDP's z."""
    device = z.device
    n = len(windows.segment)
    chunk_of = (torch.arange(n) // chunk_frames).to(device)
    g = torch.Generator().manual_seed(int(seed))
    frozen = frozen_denoiser(denoiser, schedule)
    actions, is_pad, seg_all = windows.actions.to(device), windows.is_pad.to(device), windows.segment.to(device)
    x = torch.randn(int(chunk_of.max()) + 1, *actions.shape[1:], generator=g).to(device).requires_grad_(True)
    with torch.no_grad():
        obs = frozen.observations(windows.obs_cond.to(device))
    opt = torch.optim.Adam([x], lr=lr)
    iterator = range(int(steps))
    if progress:  # the longer half of an adaptation with chunk noises (a DDIM chain per window and step)
        from tqdm.auto import tqdm

        iterator = tqdm(iterator, desc=f"fit {len(x)} chunk noises", leave=False)
    with torch.inference_mode(False), torch.enable_grad():
        for _ in iterator:
            _check_cancelled()
            idx = torch.randperm(n, generator=g)[:batch_size].to(device)
            with torch.no_grad():
                ctx = frozen.context(obs[idx], z.float(), seg_all[idx])
            chunk = _ddim_chain(frozen, schedule, x[chunk_of[idx]], ctx, sample_steps)
            mask = (~is_pad[idx]).unsqueeze(-1).to(chunk.dtype)
            loss = ((chunk - actions[idx]).pow(2) * mask).sum() / (mask.sum() * chunk.shape[-1]).clamp_min(1)
            (x.grad,) = torch.autograd.grad(loss, x)  # w.r.t. the noise alone: no weight gets a .grad
            opt.step()
    return x.detach()


def select_code(denoiser: FiLMUnet1d | FrozenDenoiser, schedule, windows: DemoWindows, codes: Tensor, batches: int, batch_size: int,
                noise_samples: int = 1, seed: int | None = 0, sample_steps: int | None = None
                ) -> tuple[Tensor, Tensor]:
    """Adaptation of a discrete latent: per phase, the one of ``codes`` [C, d_z] with the lowest L_fit (with
    ``sample_steps``, the lowest error of the chunks sampled in that many DDIM steps, as :func:`fit_loss`).

    Every code is scored on the same ``batches`` random batches of windows, steps and noise (common random
    numbers, so the comparison is not decided by the draws). Returns the chosen codes [M, d_z] and the mean
    loss of every code in every phase [C, M].
    """
    g = torch.Generator()
    g.manual_seed(int(seed) if seed is not None else int(np.random.SeedSequence().entropy % 2**63))
    frozen = frozen_denoiser(denoiser, schedule)
    codes = codes.float()
    M = windows.n_segments
    zs = codes[:, None, :].expand(len(codes), M, codes.shape[1])
    total = torch.zeros(len(codes), M, device=codes.device)
    with torch.no_grad():
        obs = frozen.observations(windows.obs_cond.to(codes.device))
        for _ in range(max(1, batches)):
            idx = _stratified_batch(windows.segment, M, batch_size, g)
            total += _errors(frozen, schedule, windows, zs, idx, noise_samples, g, obs, sample_steps)
    mean = total / max(1, batches)
    return codes[mean.argmin(0)], mean
