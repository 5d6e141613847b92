"""The denoiser's fast paths: ``FiLMUnet1d.forward`` computed differently, for the sampler and latent fitting.

A new action chunk (a few denoiser calls on a batch of one) and a latent-fitting step (z is the only input
that changes) are dominated by eager PyTorch's per-op overhead (2-4 us), not by arithmetic. So:

- **Precomputed modulation** (:class:`FrozenDenoiser`): the whole conditioning of a residual block (diffusion
  step, observations, z's FiLM) is one affine map ``scale * h + bias`` after its first convolution. It is
  computed for all blocks at once from weight constants: the step part per diffusion step, the observation
  part as one matmul, the blocks' z-MLPs as one stacked MLP. What remains per call is the U-Net's
  convolutions, norms and one ``addcmul`` per block.
- **Unfolded convolutions** (``unfold=True``): each convolution as one matmul over unfolded windows;
  PyTorch's CPU conv1d takes a slow path for batch-1, short-sequence inputs. Used on a CPU without
  autograd (the sampler, finite-difference fitting); with a backward pass PyTorch's convolution is faster.
- **A TorchScript trace** of that call (:meth:`FastDenoiser.run`, CPU): the ~160 ops without Python between.

Dropped after measuring (docs/performance.md): unfolding on a GPU, a per-z cache of z's FiLM terms, and the
fused training forward (training runs the reference forward).

On a GPU the sampler is replayed from a CUDA graph (``cuda_graphs.py``, captured around
:meth:`FastDenoiser.sample_modulation` and :meth:`FrozenDenoiser.forward`) and ``compile_model`` compiles it.
Each path is pinned to the reference forward by tests/test_denoiser.py; what each gains on a 2-core CPU is
in docs/performance.md ("Fast inference paths", ``benchmarks/bench_fast_paths.py``).
"""

from __future__ import annotations

import operator
import threading
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

from .denoiser import ConditionalResidualBlock1d, Conv1dBlock, FiLMUnet1d

# One trace at a time: two threads (a fit beside the control loop) would trace the same denoiser twice, and the
# warning filters a trace sets are process-wide, so one finishing would restore them under the other's.
_TRACE_LOCK = threading.Lock()


def conv1d_unfolded(x: Tensor, conv: nn.Conv1d) -> Tensor:
    """``conv(x)`` as one matmul over unfolded windows.

    PyTorch's CPU conv1d costs 20-80 us per call on batch-1, short-sequence inputs at 32-128 channels;
    unfold + matmul computes the same thing 2-3x faster.
    """
    (k,), (stride,), (pad,) = conv.kernel_size, conv.stride, conv.padding
    cols = (F.pad(x, (pad, pad)) if pad else x).unfold(2, k, stride)  # [B, C, L', k]
    cols = cols.permute(0, 2, 1, 3).reshape(x.shape[0], cols.shape[2], -1)
    return F.linear(cols, conv.weight.reshape(conv.out_channels, -1), conv.bias).transpose(1, 2)


def _conv_block(block: Conv1dBlock, x: Tensor, unfold: bool) -> Tensor:
    if not unfold:
        return block(x)
    norm = block.block[1]
    h = conv1d_unfolded(x, block.block[0])
    # the aten op: F.group_norm's Python batch-size check warns under tracing (a TracerWarning), and the filter
    # _trace sets is process-wide, so another thread's catch_warnings could let it through
    return F.mish(torch.group_norm(h, norm.num_groups, norm.weight, norm.bias, norm.eps, torch.backends.cudnn.enabled))


def _residual_block(res: ConditionalResidualBlock1d, x: Tensor, scale: Tensor, bias: Tensor, unfold: bool) -> Tensor:
    """The block's ``forward`` with its whole modulation after conv1 given as ``scale * h + bias``."""
    h = _conv_block(res.conv2, torch.addcmul(bias, scale, _conv_block(res.conv1, x, unfold)), unfold)
    if not isinstance(res.residual, nn.Conv1d):
        return h + x
    if not unfold:
        return h + res.residual(x)
    # a 1x1 conv is one [B*T, C_in] x [C_in, C_out] matmul
    return h + F.linear(x.transpose(1, 2), res.residual.weight[..., 0], res.residual.bias).transpose(1, 2)


