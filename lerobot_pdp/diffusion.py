"""The diffusion process around the denoiser: the noise schedule, the DDIM sampler and the training loss."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

TIMESTEP_SPACINGS = ("even", "leading", "trailing")


class PrefixGuide:
    """An x0 edit pulling each step's predicted clean chunk towards ``target`` [B, horizon, A] by ``weight``
    [1, horizon, 1] (``torch.lerp``): real-time chunking's prefix. Tensors, not a closure, so that a CUDA graph of
    the sampler takes them as inputs and replays for every new prefix."""

    def __init__(self, target: Tensor, weight: Tensor):
        self.target, self.weight = target, weight

    def __call__(self, x0: Tensor) -> Tensor:
        return torch.lerp(x0, self.target, self.weight)


class NoiseSchedule(nn.Module):
    """DDPM forward process over K steps and a deterministic DDIM sampler (eta = 0) on a sub-grid.

    Written out here (instead of diffusers' schedulers) because latent fitting differentiates through
    ``add_noise`` and the per-step Python overhead of the sampler matters for millisecond latency. The grid
    and the step rule can be exactly those of diffusers' ``DDIMScheduler`` as LeRobot's ``diffusion`` calls
    it (``timestep_spacing`` "leading" / "trailing", ``use_clipped_model_output=False``; pinned by a test),
    so that PDP and DP can sample with one sampler:

    - "even": n steps evenly spaced from K - 1 to 0, each going to the next grid point;
    - "leading" / "trailing": diffusers' grids (taken from diffusers), each step going from t to
      t - K // n, as diffusers' DDIM steps.
    """

    def __init__(self, num_train_timesteps: int, beta_schedule: str = "squaredcos_cap_v2",
                 clip_sample: bool = True, clip_sample_range: float = 1.0, timestep_spacing: str = "even",
                 use_clipped_model_output: bool = True, beta_start: float = 1e-4, beta_end: float = 0.02):
        super().__init__()
        if timestep_spacing not in TIMESTEP_SPACINGS:
            raise ValueError(f"timestep_spacing must be one of {TIMESTEP_SPACINGS}, got {timestep_spacing!r}")
        K = num_train_timesteps
        if beta_schedule == "squaredcos_cap_v2":
            f = [math.cos((t / K + 0.008) / 1.008 * math.pi / 2) ** 2 for t in range(K + 1)]
            betas = torch.tensor([min(1 - f[t + 1] / f[t], 0.999) for t in range(K)], dtype=torch.float64)
        elif beta_schedule == "linear":  # diffusers' (LeRobot diffusion's)
            betas = torch.linspace(beta_start, beta_end, K, dtype=torch.float64).clamp(max=0.999)
        else:
            raise ValueError(f"beta_schedule must be 'squaredcos_cap_v2' or 'linear', got {beta_schedule!r}")
        alphas_cumprod = torch.cumprod(1 - betas, dim=0)
        self.register_buffer("alphas_cumprod", alphas_cumprod.float(), persistent=False)
        self._alphas = alphas_cumprod.tolist()
        self.num_train_timesteps = K
        self.clip_sample = clip_sample
        self.clip_sample_range = clip_sample_range
        self.timestep_spacing = timestep_spacing
        self.use_clipped_model_output = use_clipped_model_output
        self._grids: dict[int, list[tuple[int, int | None]]] = {}

    def add_noise(self, x0: Tensor, eps: Tensor, k: Tensor) -> Tensor:
        a = self.alphas_cumprod[k].view(-1, *([1] * (x0.dim() - 1)))
        return a.sqrt() * x0 + (1 - a).sqrt() * eps

    def steps(self, num_inference_steps: int) -> list[tuple[int, int | None]]:
        """The sampler's (k, k_prev) pairs; k_prev None = the clean chunk (alpha_bar = 1)."""
        n, K = num_inference_steps, self.num_train_timesteps
        if n not in self._grids:
            if self.timestep_spacing == "even":
                ks = [int(round(K - 1 - i * (K - 1) / max(n - 1, 1))) for i in range(n)] if n > 1 else [K - 1]
                prev: list[int | None] = [*ks[1:], None]
            else:
                from diffusers import DDIMScheduler

                ref = DDIMScheduler(num_train_timesteps=K, timestep_spacing=self.timestep_spacing)
                ref.set_timesteps(n)
                ks = [int(k) for k in ref.timesteps]
                prev = [k - K // n if k - K // n >= 0 else None for k in ks]
            self._grids[n] = list(zip(ks, prev, strict=True))
        return self._grids[n]

    def timesteps(self, num_inference_steps: int) -> list[int]:
        """The diffusion steps the sampler visits, noisiest first."""
        return [k for k, _ in self.steps(num_inference_steps)]

    def ddim_step(self, eps_pred: Tensor, k: int, k_prev: int | None, x: Tensor,
                  guide: Callable[[Tensor], Tensor] | None = None) -> Tensor:
        """One DDIM step from ``x`` at step k; ``guide`` edits the predicted clean chunk before the step is
        taken (the noise is then re-derived from it, so the step moves towards the edited chunk)."""
        a = self._alphas[k]  # Python floats: each tensor op costs microseconds at batch size 1
        a_prev = self._alphas[k_prev] if k_prev is not None else 1.0
        x0 = (x - math.sqrt(1 - a) * eps_pred) * (1 / math.sqrt(a))
        if self.clip_sample:
            x0 = x0.clamp(-self.clip_sample_range, self.clip_sample_range)
            if self.use_clipped_model_output:
                eps_pred = (x - math.sqrt(a) * x0) * (1 / math.sqrt(1 - a))
        if guide is not None:
            x0 = guide(x0)
            eps_pred = (x - math.sqrt(a) * x0) * (1 / math.sqrt(1 - a))
        return torch.add(math.sqrt(a_prev) * x0, eps_pred, alpha=math.sqrt(1 - a_prev))

    def sample(self, denoise: Callable[[Tensor, int, int], Tensor], noise: Tensor,
               num_inference_steps: int, guide: Callable[[Tensor], Tensor] | None = None) -> Tensor:
        """Denoise ``noise`` in ``num_inference_steps`` DDIM steps.

        ``denoise(x, i, k)`` predicts the noise in ``x`` at the i-th sampler step, diffusion step k; ``guide``
        (optional) edits each step's predicted clean chunk (real-time chunking's prefix, ``realtime_chunking.py``).
        """
        x = noise
        for i, (k, k_prev) in enumerate(self.steps(num_inference_steps)):
            x = self.ddim_step(denoise(x, i, k), k, k_prev, x, guide)
        return x


def diffusion_loss(pred: Tensor, target: Tensor, is_pad: Tensor | None = None) -> Tensor:
    """Mean squared noise-prediction error (optionally ignoring copy-padded actions)."""
    loss = F.mse_loss(pred, target, reduction="none")
    if is_pad is None:
        return loss.mean()
    mask = (~is_pad).unsqueeze(-1).to(loss.dtype)
    return (loss * mask).sum() / (mask.sum() * loss.shape[-1]).clamp_min(1)
