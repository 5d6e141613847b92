"""The PDP model: training behaviors, trajectory VAE, FiLM denoiser, noise schedule, and the loss.

What :class:`~lerobot_pdp.modeling_pdp.PDPPolicy` (the LeRobot face) trains and samples. Data flows one way:
whole demonstrations -> behavior traces and their soft-DTW distances (``behavior.py``, kept in the behavior
bank, ``behavior_bank.py``) -> encoder mu_phi -> z -> FiLM-modulated denoiser (``denoiser.py``) -> action chunks.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

import torch
from lerobot.utils.constants import ACTION
from torch import Tensor, nn

from .behavior import BehaviorTraces, TrajectoryVAE
from .behavior_bank import BehaviorBank
from .configuration_pdp import PDPConfig, linear_beta_end
from .console import latent_text
from .cuda_graphs import GraphCache, TrainGraphs
from .denoiser import FiLMUnet1d
from .diffusion import NoiseSchedule, PrefixGuide, diffusion_loss
from .distributed import world
from .fast_inference import FastDenoiser
from .observation_encoder import ObservationEncoder
from .steering_state import as_latent_tensor

logger = logging.getLogger(__name__)

# Weight of each training step's L_DP in train_loss_dp's running mean (~20 steps). A slower mean lags a falling
# loss: at 0.01 (~100 steps) it read about twice the true error of a few-hundred-step training, so a fit's
# error ratio flattered it; at the end of a long (cosine-decayed) training the two agree.
TRAIN_LOSS_RATE = 0.05


def read_loss_terms(metrics: dict[str, Tensor], train_step: int | None = None) -> dict[str, float]:
    """The logged loss terms as floats, in one host transfer (each ``.item()`` would wait for the GPU on its
    own); ``train_step`` (in training): refuse non-finite terms, before the optimizer writes non-finite weights
    into the next checkpoint."""
    values = dict(zip(metrics, torch.stack([v.detach().float() for v in metrics.values()]).tolist(), strict=True))
    bad = {k: v for k, v in values.items() if not math.isfinite(v)}
    if train_step is not None and bad:
        raise FloatingPointError(
            f"PDP training step {train_step} of this process: non-finite loss term(s) {bad} (all terms: "
            f"{values}); the weights were not updated by it. Check the "
            "dataset for non-finite values and the soft-DTW cache (LEROBOT_PDP_CACHE), or lower the lr")
    return values


def check_finite_actions(chunk: Tensor, z: Tensor) -> None:
    """One check per action chunk: a robot must never be sent NaN. The observations were finite
    (:func:`check_finite_condition` ran first), so the weights or the latent made it."""
    if not bool(torch.isfinite(chunk).all()):
        raise FloatingPointError(
            f"PDP generated non-finite actions from finite observations (latent {z[0].tolist()}): check the "
            "checkpoint's weights and the latent it is steered to; no action is returned")


def check_finite_condition(batch: dict[str, Tensor], obs_cond: Tensor) -> None:
    """Before a chunk is sampled: an observation holding NaN or inf (a sensor glitch, an integer state the
    normaliser turned into NaN) is named, rather than sampled from and caught as non-finite actions."""
    if not bool(torch.isfinite(obs_cond).all()):
        bad = [k for k, v in batch.items() if isinstance(v, Tensor) and v.is_floating_point()
               and not bool(torch.isfinite(v).all())]
        raise FloatingPointError(
            f"observation {', '.join(map(repr, bad)) or '(its camera features)'} holds non-finite values (NaN or inf) "
            "after the preprocessor: no action is generated. Check the robot's readings (and their dtype: LeRobot's "
            "normaliser takes floats) and the checkpoint's processor statistics")


class PDPModel(nn.Module):
    """Networks, training behaviors and loss of a PDP; built from the config and the feature sizes.

    ``behaviors``: the training dataset's (at training; a loaded checkpoint fills the bank instead). The config
    is only read here: the fields the dataset decides are set before (``behavior_bank.resolve_dataset_config``).
    """

    def __init__(self, config: PDPConfig, action_dim: int, behaviors: BehaviorTraces | None = None):
        super().__init__()
        cfg = self.config = config
        self.action_dim = action_dim
        # The training behaviors (traces, where they sit, modes, delta^X, kappa): see behavior_bank.py.
        self.bank = BehaviorBank(cfg)
        # Running mean of L_DP over the last ~20 training steps (TRAIN_LOSS_RATE): the denoising error of the
        # training demonstrations at their own latents, what a fitted demonstration's L_fit is compared with
        # (FitResult.error_ratio). NaN until trained (and in checkpoints saved before it existed).
        self.register_buffer("train_loss_dp", torch.tensor(float("nan")))
        if behaviors is not None:
            self.bank.set(behaviors)
        # lerobot-train on a taught checkpoint: the taught demonstrations' windows appended to each training batch
        # (taught_rehearsal.TaughtRehearsal; set when such a checkpoint is loaded to train on)
        self.rehearsal = None

        self.vae = TrajectoryVAE(cfg.trace_length, cfg.trace_dim, cfg.latent_dim, tuple(cfg.vae_hidden_dims))
        if len(self.bank.traces):
            self.vae.set_trace_stats(self.bank.traces)
        self.obs_encoder = ObservationEncoder(cfg)
        self.denoiser = FiLMUnet1d(
            action_dim, self.obs_encoder.frame_dim * cfg.n_obs_steps, cfg.latent_dim, cfg.latent_conditioning,
            tuple(cfg.down_dims), cfg.kernel_size, cfg.n_groups, cfg.diffusion_step_embed_dim,
            tuple(cfg.film_hidden_dims),
        )
        self._cuda_graphs = True
        self._train_graphs: TrainGraphs | None = TrainGraphs()  # None: capture failed once, train eagerly
        self.set_sampler(cfg.timestep_spacing, cfg.use_clipped_model_output)

    @property
    def device(self) -> torch.device:
        """Where the model's weights and buffers are."""
        return self.bank.kappa.device

    def set_sampler(self, timestep_spacing: str, use_clipped_model_output: bool) -> None:
        """(Re)build the noise schedule with this DDIM grid and step rule (a legacy checkpoint's, on load)."""
        cfg = self.config
        self.noise_schedule = NoiseSchedule(cfg.num_train_timesteps, cfg.beta_schedule, cfg.clip_sample,
                                            cfg.clip_sample_range, timestep_spacing, use_clipped_model_output,
                                            cfg.beta_start, linear_beta_end(cfg.beta_end, cfg.num_train_timesteps))
        # captured (CUDA, see generate) and compiled (config.compile_model) samplers hold the step rule
        self.fast_denoiser = FastDenoiser(self.denoiser, cfg.num_train_timesteps)
        self._graphs = GraphCache()
        self._compiled_fns: dict[str, Callable] = {}

    # ------------------------------------------------------------------ training loss

    def optim_groups(self) -> list[dict]:
        """Two parameter groups: embedding (phi, psi) and denoiser (theta, with its camera encoders), each
        with its learning rate (``PDPPolicy.get_optim_params``)."""
        theta = [*self.denoiser.parameters(), *self.obs_encoder.parameters()]
        return [
            {"params": [p for p in self.vae.parameters() if p.requires_grad], "lr": self.config.embedding_lr},
            {"params": [p for p in theta if p.requires_grad], "lr": self.config.optimizer_lr},
        ]

    def loss_terms(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]]:
        """L_DP(theta; sg(mu_phi(tau))) + L_embed(phi, psi) on a training batch, and its logged terms as 0-d
        tensors, without a single host synchronisation (``PDPPolicy.forward`` reads them once).

        Why one summed loss reproduces the paper's alternating Algorithm 1: the two terms share no
        parameters' gradients. L_embed depends only on (phi, psi); L_DP depends only on theta because the
        latent enters it through a stop-gradient z_bar = sg(mu_phi(tau)). So the gradient of the sum is
        (grad_{phi,psi} L_embed, grad_theta L_DP), exactly Step 1 and Step 2 of Algorithm 1; LeRobot's
        optimizer applies them in one step with each group's own learning rate (:meth:`optim_groups`). The
        only difference is that Step 2 sees phi before rather than after this step's Step-1 update.

        On CUDA in training the forward and backward are replayed from captured graphs
        (``config.train_cuda_graphs``); the returned tensors are then the graphs' outputs, valid until the
        next training step."""
        self.check_batch(batch)
        if self._graph_training(batch):
            inputs = self._loss_inputs(batch)
            self.bank.ids(inputs["episode_index"], None)  # the unknown-episode check, outside the graph
            try:
                return self._train_graphs(self, self._graphed_loss_terms, inputs)
            except RuntimeError as e:  # pragma: no cover - depends on the driver and torch build
                logger.warning("CUDA graph capture of the training step failed (%r); training eagerly", e)
                self._train_graphs = None
        return self._loss_terms(batch)

    def _graph_training(self, batch: dict[str, Tensor]) -> bool:
        """Whether this training step may run from captured CUDA graphs (see ``config.train_cuda_graphs``)."""
        cfg = self.config
        actions = batch[ACTION]
        return (cfg.train_cuda_graphs and self._train_graphs is not None and actions.is_cuda and self.training
                and torch.is_grad_enabled() and not cfg.compile_model and not torch.is_autocast_enabled("cuda")
                and world()[1] == 1 and not (cfg.image_features and cfg.crop_shape and cfg.crop_is_random)
                and self.rehearsal is None)

    def _loss_inputs(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """The tensors ``_loss_terms`` reads (a LeRobot batch also holds strings, timestamps, ...)."""
        keys = [*self.config.condition_features, ACTION, "episode_index", "index", "action_is_pad"]
        return {k: batch[k] for k in keys if k in batch}

    def _graphed_loss_terms(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]]:
        return self._loss_terms(batch, check_episodes=False)

    def _loss_terms(self, batch: dict[str, Tensor], check_episodes: bool = True) -> tuple[Tensor, dict[str, Tensor]]:
        """``loss_terms`` run eagerly (and what the training graphs capture)."""
        z_bar, _ = self.batch_latents(batch, check_episodes)
        n_data = len(z_bar)
        if self.rehearsal is not None and self.training:  # the taught modes, which the dataset does not hold
            batch, rows = self.rehearsal.extend(batch)
            with torch.no_grad():
                z_bar = torch.cat([z_bar, self.behavior_latents(rows).to(z_bar)])
        obs_cond = self.obs_cond(batch)
        actions = batch[ACTION]
        eps = torch.randn_like(actions)
        k = torch.randint(0, self.config.num_train_timesteps, (actions.shape[0],), device=actions.device)
        noisy = self.noise_schedule.add_noise(actions, eps, k)
        denoiser = self.compiled("train") if self.config.compile_model else self.denoiser
        pred = denoiser(noisy, k, obs_cond, z_bar)
        is_pad = batch.get("action_is_pad") if self.config.do_mask_loss_for_padding else None
        loss_dp = diffusion_loss(pred, eps, is_pad)
        if self.training:
            with torch.no_grad():  # on the device, no host sync
                seen = self.train_loss_dp
                self.train_loss_dp.copy_(torch.where(seen.isnan(), loss_dp, torch.lerp(seen, loss_dp, TRAIN_LOSS_RATE)))
        metrics: dict[str, Tensor] = {"loss_dp": loss_dp}
        if len(actions) > n_data:  # what the taught windows alone weigh, for the log
            metrics["loss_dp_taught"] = diffusion_loss(pred[n_data:], eps[n_data:],
                                                       None if is_pad is None else is_pad[n_data:]).detach()
        loss = loss_dp
        if self.config.latent_type == "continuous" and self.training:
            loss_embed, embed_info = self.embedding_loss(actions.device)
            loss = loss + loss_embed
            metrics.update(embed_info, loss_embed=loss_embed)
        return loss, metrics

    def embedding_loss(self, device) -> tuple[Tensor, dict]:
        bank = self.bank
        pool = bank.embed_pool  # the behaviours it trains on (empty: all; an eval split's are left out)
        n = len(pool) if len(pool) else len(bank.traces)
        if torch.device(device).type == "cuda":  # randperm of a small n is drawn on the host: not graph-safe
            idx = torch.rand(n, device=device).argsort()[: self.config.embed_batch_size]
        else:
            idx = torch.randperm(n, device=device)[: self.config.embed_batch_size]
        if len(pool):
            idx = pool.to(idx.device)[idx]
        return self.vae.loss(
            bank.traces[idx], bank.distances[idx][:, idx], bank.kappa,
            self.config.beta_kl, self.config.beta_geo, self.config.embed_rec_reduction,
        )

    def check_batch(self, batch: dict[str, Tensor]) -> None:
        cfg = self.config
        expect = {k: (cfg.n_obs_steps, *ft.shape) for k, ft in cfg.condition_features.items()}
        expect[ACTION] = (cfg.horizon, self.action_dim)
        for key, shape in expect.items():
            if key not in batch:
                raise KeyError(f"batch has no '{key}'; PDP needs {sorted(expect)} (got {sorted(batch)})")
            if tuple(batch[key].shape[1:]) != shape:
                raise ValueError(f"batch['{key}'] has shape {tuple(batch[key].shape)}, expected "
                                 f"[B, {', '.join(map(str, shape))}]")
        if "episode_index" not in batch:
            raise KeyError("batch has no 'episode_index': PDP conditions each window on its episode's latent")

    @torch.no_grad()
    def checked_latent(self, z: Any) -> Any:
        """``z`` as ``set_latent`` takes it, refused (before it acts) when the denoiser overflows under it (e.g.
        [1e30, 1e30]: its FiLM scales blow the activations past float32): every action would be non-finite, and a
        robot loop would stop at its first chunk. One denoiser pass on a neutral input (zero chunk and observation
        condition) at the first and the last diffusion step, a few ms on a CPU: the latent's FiLM terms set the
        scale, not the observation."""
        if z is None or self.config.latent_conditioning == "none":
            return z
        t = as_latent_tensor(z)
        t = t[None] if t.dim() == 1 else t
        if t.dim() != 2 or t.shape[-1] != self.config.latent_dim or not bool(torch.isfinite(t).all()):
            return z  # the steering state names a wrong shape or a non-finite value
        m, dev = 2 * len(t), self.device
        k = torch.tensor([0, self.config.num_train_timesteps - 1], device=dev).repeat_interleave(len(t))
        eps = self.denoiser(torch.zeros(m, self.config.horizon, self.action_dim, device=dev), k,
                            torch.zeros(m, self.denoiser.obs_cond_dim, device=dev), t.to(dev).repeat(2, 1))
        if not bool(torch.isfinite(eps).all()):
            raise ValueError(f"latent {latent_text(t)} makes the denoiser overflow (non-finite output): every action "
                             "under it would be non-finite. Steer within the training latents (mode_latents(), "
                             "latent-map)")
        return z

    def behavior_latents(self, ids: Tensor | None = None) -> Tensor:
        """z_bar = mu_phi(X(tau)) of training behaviors (all, or ``ids``); one-hot mode codes for that ablation."""
        return self.bank.latents(self.vae, ids)

    def batch_latents(self, batch: dict[str, Tensor], check_episodes: bool = True) -> tuple[Tensor, Tensor]:
        ids = self.bank.ids(batch["episode_index"], batch.get("index"), check_episodes)
        with torch.no_grad():  # stop-gradient: L_DP must not shape the latent geometry
            if ids.device.type != "cpu":  # unique() has a data-dependent size: the host would wait for it
                return self.behavior_latents(ids).to(batch[ACTION].device), ids
            uniq, inverse = ids.unique(return_inverse=True)
            z = self.behavior_latents(uniq)
        return z[inverse].to(batch[ACTION].device), ids

    def obs_cond(self, batch: dict[str, Tensor]) -> Tensor:
        """The denoiser's observation condition [B, n_obs_steps * frame_dim] of observation histories."""
        return self.obs_encoder(batch).flatten(1)

    def acting_cond(self, batch: dict[str, Tensor]) -> Tensor:
        """:meth:`obs_cond` to act on: one holding a non-finite value is refused, naming the observation."""
        cond = self.obs_cond(batch)
        check_finite_condition(batch, cond)
        return cond

    # ------------------------------------------------------------------ sampling

    @torch.no_grad()
    def generate(self, obs_cond: Tensor, z: Tensor, noise: Tensor | None = None,
                 generator: torch.Generator | None = None, guide: Callable[[Tensor], Tensor] | None = None) -> Tensor:
        """Denoise action chunks [B, horizon, A] (normalised) for conditions ``obs_cond`` [B, C], ``z`` [B, d_z];
        ``guide`` edits each step's predicted clean chunk (:meth:`NoiseSchedule.sample`); on CUDA a
        :class:`PrefixGuide` is replayed from the sampler's graph, any other edit runs eagerly."""
        b = obs_cond.shape[0]
        if noise is None:
            noise = torch.randn(b, self.config.horizon, self.action_dim, device=obs_cond.device,
                                generator=generator)
        n = self.config.num_inference_steps
        z, noise = z.to(obs_cond), noise.to(obs_cond)  # a caller's CPU latent or noise for a policy on a GPU
        graphable = guide is None or isinstance(guide, PrefixGuide)  # another x0 edit: eager kernels
        if obs_cond.device.type == "cuda" and self._cuda_graphs and graphable:
            try:
                return self._generate_graphed(obs_cond, z, noise, n, guide)
            except RuntimeError as e:  # pragma: no cover - depends on the driver and torch build
                logger.warning("CUDA graph capture of the sampler failed (%r); acting eagerly", e)
                self._cuda_graphs = False
                self._graphs.clear()
        return self._sample(obs_cond, z, noise, n, guide)

    def _sample(self, obs_cond: Tensor, z: Tensor, noise: Tensor, n: int,
                guide: Callable[[Tensor], Tensor] | None = None) -> Tensor:
        steps = self.noise_schedule.timesteps(n)
        fast = self.fast_denoiser
        if self.config.compile_model and guide is None:
            mod = fast.sample_modulation(obs_cond, z, steps)
            return self.compiled("sample")(noise, mod, n)
        context = fast.contexts(obs_cond, z, steps)
        return self.noise_schedule.sample(lambda x, i, k: fast.run(x, context[i]), noise, n, guide)

    def _denoise(self, noise: Tensor, mod: Tensor, n: int) -> Tensor:
        """The whole sampler given its steps' modulation rows (``sample_modulation``); what ``compiled("sample")``
        compiles: one graph for all steps (a step's rows as input would be a view at another storage offset
        per step, which the compiled code is specialised on)."""
        fast = self.fast_denoiser
        return self.noise_schedule.sample(lambda x, i, k: fast.forward(x, mod[i]), noise, n)

    def compiled(self, name: str) -> Callable:
        """The torch.compile'd denoiser, built on first use: ``"train"`` (its forward, in ``compile_mode``)
        or ``"sample"`` (``_denoise``, the whole sampler). The sampler's compile has no CUDA graphs of its own:
        on CUDA it is captured into PDP's graph (``_generate_graphed``) around it."""
        fn = self._compiled_fns.get(name)
        if fn is None:
            mode = self.config.compile_mode
            if name == "train":
                fn = torch.compile(self.denoiser, mode=mode, fullgraph=True, dynamic=False)
            elif name == "sample":
                mode = "max-autotune-no-cudagraphs" if mode.startswith("max-autotune") else "default"
                fn = torch.compile(self._denoise, mode=mode, fullgraph=True, dynamic=False)
            else:
                raise ValueError(f"no compiled denoiser {name!r}; 'train' or 'sample'")
            self._compiled_fns[name] = fn
        return fn

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_compiled_fns"] = {}  # compiled code is rebuilt on demand and does not pickle
        return state

    def _generate_graphed(self, obs_cond: Tensor, z: Tensor, noise: Tensor, n: int,
                          guide: PrefixGuide | None = None) -> Tensor:
        """:meth:`_sample` replayed from a CUDA graph, captured per input shape, sampler steps and whether a
        prefix guides it (its target and weights are inputs: one graph serves every prefix).

        Recaptured when the weights change (the graph reads the weight constants of the capture, and
        ``FastDenoiser.frozen`` returns a new object after an optimizer step, ``load_state_dict`` or ``.to``).
        """
        consts = self.fast_denoiser.frozen()
        inputs = (obs_cond, z, noise) if guide is None else (obs_cond, z, noise, guide.target, guide.weight)
        key = (tuple(tuple(x.shape) for x in inputs), n, obs_cond.dtype, obs_cond.device,
               torch.is_inference_mode_enabled())

        def sample(o: Tensor, zz: Tensor, x: Tensor, *prefix: Tensor) -> Tensor:
            return self._sample(o, zz, x, n, PrefixGuide(*prefix) if prefix else None)

        return self._graphs.get(key, consts, sample, inputs)(*inputs)
