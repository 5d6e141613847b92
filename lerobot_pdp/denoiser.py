"""The latent-modulated denoiser eps_theta(A^k, k, c, z): a 1-D conditional U-Net over action chunks.

Structure follows Chi et al.'s ``ConditionalUnet1D`` (as in LeRobot's diffusion policy): residual conv
blocks whose features are FiLM-modulated by the global condition (observation history + diffusion-step
embedding). PDP adds a second, *behavior* modulation in every residual block (paper Fig. 2)::

    h <- gamma_l(z) * h + beta_l(z)

with a small MLP per block (hidden sizes ``film_hidden_dims``). gamma starts at 1 and beta at 0, so an
untrained z-branch is the identity and z has to earn its influence. Two ablations share the network:
``concat`` appends z to the global condition, ``none`` ignores z.

Also here: the noise schedule (K training steps) and the deterministic DDIM sampler used at inference.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn


class SinusoidalPosEmb(nn.Module):
    """Diffusion-step embedding."""

    def __init__(self, dim: int):
        super().__init__()
        self.dim = dim

    def forward(self, k: Tensor) -> Tensor:
        half = self.dim // 2
        freqs = torch.exp(torch.arange(half, device=k.device) * -(math.log(10000) / (half - 1)))
        emb = k.float()[:, None] * freqs[None, :]
        return torch.cat((emb.sin(), emb.cos()), dim=-1)


class Conv1dBlock(nn.Module):
    """Conv1d -> GroupNorm -> Mish."""

    def __init__(self, in_ch: int, out_ch: int, kernel_size: int, n_groups: int):
        super().__init__()
        self.block = nn.Sequential(
            nn.Conv1d(in_ch, out_ch, kernel_size, padding=kernel_size // 2),
            nn.GroupNorm(min(n_groups, out_ch), out_ch),
            nn.Mish(),
        )

    def forward(self, x: Tensor) -> Tensor:
        return self.block(x)

    def fast(self, x: Tensor) -> Tensor:
        """Inference path: the convolution as one matmul over unfolded windows.

        PyTorch's CPU conv1d takes its slow path for batch-1, short-sequence inputs (~30-80 us per call
        at 64-128 channels); unfold + matmul computes the same thing 2-3x faster.
        """
        conv, norm = self.block[0], self.block[1]
        k = conv.kernel_size[0]
        cols = F.pad(x, (k // 2, k // 2)).unfold(2, k, 1)  # [B, C, L, k]
        cols = cols.permute(0, 2, 1, 3).reshape(x.shape[0], x.shape[2], -1)
        h = F.linear(cols, conv.weight.reshape(conv.out_channels, -1), conv.bias).transpose(1, 2)
        return F.mish(F.group_norm(h, norm.num_groups, norm.weight, norm.bias, norm.eps))


class LatentFiLM(nn.Module):
    """z -> (gamma, beta) for one block: a lightweight MLP, initialised to the identity modulation."""

    def __init__(self, latent_dim: int, channels: int, hidden_dims: tuple[int, ...]):
        super().__init__()
        layers: list[nn.Module] = []
        d = latent_dim
        for h in hidden_dims:
            layers += [nn.Linear(d, h), nn.Mish()]
            d = h
        out = nn.Linear(d, 2 * channels)
        nn.init.zeros_(out.weight)  # gamma = 1, beta = 0 at init
        nn.init.zeros_(out.bias)
        self.mlp = nn.Sequential(*layers, out)

    def forward(self, z: Tensor) -> tuple[Tensor, Tensor]:
        d_gamma, beta = self.mlp(z).unsqueeze(-1).chunk(2, dim=1)
        return 1.0 + d_gamma, beta


class ConditionalResidualBlock1d(nn.Module):
    """Two conv blocks; after the first, FiLM by the global condition and (optionally) by z."""

    def __init__(self, in_ch: int, out_ch: int, cond_dim: int, kernel_size: int, n_groups: int,
                 latent_dim: int | None, film_hidden_dims: tuple[int, ...]):
        super().__init__()
        self.conv1 = Conv1dBlock(in_ch, out_ch, kernel_size, n_groups)
        self.conv2 = Conv1dBlock(out_ch, out_ch, kernel_size, n_groups)
        self.out_ch = out_ch
        self.cond_encoder = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * out_ch))
        self.latent_film = LatentFiLM(latent_dim, out_ch, film_hidden_dims) if latent_dim else None
        self.residual = nn.Conv1d(in_ch, out_ch, 1) if in_ch != out_ch else nn.Identity()

    def forward(self, x: Tensor, cond: Tensor, z: Tensor | None) -> Tensor:
        h = self.conv1(x)
        scale, bias = self.cond_encoder(cond).unsqueeze(-1).chunk(2, dim=1)
        h = scale * h + bias
        if self.latent_film is not None:
            gamma, beta = self.latent_film(z)
            h = gamma * h + beta
        h = self.conv2(h)
        return h + self.residual(x)

    def static_modulation(self, static_cond: Tensor, z: Tensor | None, step_dim: int) -> tuple[Tensor, Tensor, Tensor]:
        """What stays fixed while one chunk is denoised: the observation part of the condition and z's FiLM.

        ``Mish`` acts elementwise, so ``Linear(Mish([s, c]))`` = ``W_s Mish(s) + W_c Mish(c) + b``: the
        c-part (observations, and z for ``concat``) is computed once per chunk instead of once per step.
        Returns (static scale/bias pre-activation [B, 2C, 1], gamma [B, C, 1], beta [B, C, 1]).
        """
        lin = self.cond_encoder[1]
        static = F.linear(F.mish(static_cond), lin.weight[:, step_dim:], lin.bias).unsqueeze(-1)
        if self.latent_film is not None:
            gamma, beta = self.latent_film(z)
        else:
            gamma = beta = None
        return static, gamma, beta

    def forward_cached(self, x: Tensor, step_feat: Tensor, static: Tensor, gamma: Tensor | None,
                       beta: Tensor | None, step_dim: int) -> Tensor:
        """Same as ``forward`` with the chunk-constant parts precomputed (see ``static_modulation``)."""
        h = self.conv1.fast(x)
        lin = self.cond_encoder[1]
        scale, bias = (F.linear(step_feat, lin.weight[:, :step_dim]).unsqueeze(-1) + static).chunk(2, dim=1)
        if gamma is not None:
            # fold both modulations into one affine map: gamma * (scale * h + bias) + beta
            h = torch.addcmul(gamma * bias + beta, gamma * scale, h)
        else:
            h = torch.addcmul(bias, scale, h)
        h = self.conv2.fast(h)
        if isinstance(self.residual, nn.Conv1d):  # 1x1 conv = a linear map over channels
            res = F.linear(x.transpose(1, 2), self.residual.weight[..., 0], self.residual.bias).transpose(1, 2)
        else:
            res = x
        return h + res


class FiLMUnet1d(nn.Module):
    """eps_theta(A^k, k, c, z) over chunks ``[B, horizon, action_dim]``.

    Args:
        action_dim: dimension of one action.
        obs_cond_dim: flattened observation-history dimension (the global condition c).
        latent_dim: d_z; used by ``film`` and ``concat`` conditioning.
        latent_conditioning: ``"film"`` | ``"concat"`` | ``"none"``.
    """

    def __init__(self, action_dim: int, obs_cond_dim: int, latent_dim: int, latent_conditioning: str = "film",
                 down_dims: tuple[int, ...] = (32, 64, 128), kernel_size: int = 5, n_groups: int = 8,
                 step_embed_dim: int = 64, film_hidden_dims: tuple[int, ...] = (16, 32)):
        super().__init__()
        self.latent_conditioning = latent_conditioning
        self.step_encoder = nn.Sequential(
            SinusoidalPosEmb(step_embed_dim),
            nn.Linear(step_embed_dim, step_embed_dim * 4),
            nn.Mish(),
            nn.Linear(step_embed_dim * 4, step_embed_dim),
        )
        self.step_embed_dim = step_embed_dim
        cond_dim = step_embed_dim + obs_cond_dim + (latent_dim if latent_conditioning == "concat" else 0)
        film_dim = latent_dim if latent_conditioning == "film" else None

        def block(i: int, o: int) -> ConditionalResidualBlock1d:
            return ConditionalResidualBlock1d(i, o, cond_dim, kernel_size, n_groups, film_dim, film_hidden_dims)

        dims = [action_dim, *down_dims]
        self.down = nn.ModuleList()
        for idx, (i, o) in enumerate(zip(dims[:-1], dims[1:], strict=True)):
            last = idx == len(down_dims) - 1
            self.down.append(nn.ModuleList([
                block(i, o), block(o, o),
                nn.Conv1d(o, o, 3, 2, 1) if not last else nn.Identity(),
            ]))
        self.mid = nn.ModuleList([block(down_dims[-1], down_dims[-1]), block(down_dims[-1], down_dims[-1])])
        self.up = nn.ModuleList()
        rev = list(reversed(down_dims))
        for i, o in zip(rev[:-1], rev[1:], strict=True):
            self.up.append(nn.ModuleList([
                block(i * 2, o), block(o, o),
                nn.ConvTranspose1d(o, o, 4, 2, 1),
            ]))
        self.final = nn.Sequential(
            Conv1dBlock(down_dims[0], down_dims[0], kernel_size, n_groups),
            nn.Conv1d(down_dims[0], action_dim, 1),
        )

    def forward(self, sample: Tensor, k: Tensor, obs_cond: Tensor, z: Tensor | None) -> Tensor:
        """sample: [B, T, A]; k: [B] diffusion steps; obs_cond: [B, C]; z: [B, d_z] or None."""
        x = sample.transpose(1, 2)
        cond = [self.step_encoder(k), obs_cond]
        if self.latent_conditioning == "concat":
            cond.append(z)
        cond = torch.cat(cond, dim=-1)
        film_z = z if self.latent_conditioning == "film" else None

        skips = []
        for res1, res2, downsample in self.down:
            x = res2(res1(x, cond, film_z), cond, film_z)
            skips.append(x)
            x = downsample(x)
        for res in self.mid:
            x = res(x, cond, film_z)
        for res1, res2, upsample in self.up:
            x = torch.cat((x, skips.pop()), dim=1)
            x = res2(res1(x, cond, film_z), cond, film_z)
            x = upsample(x)
        return self.final(x).transpose(1, 2)

    def blocks(self) -> list[ConditionalResidualBlock1d]:
        """Residual blocks in the order ``forward`` runs them."""
        out = []
        for res1, res2, _ in self.down:
            out += [res1, res2]
        out += list(self.mid)
        for res1, res2, _ in self.up:
            out += [res1, res2]
        return out

    @torch.no_grad()
    def make_context(self, obs_cond: Tensor, z: Tensor | None) -> list[tuple[Tensor, Tensor | None, Tensor | None]]:
        """Per-block chunk-constant modulation for :meth:`forward_cached` (inference only)."""
        static = obs_cond if self.latent_conditioning != "concat" else torch.cat([obs_cond, z], dim=-1)
        film_z = z if self.latent_conditioning == "film" else None
        return [b.static_modulation(static, film_z, self.step_embed_dim) for b in self.blocks()]

    @torch.no_grad()
    def forward_cached(self, sample: Tensor, k: Tensor, context: list) -> Tensor:
        """``forward`` for inference: only the diffusion-step part of the condition is recomputed."""
        x = sample.transpose(1, 2)
        step_feat = F.mish(self.step_encoder(k))
        ctx = iter(context)
        d = self.step_embed_dim
        skips = []
        for res1, res2, downsample in self.down:
            x = res1.forward_cached(x, step_feat, *next(ctx), d)
            x = res2.forward_cached(x, step_feat, *next(ctx), d)
            skips.append(x)
            x = downsample(x)
        for res in self.mid:
            x = res.forward_cached(x, step_feat, *next(ctx), d)
        for res1, res2, upsample in self.up:
            x = torch.cat((x, skips.pop()), dim=1)
            x = res1.forward_cached(x, step_feat, *next(ctx), d)
            x = res2.forward_cached(x, step_feat, *next(ctx), d)
            x = upsample(x)
        x = self.final[0].fast(x)
        return self.final[1](x).transpose(1, 2)


class NoiseSchedule(nn.Module):
    """DDPM forward process over K steps and a deterministic DDIM sampler (eta = 0) on a sub-grid.

    Written out here (instead of diffusers' schedulers) because latent fitting differentiates through
    ``add_noise`` and the per-step Python overhead of the sampler matters for millisecond latency.
    """

    def __init__(self, num_train_timesteps: int, beta_schedule: str = "squaredcos_cap_v2",
                 clip_sample: bool = True, clip_sample_range: float = 1.0):
        super().__init__()
        K = num_train_timesteps
        if beta_schedule == "squaredcos_cap_v2":
            f = [math.cos((t / K + 0.008) / 1.008 * math.pi / 2) ** 2 for t in range(K + 1)]
            betas = torch.tensor([min(1 - f[t + 1] / f[t], 0.999) for t in range(K)], dtype=torch.float64)
        else:
            betas = torch.linspace(1e-4, 0.02 * 100 / K, K, dtype=torch.float64).clamp(max=0.999)
        alphas_cumprod = torch.cumprod(1 - betas, dim=0)
        self.register_buffer("alphas_cumprod", alphas_cumprod.float(), persistent=False)
        self.num_train_timesteps = K
        self.clip_sample = clip_sample
        self.clip_sample_range = clip_sample_range

    def add_noise(self, x0: Tensor, eps: Tensor, k: Tensor) -> Tensor:
        a = self.alphas_cumprod[k].view(-1, *([1] * (x0.dim() - 1)))
        return a.sqrt() * x0 + (1 - a).sqrt() * eps

    def timesteps(self, num_inference_steps: int) -> list[int]:
        """Evenly spaced steps from K-1 down to 0."""
        n = num_inference_steps
        K = self.num_train_timesteps
        return [int(round(K - 1 - i * (K - 1) / max(n - 1, 1))) for i in range(n)] if n > 1 else [K - 1]

    def ddim_step(self, eps_pred: Tensor, k: int, k_prev: int | None, x: Tensor) -> Tensor:
        a = self.alphas_cumprod[k]
        a_prev = self.alphas_cumprod[k_prev] if k_prev is not None else torch.ones_like(a)
        x0 = (x - (1 - a).sqrt() * eps_pred) / a.sqrt()
        if self.clip_sample:
            x0 = x0.clamp(-self.clip_sample_range, self.clip_sample_range)
            eps_pred = (x - a.sqrt() * x0) / (1 - a).sqrt()
        return a_prev.sqrt() * x0 + (1 - a_prev).sqrt() * eps_pred

    def sample(self, model, noise: Tensor, num_inference_steps: int, **model_kwargs) -> Tensor:
        """Denoise ``noise`` with ``model(x, k, **model_kwargs)`` in ``num_inference_steps`` DDIM steps."""
        x = noise
        steps = self.timesteps(num_inference_steps)
        for i, k in enumerate(steps):
            kk = torch.full((x.shape[0],), k, dtype=torch.long, device=x.device)
            eps = model(x, kk, **model_kwargs)
            x = self.ddim_step(eps, k, steps[i + 1] if i + 1 < len(steps) else None, x)
        return x


def diffusion_loss(pred: Tensor, target: Tensor, is_pad: Tensor | None = None) -> Tensor:
    """Mean squared noise-prediction error (optionally ignoring copy-padded actions)."""
    loss = F.mse_loss(pred, target, reduction="none")
    if is_pad is None:
        return loss.mean()
    mask = (~is_pad).unsqueeze(-1).to(loss.dtype)
    return (loss * mask).sum() / (mask.sum() * loss.shape[-1]).clamp_min(1)
