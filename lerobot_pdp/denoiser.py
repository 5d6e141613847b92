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

Also here: the noise schedule (K training steps) and the deterministic DDIM sampler used at inference.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import Any

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

    def fast(self, x: Tensor) -> Tensor:
        """Inference path: the convolution as one matmul over unfolded windows (see ``conv1d_unfolded``)."""
        norm = self.block[1]
        h = conv1d_unfolded(x, self.block[0])
        return F.mish(F.group_norm(h, norm.num_groups, norm.weight, norm.bias, norm.eps))


def conv1d_unfolded(x: Tensor, conv: nn.Conv1d) -> Tensor:
    """``conv(x)`` as one matmul over unfolded windows (inference path).

    PyTorch's CPU conv1d takes a slow path for batch-1, short-sequence inputs (20-80 us per call at 32-128
    channels); unfold + matmul computes the same thing 2-3x faster.
    """
    (k,), (stride,), (pad,) = conv.kernel_size, conv.stride, conv.padding
    cols = (F.pad(x, (pad, pad)) if pad else x).unfold(2, k, stride)  # [B, C, L', k]
    cols = cols.permute(0, 2, 1, 3).reshape(x.shape[0], cols.shape[2], -1)
    return F.linear(cols, conv.weight.reshape(conv.out_channels, -1), conv.bias).transpose(1, 2)


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

    def forward_cached(self, x: Tensor, scale: Tensor, bias: Tensor, fast_conv: bool = True,
                       conv_residual: bool = False) -> Tensor:
        """``forward`` with the whole modulation after conv1 precomputed: ``scale * h + bias``.
        ``conv_residual`` keeps the 1x1 residual a convolution (training: one kernel, not a copy and a matmul)."""
        conv1, conv2 = (self.conv1.fast, self.conv2.fast) if fast_conv else (self.conv1, self.conv2)
        h = conv2(torch.addcmul(bias, scale, conv1(x)))
        if conv_residual:
            return h + self.residual(x)
        if isinstance(self.residual, nn.Conv1d):  # 1x1 conv = a matmul over channels
            w = self.residual.weight[..., 0]
            if x.shape[0] == 1:  # batch-1 inference: one small bmm is the cheapest call
                # (expand to x's size, not to 1: a trace made at batch 1 must replay at any batch size)
                return torch.baddbmm(h + self.residual.bias[:, None], w.expand(x.shape[0], -1, -1), x)
            # larger batches (latent fitting): one [B*T, C_in] x [C_in, C_out] matmul; a bmm over the
            # batch with broadcast weights costs ~5x more here
            return h + F.linear(x.transpose(1, 2), w, self.residual.bias).transpose(1, 2)
        return h + x


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

        # ``input``: z as d_z extra input channels, constant over the chunk (see _with_input_latent)
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
        self._consts: tuple | None = None  # see weight_constants
        self._modules_flat: list[nn.Module] | None = None
        self._traced: dict[tuple, Any] = {}  # TorchScript traces of forward_cached, see run_cached
        # The sampler's convolutions as unfold + matmul on a GPU too: measured against cuDNN's conv inside
        # the captured graph, equal within 2 % (benchmarks/bench_select_action.py, ``pdp`` vs ``pdp_cudnn``).
        self.unfold_on_gpu = True
        self.final = nn.Sequential(
            Conv1dBlock(down_dims[0], down_dims[0], kernel_size, n_groups),
            nn.Conv1d(down_dims[0], action_dim, 1),
        )
        # rows of each block's scale and bias in a modulation row vector (fixed by the architecture); with
        # ``input`` conditioning the vector ends with z itself, so every cached path (sampler, CUDA graph,
        # latent fitting) carries z to the input the way it carries the blocks' modulation
        self._block_rows = sum(2 * b.out_ch for b in self.blocks())
        self._mod_sizes = [ch for b in self.blocks() for ch in (b.out_ch, b.out_ch)]
        if self.input_latent_dim:
            self._mod_sizes.append(self.input_latent_dim)
        # Training runs the whole conditioning of all blocks as a few large ops (``modulation``) instead of
        # ~10 small ones per block: on a GPU a small model's step is bound by kernel launches. Off, the
        # blocks' own modules run one by one (``forward_blocks``, the reference it is tested against).
        self.fused_modulation = True
        # z's FiLM output rows are, per block, [d_gamma (C), beta (C)], aligned with its [scale, bias] rows:
        # gain = 1 + d_gamma on both, shift = beta on the bias rows only
        gain_index, bias_rows, row = [], [], 0
        for ch in self._mod_sizes[::2]:
            gain_index += [*range(row, row + ch), *range(row, row + ch)]
            bias_rows += [0.0] * ch + [1.0] * ch
            row += 2 * ch
        self.register_buffer("_film_gain_index", torch.tensor(gain_index), persistent=False)
        self.register_buffer("_film_bias_rows", torch.tensor(bias_rows), persistent=False)

    def forward(self, sample: Tensor, k: Tensor, obs_cond: Tensor, z: Tensor | None) -> Tensor:
        """sample: [B, T, A]; k: [B] diffusion steps; obs_cond: [B, C]; z: [B, d_z] or None."""
        if not self.fused_modulation:
            return self.forward_blocks(sample, k, obs_cond, z)
        mod = self.modulation(k, obs_cond, z)
        return self.forward_cached(sample, list(mod.unsqueeze(-1).split(self._mod_sizes, dim=1)), fast_conv=False,
                                   conv_residual=True)

    def modulation(self, k: Tensor, obs_cond: Tensor, z: Tensor | None) -> Tensor:
        """Every block's ``scale, bias`` rows [B, sum 2C], z's FiLM folded in, differentiable (training).

        ``Linear(Mish(cond))`` of all blocks is one matmul with their weights stacked; the z-MLPs of all
        blocks are one MLP (first layer stacked, later layers block-diagonal); and per block
        ``gamma * (scale * h + bias) + beta = (gamma scale) h + (gamma bias + beta)``.
        """
        blocks = self.blocks()
        lins = [b.cond_encoder[1] for b in blocks]
        act = F.mish(torch.cat([self.step_encoder(k), obs_cond], dim=-1))
        if self.latent_conditioning == "concat":
            act = torch.cat([act, z], dim=-1)  # raw z: no nonlinearity before its first linear map
        mod = F.linear(act, torch.cat([lin.weight for lin in lins]), torch.cat([lin.bias for lin in lins]))
        if self.latent_conditioning == "input":
            return torch.cat([mod, z], dim=-1)
        if self.latent_conditioning != "film":
            return mod
        *hidden, (w, b) = self._film_layers(blocks)
        h = z
        for wh, bh in hidden:
            h = F.mish(F.linear(h, wh, bh))
        h = F.linear(h, w, b)  # per block [d_gamma, beta]
        gain = 1.0 + h.index_select(1, self._film_gain_index)
        return torch.addcmul(h * self._film_bias_rows, gain, mod)

    def forward_blocks(self, sample: Tensor, k: Tensor, obs_cond: Tensor, z: Tensor | None) -> Tensor:
        """``forward`` through each block's own modules, one after the other."""
        x = sample.transpose(1, 2)
        if self.input_latent_dim:
            x = self._with_input_latent(x, z[:, :, None])
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
    def _with_input_latent(x: Tensor, z: Tensor) -> Tensor:
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

    # ------------------------------------------------------------------ precomputed-modulation path
    # Inference (~5 denoiser calls on a batch of one) and latent fitting (z is the only input that changes)
    # are dominated by eager PyTorch's per-op overhead (2-4 us), not arithmetic. This path therefore folds
    # the whole conditioning (step, observations, z) into one affine map per block, ``scale * h + bias``
    # after the block's first convolution, computed from precomputed weight constants in a few large ops.

    def weight_constants(self, steps: list[int]) -> dict[str, Any]:
        """Quantities that depend only on the weights and the diffusion steps, cached until a weight changes.

        ``Mish`` acts elementwise, so each block's ``Linear([Mish(s), Mish(c), z])`` splits into
        ``W_s Mish(s) + W_c Mish(c) + W_z z + b`` (``z`` only for ``concat``): the step part of every block and step is
        precomputed, and the observation part of all blocks is one matmul. The ten z-FiLM MLPs are stacked
        into one MLP (block-diagonal weights) that outputs the FiLM of all blocks at once.
        """
        # Module.parameters() walks the module tree (~0.35 ms here), so the module list is taken once;
        # optimizer steps and load_state_dict change weights in place, which bumps their _version.
        if self._modules_flat is None:
            self._modules_flat = list(self.modules())
        params = [p for m in self._modules_flat for p in m._parameters.values() if p is not None]
        key = (tuple(steps), tuple(map(id, params)), tuple(p._version for p in params), params[0].device,
               params[0].dtype)
        if self._consts is not None and self._consts[0] == key:
            return self._consts[1]
        d, c = self.step_embed_dim, self.obs_cond_dim
        blocks = self.blocks()
        lins = [b.cond_encoder[1] for b in blocks]
        with torch.no_grad():
            k = torch.as_tensor(steps, device=params[0].device, dtype=params[0].dtype)
            # ``input``: the rows after the blocks' are z itself (w_z = [0; I]), zero in every other term
            extra = self.input_latent_dim
            w_z = torch.cat([lin.weight[:, d + c :] for lin in lins])  # concat conditioning only
            if extra:
                w_z = torch.cat([w_z.new_zeros(self._block_rows, extra),
                                 torch.eye(extra, device=w_z.device, dtype=w_z.dtype)])
            step = F.linear(F.mish(self.step_encoder(k)), torch.cat([lin.weight[:, :d] for lin in lins]))
            consts = {
                "step": F.pad(step, (0, extra)),  # [S, rows]
                "w_obs": F.pad(torch.cat([lin.weight[:, d : d + c] for lin in lins]), (0, 0, 0, extra)),  # [rows, c]
                "b": F.pad(torch.cat([lin.bias for lin in lins]), (0, extra)),
                "w_z": w_z,
                # per block: C scale rows then C bias rows (``chunk(2)`` in ``forward``)
                "sizes": self.modulation_sizes(),
                "film": self._stacked_film(blocks) if self.latent_conditioning == "film" else None,
                "film_cache": None,  # (z, gain, shift) of the last z seen at inference
            }
        self._consts = (key, consts)
        return consts

    @staticmethod
    def _film_layers(blocks: list[ConditionalResidualBlock1d]) -> list[tuple[Tensor, Tensor]]:
        """All blocks' z-MLPs as one MLP, ``(weight, bias)`` per layer: layer 0 reads the shared z (weights
        stacked), later layers their block's slice (block-diagonal). Its output rows are, per block,
        ``[d_gamma, beta]``, aligned with the block's ``[scale, bias]`` modulation rows."""
        layers = [[m for m in b.latent_film.mlp if isinstance(m, nn.Linear)] for b in blocks]
        out = []
        for j in range(len(layers[0])):
            ws = [ls[j].weight for ls in layers]
            out.append((torch.cat(ws) if j == 0 else torch.block_diag(*ws), torch.cat([ls[j].bias for ls in layers])))
        return out

    def _stacked_film(self, blocks: list[ConditionalResidualBlock1d]) -> dict[str, Any]:
        """:meth:`_film_layers` with its last layer split into (gain, shift) on the modulation rows, so that
        inference applies z with two matmuls: gamma * (scale * h + bias) + beta = (gamma scale) h +
        (gamma bias + beta), i.e. per block gain = [gamma, gamma] and shift = [0, beta]."""
        *hidden, (w, b) = self._film_layers(blocks)
        idx, rows = self._film_gain_index, self._film_bias_rows
        return {"hidden": hidden, "gain": (w[idx], 1.0 + b[idx]), "shift": (w * rows[:, None], b * rows)}

    def latent_terms(self, consts: dict[str, Any], z: Tensor) -> tuple[Tensor | None, Tensor | None]:
        """z's contribution to the modulation rows: ``mod -> gain * mod + shift`` (differentiable in z)."""
        if self.latent_conditioning in ("concat", "input"):
            return None, F.linear(z, consts["w_z"])  # raw z: no nonlinearity before its first linear map
        if self.latent_conditioning != "film":
            return None, None
        film = consts["film"]
        h = z
        for w, b in film["hidden"]:
            h = F.mish(F.linear(h, w, b))
        return F.linear(h, *film["gain"]), F.linear(h, *film["shift"])

    def obs_modulation(self, consts: dict[str, Any], obs_cond: Tensor) -> Tensor:
        """The observation part of the modulation rows, [B, sum 2C] (constant while fitting z)."""
        return F.linear(F.mish(obs_cond), consts["w_obs"], consts["b"])

    @torch.no_grad()
    def make_context(self, obs_cond: Tensor, z: Tensor | None, steps: list[int],
                     cache_latent: bool = True) -> list[list[Tensor]]:
        """Everything but the sample that ``forward`` computes, for one chunk denoised at ``steps``.

        Returns, per step, the blocks' ``scale, bias`` ([B, C, 1] each, flattened in block order) that
        :meth:`forward_cached` applies after each block's first convolution.
        """
        sizes = self.modulation_sizes()
        return [list(m.unsqueeze(-1).split(sizes, dim=1))
                for m in self.make_modulation(obs_cond, z, steps, cache_latent)]

    def modulation_sizes(self) -> list[int]:
        """Rows of each block's ``scale`` and ``bias`` in a modulation row vector, in block order."""
        return self._mod_sizes

    @torch.no_grad()
    def make_modulation(self, obs_cond: Tensor, z: Tensor | None, steps: list[int],
                        cache_latent: bool = True) -> Tensor:
        """:meth:`make_context` before the split into blocks: [S, B, sum 2C] modulation rows per step.

        ``cache_latent`` reuses z's FiLM terms while z stays the same; comparing z reads it back to the
        host, so a captured CUDA graph (no host syncs allowed) computes them every time instead.
        """
        consts = self.weight_constants(steps)
        mod = consts["step"][:, None] + self.obs_modulation(consts, obs_cond)  # [S, B, sum 2C]
        if self.latent_conditioning != "none" and not cache_latent:
            gain, shift = self.latent_terms(consts, z)
            mod = mod + shift if gain is None else torch.addcmul(shift, gain, mod)
        elif self.latent_conditioning != "none":
            cached = consts["film_cache"]  # a steered policy keeps one z for many chunks
            if cached is None or cached[0].shape != z.shape or not torch.equal(cached[0], z):
                cached = consts["film_cache"] = (z.clone(), *self.latent_terms(consts, z))
            gain, shift = cached[1], cached[2]
            mod = mod + shift if gain is None else torch.addcmul(shift, gain, mod)
        return mod

    @staticmethod
    def split_modulation(consts: dict[str, Any], mod: Tensor) -> list[Tensor]:
        """[B, sum 2C] modulation rows -> per block ``scale, bias`` views [B, C, 1]."""
        return list(mod.unsqueeze(-1).split(consts["sizes"], dim=1))

    def forward_cached(self, sample: Tensor, context: list[Tensor], fast_conv: bool = True,
                       conv_residual: bool = False) -> Tensor:
        """``forward`` given the blocks' precomputed ``scale, bias`` (one step's entry of :meth:`make_context`).

        ``fast_conv`` runs convolutions as unfold + matmul (batch-1 inference); with autograd (latent
        fitting) PyTorch's own convolution is faster. ``conv_residual``: see the block's ``forward_cached``.
        """
        x = sample.transpose(1, 2)
        if self.input_latent_dim:  # the last entry is z [B, d_z, 1] (see _mod_sizes)
            x, context = self._with_input_latent(x, context[-1]), context[:-1]
        it = iter(context)
        ctx = zip(it, it, strict=True)  # (scale, bias) per block
        skips = []
        for res1, res2, downsample in self.down:
            x = res1.forward_cached(x, *next(ctx), fast_conv, conv_residual)
            x = res2.forward_cached(x, *next(ctx), fast_conv, conv_residual)
            skips.append(x)
            x = conv1d_unfolded(x, downsample) if fast_conv and isinstance(downsample, nn.Conv1d) else downsample(x)
        for res in self.mid:
            x = res.forward_cached(x, *next(ctx), fast_conv, conv_residual)
        for res1, res2, upsample in self.up:
            x = torch.cat((x, skips.pop()), dim=1)
            x = res1.forward_cached(x, *next(ctx), fast_conv, conv_residual)
            x = res2.forward_cached(x, *next(ctx), fast_conv, conv_residual)
            x = upsample(x)
        if not fast_conv:
            return self.final[1](self.final[0](x)).transpose(1, 2)
        out = self.final[1]  # 1x1 conv = a linear map over channels, straight into [B, T, A]
        return F.linear(self.final[0].fast(x).transpose(1, 2), out.weight[..., 0], out.bias)

    @torch.no_grad()
    def run_cached(self, sample: Tensor, context: list[Tensor]) -> Tensor:
        """:meth:`forward_cached`, on CPU through a TorchScript trace of it (built on first use); on a GPU
        eagerly (a CUDA graph captures it), with PyTorch's own convolutions if ``unfold_on_gpu`` is off.

        The trace runs the same ~160 ops without Python in between: ~0.9 -> ~0.75 ms per call here. It
        references the live parameters (not a frozen copy), so later weight updates are seen. TorchScript
        is deprecated upstream but present in every torch that lerobot 0.6 allows (< 2.12); if tracing
        fails for any reason the eager path is used.
        """
        if sample.device.type != "cpu":
            return self.forward_cached(sample, context, fast_conv=self.unfold_on_gpu)
        key = (sample.dtype, len(context))
        fn = self._traced.get(key)
        if fn is None:
            fn = self._traced[key] = self._trace(sample, context)
        return fn(sample, *context)

    def _trace(self, sample: Tensor, context: list[Tensor]):
        class _Cached(nn.Module):
            def __init__(self, net: FiLMUnet1d):
                super().__init__()
                self.net = net

            def forward(self, x: Tensor, *ctx: Tensor) -> Tensor:
                return self.net.forward_cached(x, list(ctx))

        try:
            with warnings.catch_warnings(), torch.no_grad():
                warnings.simplefilter("ignore")  # jit's DeprecationWarning and TracerWarnings
                return torch.jit.trace(_Cached(self), (sample, *context), check_trace=False)
        except Exception as e:  # pragma: no cover - depends on the torch build
            warnings.warn(f"TorchScript tracing of the denoiser failed ({e!r}); using eager inference",
                          stacklevel=3)
            return lambda x, *ctx: self.forward_cached(x, list(ctx))

    def __getstate__(self) -> dict:
        # traces and caches are rebuilt on demand; ScriptModules do not pickle
        state = self.__dict__.copy()
        state.update(_traced={}, _consts=None, _modules_flat=None)
        return state