def modulated_forward(net: FiLMUnet1d, sample: Tensor, context: list[Tensor], unfold: bool) -> Tensor:
    """``net.forward`` given every block's ``scale, bias`` ([B, C, 1] each, in block order; with ``input``
    conditioning then z [B, d_z, 1]), as :func:`split_modulation` makes them. ``unfold``: convolutions
    as unfold + matmul (faster on a CPU without autograd)."""
    x = sample.transpose(1, 2)
    if net.input_latent_dim:
        x, context = net.with_input_latent(x, context[-1]), context[:-1]
    it = iter(context)
    ctx = zip(it, it, strict=True)  # (scale, bias) per block
    skips = []
    for res1, res2, downsample in net.down:
        x = _residual_block(res1, x, *next(ctx), unfold)
        x = _residual_block(res2, x, *next(ctx), unfold)
        skips.append(x)
        x = conv1d_unfolded(x, downsample) if unfold and isinstance(downsample, nn.Conv1d) else downsample(x)
    for res in net.mid:
        x = _residual_block(res, x, *next(ctx), unfold)
    for res1, res2, upsample in net.up:
        x = torch.cat((x, skips.pop()), dim=1)
        x = _residual_block(res1, x, *next(ctx), unfold)
        x = _residual_block(res2, x, *next(ctx), unfold)
        x = upsample(x)
    if not unfold:
        return net.final(x).transpose(1, 2)
    out = net.final[1]  # 1x1 conv = a linear map over channels, straight into [B, T, A]
    return F.linear(_conv_block(net.final[0], x, True).transpose(1, 2), out.weight[..., 0], out.bias)


def modulation_sizes(net: FiLMUnet1d) -> list[int]:
    """Rows of each block's scale and bias in a modulation row vector, in block order (fixed by the
    architecture); with ``input`` conditioning the rows end with z itself (d_z rows), so that every path
    carries z to the input the way it carries the blocks' modulation."""
    return [*(ch for b in net.blocks() for ch in (b.out_ch, b.out_ch)), *([net.input_latent_dim] * bool(net.input_latent_dim))]


def split_modulation(mod: Tensor, sizes: list[int]) -> list[Tensor]:
    """[B, R] modulation rows -> per block ``scale, bias`` views [B, C, 1] (then z for ``input``)."""
    return list(mod.unsqueeze(-1).split(sizes, dim=1))


@dataclass
class Context:
    """One chunk batch's conditioning without the diffusion step: modulation rows ``base`` [B, R] and z's
    FiLM gain on the step part (``None``: the step part is added as is)."""

    base: Tensor
    gain: Tensor | None


