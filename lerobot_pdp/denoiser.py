"""The latent-modulated denoiser eps_theta(A^k, k, c, z): a 1-D conditional U-Net over action chunks.

Structure follows Chi et al.'s ``ConditionalUnet1D`` (as in LeRobot's diffusion policy): residual conv
blocks whose features are FiLM-modulated by the global condition (observation history + diffusion-step
embedding). PDP adds a second, *behavior* modulation in every residual block (paper Fig. 2)::

    h <- gamma_l(z) * h + beta_l(z)

with a small MLP per block (hidden sizes ``film_hidden_dims``). gamma starts at 1 and beta at 0, so an
untrained z-branch is the identity and z has to earn its influence. Three ablations share the network:
``concat`` appends the raw z to the global condition (after the condition encoder's Mish, which acts on
the step embedding and observations only: the first map z meets is linear), so z still reaches every
block through the condition's FiLM Linear (an affine FiLM by z in all but name); ``input`` appends z to the
denoiser's *input*, as extra channels of the noisy chunk at every time step (the paper's shallow
concatenation ablation: z meets only the first convolution); ``none`` ignores z.

This module is the network and its one reference forward, which training runs. The sampler and latent
fitting compute the same function faster (precomputed modulation, unfolded convolutions, a TorchScript
trace): ``fast_inference.py``, pinned to this forward by tests. The noise schedule and the loss live in
``diffusion.py`` (re-exported here for older imports).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from .diffusion import TIMESTEP_SPACINGS, NoiseSchedule, diffusion_loss

__all__ = ["TIMESTEP_SPACINGS", "ConditionalResidualBlock1d", "Conv1dBlock", "FiLMUnet1d", "LatentFiLM",
           "NoiseSchedule", "SinusoidalPosEmb", "diffusion_loss"]


class SinusoidalPosEmb(nn.Module):
    """Diffusion-step embedding."""

    def __init__(self, dim: int):
        super().__init__()
        self.dim = dim

    def forward(self, k: Tensor) -> Tensor:
        half = self.dim // 2
        # float32 for integer steps; a floating k keeps its dtype (a float64 copy of the model stays float64)
        dtype = k.dtype if k.is_floating_point() else torch.float32
        freqs = torch.exp(torch.arange(half, device=k.device, dtype=dtype) * -(math.log(10000) / (half - 1)))
        emb = k.to(dtype)[:, None] * freqs[None, :]
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

    def forward(self, x: Tensor, cond: Tensor, z: Tensor | None, z_concat: Tensor | None = None) -> Tensor:
        """``z`` FiLM-modulates (``film``); ``z_concat`` joins the condition after its Mish (``concat``)."""
        h = self.conv1(x)
        act = self.cond_encoder[0](cond)
        if z_concat is not None:
            act = torch.cat([act, z_concat], dim=-1)
        scale, bias = self.cond_encoder[1](act).unsqueeze(-1).chunk(2, dim=1)
        h = scale * h + bias
        if self.latent_film is not None:
            gamma, beta = self.latent_film(z)
            h = gamma * h + beta
        h = self.conv2(h)
        return h + self.residual(x)


class FiLMUnet1d(nn.Module):
    """eps_theta(A^k, k, c, z) over chunks ``[B, horizon, action_dim]``.

    Args:
        action_dim: dimension of one action.
        obs_cond_dim: flattened observation-history dimension (the global condition c).
        latent_dim: d_z; used by ``film``, ``concat`` and ``input`` conditioning.
        latent_conditioning: ``"film"`` | ``"concat"`` | ``"input"`` | ``"none"``.
    """

    def __init__(self, action_dim: int, obs_cond_dim: int, latent_dim: int, latent_conditioning: str = "film",
                 down_dims: tuple[int, ...] = (32, 64, 128), kernel_size: int = 5, n_groups: int = 8,
                 step_embed_dim: int = 64, film_hidden_dims: tuple[int, ...] = (16, 32)):
        super().__init__()
        self.latent_conditioning = latent_conditioning
        self.obs_cond_dim = obs_cond_dim
        self.step_embed_dim = step_embed_dim
        self.step_encoder = nn.Sequential(
            SinusoidalPosEmb(step_embed_dim),
            nn.Linear(step_embed_dim, step_embed_dim * 4),
            nn.Mish(),
            nn.Linear(step_embed_dim * 4, step_embed_dim),
        )
        cond_dim = step_embed_dim + obs_cond_dim + (latent_dim if latent_conditioning == "concat" else 0)
        film_dim = latent_dim if latent_conditioning == "film" else None

        def block(i: int, o: int) -> ConditionalResidualBlock1d:
            return ConditionalResidualBlock1d(i, o, cond_dim, kernel_size, n_groups, film_dim, film_hidden_dims)

        # ``input``: z as d_z extra input channels, constant over the chunk (see with_input_latent)
        self.input_latent_dim = latent_dim if latent_conditioning == "input" else 0
        dims = [action_dim + self.input_latent_dim, *down_dims]
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
        if self.input_latent_dim:
            x = self.with_input_latent(x, z[:, :, None])
        cond = torch.cat([self.step_encoder(k), obs_cond], dim=-1)
        film_z = z if self.latent_conditioning == "film" else None
        cat_z = z if self.latent_conditioning == "concat" else None

        skips = []
        for res1, res2, downsample in self.down:
            x = res2(res1(x, cond, film_z, cat_z), cond, film_z, cat_z)
            skips.append(x)
            x = downsample(x)
        for res in self.mid:
            x = res(x, cond, film_z, cat_z)
        for res1, res2, upsample in self.up:
            x = torch.cat((x, skips.pop()), dim=1)
            x = res2(res1(x, cond, film_z, cat_z), cond, film_z, cat_z)
            x = upsample(x)
        return self.final(x).transpose(1, 2)

    @staticmethod
    def with_input_latent(x: Tensor, z: Tensor) -> Tensor:
        """[B, A, T] chunk with z [B, d_z, 1] appended as d_z channels, the same at every time step."""
        return torch.cat([x, z.expand(-1, -1, x.shape[-1])], dim=1)

    def blocks(self) -> list[ConditionalResidualBlock1d]:
        """Residual blocks in the order ``forward`` runs them."""
        out = []
        for res1, res2, _ in self.down:
            out += [res1, res2]
        out += list(self.mid)
        for res1, res2, _ in self.up:
            out += [res1, res2]
        return out