TIMESTEP_SPACINGS = ("even", "leading", "trailing")


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
                 use_clipped_model_output: bool = True):
        super().__init__()
        if timestep_spacing not in TIMESTEP_SPACINGS:
            raise ValueError(f"timestep_spacing must be one of {TIMESTEP_SPACINGS}, got {timestep_spacing!r}")
        K = num_train_timesteps
        if beta_schedule == "squaredcos_cap_v2":
            f = [math.cos((t / K + 0.008) / 1.008 * math.pi / 2) ** 2 for t in range(K + 1)]
            betas = torch.tensor([min(1 - f[t + 1] / f[t], 0.999) for t in range(K)], dtype=torch.float64)
        else:
            betas = torch.linspace(1e-4, 0.02 * 100 / K, K, dtype=torch.float64).clamp(max=0.999)
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

    def ddim_step(self, eps_pred: Tensor, k: int, k_prev: int | None, x: Tensor) -> Tensor:
        a = self._alphas[k]  # Python floats: each tensor op costs microseconds at batch size 1
        a_prev = self._alphas[k_prev] if k_prev is not None else 1.0
        x0 = (x - math.sqrt(1 - a) * eps_pred) * (1 / math.sqrt(a))
        if self.clip_sample:
            x0 = x0.clamp(-self.clip_sample_range, self.clip_sample_range)
            if self.use_clipped_model_output:
                eps_pred = (x - math.sqrt(a) * x0) * (1 / math.sqrt(1 - a))
        return torch.add(math.sqrt(a_prev) * x0, eps_pred, alpha=math.sqrt(1 - a_prev))

    def sample(self, denoise: Callable[[Tensor, int, int], Tensor], noise: Tensor,
               num_inference_steps: int) -> Tensor:
        """Denoise ``noise`` in ``num_inference_steps`` DDIM steps.

        ``denoise(x, i, k)`` predicts the noise in ``x`` at the i-th sampler step, diffusion step k.
        """
        x = noise
        for i, (k, k_prev) in enumerate(self.steps(num_inference_steps)):
            x = self.ddim_step(denoise(x, i, k), k, k_prev, x)
        return x


def diffusion_loss(pred: Tensor, target: Tensor, is_pad: Tensor | None = None) -> Tensor:
    """Mean squared noise-prediction error (optionally ignoring copy-padded actions)."""
    loss = F.mse_loss(pred, target, reduction="none")
    if is_pad is None:
        return loss.mean()
    mask = (~is_pad).unsqueeze(-1).to(loss.dtype)
    return (loss * mask).sum() / (mask.sum() * loss.shape[-1]).clamp_min(1)