class FrozenDenoiser:
    """eps_theta with its weights frozen, as the sampler and latent fitting call it, over precomputed
    modulation rows (the layout stays in here).

        frozen = FrozenDenoiser(net, num_train_timesteps)
        obs = frozen.observations(obs_cond)    # once per set of chunks
        ctx = frozen.context(obs, z)           # differentiable in z
        eps = frozen.eps(sample, k, ctx)       # k: an int or one step per chunk

    ``Mish`` acts elementwise, so each block's ``Linear([Mish(s), Mish(c), z])`` splits into
    ``W_s Mish(s) + W_c Mish(c) + W_z z + b`` (``z`` only for ``concat``), and per block
    ``gamma (scale h + bias) + beta = (gamma scale) h + (gamma bias + beta)``: a chunk's modulation rows
    are ``gain * (step[k] + obs) + shift`` with (gain, shift) z's terms. The constants are taken when it is
    built: build a new one after the weights change.
    """

    def __init__(self, net: FiLMUnet1d, num_train_timesteps: int):
        self.net = net
        blocks = net.blocks()
        lins = [b.cond_encoder[1] for b in blocks]
        d, c = net.step_embed_dim, net.obs_cond_dim
        self.sizes = modulation_sizes(net)
        extra = net.input_latent_dim
        block_rows = sum(self.sizes) - extra
        w0 = lins[0].weight
        with torch.no_grad():
            k = torch.arange(num_train_timesteps, device=w0.device, dtype=w0.dtype)
            step = F.linear(F.mish(net.step_encoder(k)), torch.cat([lin.weight[:, :d] for lin in lins]))
            self.step = F.pad(step, (0, extra))  # [K, R]
            self.w_obs = F.pad(torch.cat([lin.weight[:, d : d + c] for lin in lins]), (0, 0, 0, extra))
            self.b = F.pad(torch.cat([lin.bias for lin in lins]), (0, extra))
            self.w_z: Tensor | None = None
            self.film: tuple | None = None
            if net.latent_conditioning == "concat":  # raw z: no nonlinearity before its first linear map
                self.w_z = torch.cat([lin.weight[:, d + c :] for lin in lins])
            elif net.latent_conditioning == "input":
                self.w_z = torch.cat([w0.new_zeros(block_rows, extra), torch.eye(extra, device=w0.device, dtype=w0.dtype)])
            elif net.latent_conditioning == "film":
                self.film = _stacked_film(blocks)

    def latent_terms(self, z: Tensor) -> tuple[Tensor | None, Tensor | None]:
        """z's contribution to the modulation rows, ``mod -> gain * mod + shift`` ([L, R] each or None)."""
        if self.w_z is not None:
            return None, F.linear(z, self.w_z)
        if self.film is None:
            return None, None
        hidden, gain, shift = self.film
        h = z
        for w, b in hidden:
            h = F.mish(F.linear(h, w, b))
        return F.linear(h, *gain), F.linear(h, *shift)

    def observations(self, obs_cond: Tensor) -> Tensor:
        """The observation part of the chunks' conditioning, one row per chunk ([B, R]; index or repeat it
        along with the chunks): what :meth:`context` takes, worth computing once while only z changes."""
        return F.linear(F.mish(obs_cond), self.w_obs, self.b)

    def context(self, observations: Tensor, z: Tensor | None, rows: Tensor | None = None,
                terms: tuple[Tensor | None, Tensor | None] | None = None) -> Context:
        """Conditioning of chunks with :meth:`observations` rows [B, R] under latents ``z`` [L, d_z]; chunk b
        takes latent ``rows[b]`` (default: b). Differentiable in z. ``terms``: z's :meth:`latent_terms`, when
        the caller kept them."""
        if terms is None:
            terms = self.latent_terms(z) if z is not None else (None, None)
        gain, shift = terms
        if rows is not None:
            gain = gain[rows] if gain is not None else None
            shift = shift[rows] if shift is not None else None
        if gain is not None:
            return Context(torch.addcmul(shift, gain, observations), gain)
        return Context(observations if shift is None else observations + shift, None)

    def modulation(self, k: int | list[int] | Tensor, ctx: Context) -> Tensor:
        """Modulation rows at diffusion step(s) ``k``: an int -> [B, R]; a tensor of one step per chunk
        -> [B, R]; a list of S steps -> [S, B, R]."""
        # a list's rows by Python ints (views, one stack): indexing with the list would first build an index
        # tensor on the host and copy it to the GPU, which a CUDA graph capture refuses (and which waits)
        step = self.step[k] if not isinstance(k, list) else torch.stack([self.step[i] for i in k])[:, None]
        return ctx.base + step if ctx.gain is None else torch.addcmul(ctx.base, ctx.gain, step)

    def forward(self, sample: Tensor, mod: Tensor, unfold: bool = False) -> Tensor:
        """The denoiser on [B, R] modulation rows (``unfold``: see :func:`modulated_forward`)."""
        return modulated_forward(self.net, sample, split_modulation(mod, self.sizes), unfold)

    def eps(self, sample: Tensor, k: int | Tensor, ctx: Context, unfold: bool | None = None) -> Tensor:
        """eps_theta(sample, k, ctx). ``unfold`` defaults to "when autograd is off": on a CPU, at latent
        fitting's batches, unfolded convolutions are ~10 % faster without a backward pass and ~13 % slower
        with one (docs/performance.md)."""
        return self.forward(sample, self.modulation(k, ctx), not torch.is_grad_enabled() if unfold is None else unfold)


def _stacked_film(blocks: list[ConditionalResidualBlock1d]) -> tuple:
    """All blocks' z-MLPs as one MLP: layer 0 reads the shared z (weights stacked), later layers their
    block's slice (block-diagonal). Its output rows, per block ``[d_gamma, beta]``, are mapped onto the
    block's ``[scale, bias]`` rows as ``gain = 1 + d_gamma`` on both and ``shift = beta`` on the bias rows:
    ``(hidden layers, gain (w, b), shift (w, b))``."""
    layers = [[m for m in b.latent_film.mlp if isinstance(m, nn.Linear)] for b in blocks]
    stacked = []
    for j in range(len(layers[0])):
        ws = [ls[j].weight for ls in layers]
        stacked.append((torch.cat(ws) if j == 0 else torch.block_diag(*ws), torch.cat([ls[j].bias for ls in layers])))
    *hidden, (w, b) = stacked
    index, bias_rows, row = [], [], 0
    for blk in blocks:
        ch = blk.out_ch
        index += [*range(row, row + ch), *range(row, row + ch)]
        bias_rows += [0.0] * ch + [1.0] * ch
        row += 2 * ch
    idx = torch.tensor(index, device=w.device)
    rows = torch.tensor(bias_rows, device=w.device, dtype=w.dtype)
    return hidden, (w[idx], 1.0 + b[idx]), (w * rows[:, None], b * rows)


class FastDenoiser:
    """The sampler's view of a denoiser: a :class:`FrozenDenoiser` rebuilt when a weight changes, and on CPU
    a TorchScript trace of its (unfolded) batch-1 call.

    Weight changes are seen through the parameters' ``_version`` counters (optimizer steps and
    ``load_state_dict`` change weights in place), their identity, device and dtype.
    """

    def __init__(self, net: FiLMUnet1d, num_train_timesteps: int):
        self.net = net
        self.num_train_timesteps = num_train_timesteps
        self.sizes = modulation_sizes(net)
        # (parameters, their versions and storages, device, dtype) the FrozenDenoiser was built from, and it
        self._frozen: tuple[list[Tensor], list[tuple[int, int]], torch.device, torch.dtype, FrozenDenoiser] | None = None
        self._param_dicts: list[dict] | None = None
        self._traced: dict[tuple, Callable] = {}
        # z's modulation terms of the last chunk: (FrozenDenoiser, inference mode, a copy of z, terms)
        self._terms: tuple | None = None

    def frozen(self) -> FrozenDenoiser:
        """The current weights' :class:`FrozenDenoiser` (the same object until a weight changes: a captured
        CUDA graph that reads its constants is recaptured when it is not)."""
        if self._param_dicts is None:  # Module.parameters() walks the module tree (~0.35 ms here): once
            self._param_dicts = [m._parameters for m in self.net.modules() if m._parameters]
        # checked per chunk, so kept cheap (~0.08 ms for 220 parameters; id() and tuple keys took 0.24 ms)
        params = [p for d in self._param_dicts for p in d.values() if p is not None]
        # the storage too: ``.to()`` there and back (or ``p.data = ...``) gives a parameter new memory under the same
        # version, and a captured sampler graph, which reads the weights, would go on reading the freed memory
        versions = [(p._version, p.data_ptr()) for p in params]
        old = self._frozen
        same = old is not None and len(params) == len(old[0]) and all(map(operator.is_, params, old[0]))
        if not same:  # parameters replaced by new objects (load_state_dict(assign=True)): a trace holds the old ones
            self._traced = {}
        if not same or versions != old[1] or params[0].device != old[2] or params[0].dtype != old[3]:
            self._frozen = old = (params, versions, params[0].device, params[0].dtype,
                                  FrozenDenoiser(self.net, self.num_train_timesteps))
        return old[4]

    @torch.no_grad()
    def sample_modulation(self, obs_cond: Tensor, z: Tensor | None, steps: list[int]) -> Tensor:
        """Modulation rows of one chunk batch at each sampler step: [S, B, R]."""
        frozen = self.frozen()
        return frozen.modulation(steps, frozen.context(frozen.observations(obs_cond), z, terms=self._latent_terms(frozen, z)))

    def _latent_terms(self, frozen: FrozenDenoiser, z: Tensor | None) -> tuple[Tensor | None, Tensor | None]:
        """z's terms, reused while z and the weights stay the same (a robot acts on one latent for many chunks;
        the FiLM MLP is ~5 % of a CPU chunk). CPU only: comparing z on a GPU would wait for it."""
        if z is None or z.device.type != "cpu":
            return frozen.latent_terms(z) if z is not None else (None, None)
        inference = torch.is_inference_mode_enabled()
        kept = self._terms
        if (kept is not None and kept[0] is frozen and kept[1] == inference and kept[2].shape == z.shape
                and kept[2].dtype == z.dtype and torch.equal(kept[2], z)):
            return kept[3]
        terms = frozen.latent_terms(z)
        self._terms = (frozen, inference, z.clone(), terms)
        return terms

    def contexts(self, obs_cond: Tensor, z: Tensor | None, steps: list[int]) -> list[list[Tensor]]:
        """:meth:`sample_modulation` split per step into the blocks' ``scale, bias``, as :meth:`run` takes them."""
        return [split_modulation(m, self.sizes) for m in self.sample_modulation(obs_cond, z, steps)]

    def forward(self, sample: Tensor, mod: Tensor) -> Tensor:
        """The denoiser on one step's [B, R] rows of :meth:`sample_modulation`, eagerly (what
        ``compile_model`` compiles: no weight check, which would not trace)."""
        return modulated_forward(self.net, sample, split_modulation(mod, self.sizes), False)

    @torch.no_grad()
    def run(self, sample: Tensor, context: list[Tensor]) -> Tensor:
        """One sampler step's denoiser call (a step's entry of :meth:`contexts`): on CPU through a
        TorchScript trace of the unfolded path (built on first use), on a GPU eagerly with PyTorch's (cuDNN)
        convolutions (a CUDA graph captures it; unfolding measured equal there, within 2 %).

        The trace runs the same ~160 ops without Python in between. It references the live parameters
        (not a frozen copy), so later weight updates are seen. TorchScript is deprecated upstream but present
        in every torch that lerobot 0.6 allows (< 2.12); if tracing fails the eager path is used.
        """
        if sample.device.type != "cpu":
            return modulated_forward(self.net, sample, context, False)
        key = (sample.dtype, len(context))
        fn = self._traced.get(key)
        if fn is None:
            with _TRACE_LOCK:
                fn = self._traced.get(key)
                if fn is None:
                    fn = self._traced[key] = self._trace(sample, context)
        return fn(sample, *context)

    def _trace(self, sample: Tensor, context: list[Tensor]) -> Callable:
        class _Modulated(nn.Module):
            def __init__(self, net: FiLMUnet1d):
                super().__init__()
                self.net = net

            def forward(self, x: Tensor, *ctx: Tensor) -> Tensor:
                return modulated_forward(self.net, x, list(ctx), True)

        try:
            with warnings.catch_warnings(), torch.no_grad():
                # jit's own warnings only: the filters are process-wide, and another thread's warnings in the
                # meantime (a fit beside the control loop) must still be seen
                warnings.filterwarnings("ignore", message=r".*torch\.jit\.trace", category=DeprecationWarning)
                warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
                return torch.jit.trace(_Modulated(self.net), (sample, *context), check_trace=False)
        except Exception as e:  # pragma: no cover - depends on the torch build
            warnings.warn(f"TorchScript tracing of the denoiser failed ({e!r}); using eager inference",
                          stacklevel=3)
            return lambda x, *ctx: modulated_forward(self.net, x, list(ctx), True)

    def __getstate__(self) -> dict:
        # traces and constants are rebuilt on demand; ScriptModules do not pickle
        return {**self.__dict__, "_traced": {}, "_frozen": None, "_param_dicts": None}
