"""The PDP model: training behaviors, trajectory VAE, FiLM denoiser, noise schedule, and the loss.

What :class:`~lerobot_pdp.modeling_pdp.PDPPolicy` (the LeRobot face) trains and samples. Data flows one way:
whole demonstrations -> behavior traces and their soft-DTW distances (``behavior.py``) -> encoder
mu_phi -> z -> FiLM-modulated denoiser (``denoiser.py``) -> action chunks.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from lerobot.utils.constants import ACTION
from torch import Tensor, nn

from .behavior import UNLABELED, BehaviorTraces, TrajectoryVAE, choose_kappa, trace_distances
from .configuration_pdp import PDPConfig
from .cuda_graphs import GraphCache, TrainGraphs
from .denoiser import FiLMUnet1d
from .diffusion import NoiseSchedule, diffusion_loss
from .distributed import agree_across_ranks, warn_if_cpu_launch_ran_one_process, world
from .fast_inference import FastDenoiser
from .observation_encoder import ObservationEncoder

logger = logging.getLogger(__name__)

# Buffers whose first dimension is the number of behaviors in the training set: their size is only known
# from the dataset (at training) or from the checkpoint file (at load).
BEHAVIOR_BUFFERS = ("behavior_traces", "behavior_episode", "behavior_start", "behavior_global_start",
                    "behavior_end", "behavior_mode", "trace_distance_matrix")


class PDPModel(nn.Module):
    """Networks, training behaviors and loss of a PDP; built from the config and the feature sizes.

    ``behaviors`` (read from the training dataset) must be given before the networks are built: the
    one-hot ablation takes its latent size from the number of modes.
    """

    def __init__(self, config: PDPConfig, action_dim: int, behaviors: BehaviorTraces | None = None):
        super().__init__()
        cfg = self.config = config
        self.action_dim = action_dim
        # Behaviors of the training set (traces, where they sit in which episode, mode labels, delta^X).
        self.register_buffer("behavior_traces", torch.zeros(0, cfg.trace_length, cfg.trace_dim))
        self.register_buffer("behavior_episode", torch.zeros(0, dtype=torch.long))
        self.register_buffer("behavior_start", torch.zeros(0, dtype=torch.long))
        self.register_buffer("behavior_global_start", torch.zeros(0, dtype=torch.long))
        self.register_buffer("behavior_end", torch.zeros(0, dtype=torch.long))
        self.register_buffer("behavior_mode", torch.zeros(0, dtype=torch.long))
        self.register_buffer("trace_distance_matrix", torch.zeros(0, 0))
        self.register_buffer("geo_kappa", torch.tensor(1.0 if cfg.geo_kappa is None else cfg.geo_kappa))
        # Running mean of L_DP over the last ~100 training steps: the denoising error of the training
        # demonstrations at their own latents, what a fitted demonstration's L_fit is compared with
        # (FitResult.error_ratio). NaN until trained (and in checkpoints saved before it existed).
        self.register_buffer("train_loss_dp", torch.tensor(float("nan")))
        if behaviors is not None:
            self.set_behaviors(behaviors)

        self.vae = TrajectoryVAE(cfg.trace_length, cfg.trace_dim, cfg.latent_dim, tuple(cfg.vae_hidden_dims))
        if len(self.behavior_traces):
            self.vae.set_trace_stats(self.behavior_traces)
        self.obs_encoder = ObservationEncoder(cfg)
        self.denoiser = FiLMUnet1d(
            action_dim, self.obs_encoder.frame_dim * cfg.n_obs_steps, cfg.latent_dim, cfg.latent_conditioning,
            tuple(cfg.down_dims), cfg.kernel_size, cfg.n_groups, cfg.diffusion_step_embed_dim,
            tuple(cfg.film_hidden_dims),
        )
        self._cuda_graphs = True
        self._train_graphs: TrainGraphs | None = TrainGraphs()  # None: capture failed once, train eagerly
        self.set_sampler(cfg.timestep_spacing, cfg.use_clipped_model_output)

    def set_sampler(self, timestep_spacing: str, use_clipped_model_output: bool) -> None:
        """(Re)build the noise schedule with this DDIM grid and step rule (a legacy checkpoint's, on load)."""
        cfg = self.config
        self.noise_schedule = NoiseSchedule(cfg.num_train_timesteps, cfg.beta_schedule, cfg.clip_sample,
                                            cfg.clip_sample_range, timestep_spacing, use_clipped_model_output)
        # captured (CUDA, see generate) and compiled (config.compile_model) samplers hold the step rule
        self.fast_denoiser = FastDenoiser(self.denoiser, cfg.num_train_timesteps)
        self._graphs = GraphCache()
        self._compiled_fns: dict[str, Callable] = {}

    # ------------------------------------------------------------------ training behaviors

    def set_behaviors(self, b: BehaviorTraces) -> None:
        """Take the training behaviors and compute their soft-DTW distance matrix delta^X (and kappa)."""
        cfg = self.config
        self.behavior_traces = torch.as_tensor(b.traces, dtype=torch.float32)
        self.behavior_episode = torch.as_tensor(b.episode_index, dtype=torch.long)
        self.behavior_start = torch.as_tensor(b.start, dtype=torch.long)
        self.behavior_global_start = torch.as_tensor(b.global_start, dtype=torch.long)
        self.behavior_end = torch.as_tensor(b.end, dtype=torch.long)
        self.behavior_mode = torch.as_tensor(b.mode, dtype=torch.long)
        if b.mode_names:
            cfg.mode_names = {str(k): v for k, v in sorted(b.mode_names.items())}
        if cfg.latent_type == "onehot":
            n_modes = int(b.mode.max()) + 1 if (b.mode >= 0).any() else 0
            if n_modes < 1 or (b.mode == UNLABELED).any():
                raise ValueError("latent_type='onehot' needs a mode label for every episode (meta/mode_labels.json, "
                                 "or task strings 'mode <id>: <name>')")
            if cfg.latent_dim != n_modes:
                logger.info("onehot latent: setting latent_dim = %d (number of modes)", n_modes)
                cfg.latent_dim = n_modes
            self.trace_distance_matrix = torch.zeros(len(b), len(b))
            self.check_ranks_agree("not needed (one-hot latents)")
            return
        report: dict[str, str] = {}
        d = trace_distances(b.traces, cfg.sdtw_gamma, cfg.sdtw_normalize, report=report)
        self.trace_distance_matrix = torch.as_tensor(d, dtype=torch.float32)
        kappa = cfg.geo_kappa if cfg.geo_kappa is not None else choose_kappa(d, cfg.latent_dim)
        self.geo_kappa = torch.tensor(float(kappa))
        self.check_ranks_agree(report.get("source", "computed"))

    def behavior_digest(self) -> str:
        """SHA-1 of the behavior bank (traces, where they sit, modes, delta^X, kappa): equal iff the banks are."""
        h = hashlib.sha1()
        for name in (*BEHAVIOR_BUFFERS, "geo_kappa"):
            t = getattr(self, name).detach().cpu().contiguous()
            h.update(f"{name}{tuple(t.shape)}{t.dtype}".encode())
            h.update(t.numpy().tobytes())
        return h.hexdigest()

    def check_ranks_agree(self, distance_source: str) -> None:
        """Under multi-process training, make sure every rank built the same behavior bank, and log (rank 0)
        which rank computed delta^X and which read it from the cache. A no-op in a single process."""
        rank, size = world()
        if size == 1:
            warn_if_cpu_launch_ran_one_process()
            return
        digest = self.behavior_digest()
        sources = agree_across_ranks("the behavior bank", digest, distance_source)
        if rank == 0:
            logger.info("behavior bank: %d behaviors, identical on all %d ranks (sha1 %s); soft-DTW distances: %s",
                        len(self.behavior_traces), size, digest[:12],
                        ", ".join(f"rank {r} {s}" for r, s in enumerate(sources)))

    def resize_behaviors(self, shapes: dict[str, tuple[int, ...]]) -> None:
        """Give the dataset-sized buffers the shapes a checkpoint holds, so that it loads into them."""
        for name, shape in shapes.items():
            setattr(self, name, torch.zeros(shape, dtype=getattr(self, name).dtype))

    def behavior_phase(self) -> Tensor:
        """Phase index of each training behavior within its episode (0 when episodes are not segmented)."""
        same = self.behavior_episode.view(-1, 1) == self.behavior_episode.view(1, -1)
        earlier = self.behavior_start.view(1, -1) < self.behavior_start.view(-1, 1)
        return (same & earlier).sum(1)

    def behavior_table(self) -> dict[str, np.ndarray]:
        """Latent of every training behavior with its episode, frame range and mode (for maps/plots)."""
        with torch.no_grad():
            z = self.behavior_latents().cpu().numpy()
        return {"z": z, "episode": self.behavior_episode.cpu().numpy(), "start": self.behavior_start.cpu().numpy(),
                "end": self.behavior_end.cpu().numpy(), "mode": self.behavior_mode.cpu().numpy()}

    # ------------------------------------------------------------------ training loss

    def loss_terms(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]]:
        """L_DP(theta; sg(mu_phi(tau))) + L_embed(phi, psi) on a training batch, and its logged terms as 0-d
        tensors, without a single host synchronisation (see ``PDPPolicy.forward``).

        On CUDA in training the forward and backward are replayed from captured graphs
        (``config.train_cuda_graphs``); the returned tensors are then the graphs' outputs, valid until the
        next training step."""
        self.check_batch(batch)
        if self._graph_training(batch):
            inputs = self._loss_inputs(batch)
            self.behavior_ids(inputs["episode_index"], None)  # the unknown-episode check, outside the graph
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
                and world()[1] == 1 and not (cfg.image_features and cfg.crop_shape and cfg.crop_is_random))

    def _loss_inputs(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """The tensors ``_loss_terms`` reads (a LeRobot batch also holds strings, timestamps, ...)."""
        keys = [*self.config.condition_features, ACTION, "episode_index", "index", "action_is_pad"]
        return {k: batch[k] for k in keys if k in batch}

    def _graphed_loss_terms(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]]:
        return self._loss_terms(batch, check_episodes=False)

    def _loss_terms(self, batch: dict[str, Tensor], check_episodes: bool = True) -> tuple[Tensor, dict[str, Tensor]]:
        """``loss_terms`` run eagerly (and what the training graphs capture)."""
        z_bar, behavior = self.batch_latents(batch, check_episodes)
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
                self.train_loss_dp.copy_(torch.where(seen.isnan(), loss_dp, torch.lerp(seen, loss_dp, 0.01)))
        metrics: dict[str, Tensor] = {"loss_dp": loss_dp}
        loss = loss_dp
        if self.config.latent_type == "continuous" and self.training:
            loss_embed, embed_info = self.embedding_loss(actions.device)
            loss = loss + loss_embed
            metrics.update(embed_info, loss_embed=loss_embed)
        return loss, metrics

    def embedding_loss(self, device) -> tuple[Tensor, dict]:
        n = len(self.behavior_traces)
        if torch.device(device).type == "cuda":  # randperm of a small n is drawn on the host: not graph-safe
            idx = torch.rand(n, device=device).argsort()[: self.config.embed_batch_size]
        else:
            idx = torch.randperm(n, device=device)[: self.config.embed_batch_size]
        return self.vae.loss(
            self.behavior_traces[idx], self.trace_distance_matrix[idx][:, idx], self.geo_kappa,
            self.config.beta_kl, self.config.beta_geo,
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

    def behavior_ids(self, episode_index: Tensor, global_index: Tensor | None, check: bool = True) -> Tensor:
        """Behavior (episode, or gripper phase of an episode) of each training sample; ``check``: refuse an
        episode that is not among the training behaviors."""
        if len(self.behavior_episode) == 0:
            raise RuntimeError(
                "PDP has no behavior traces: build it with dataset_meta (lerobot-train does) or load a checkpoint"
            )
        ep = episode_index.view(-1, 1).to(self.behavior_episode.device)
        match = ep == self.behavior_episode.view(1, -1)
        known = match.any(1).all()
        if check and known.device.type == "cpu":
            if not bool(known):
                missing = episode_index.view(-1)[~match.any(1).cpu()].unique().tolist()
                raise KeyError(f"episode(s) {missing} are not among the policy's training episodes "
                               f"({self.behavior_episode.unique().numel()} episodes, "
                               f"{len(self.behavior_episode)} behaviors)")
        elif check:  # checked on the device: reading the flag back would stall the GPU every training step
            torch._assert_async(known, "a training batch holds episodes that are not among the policy's "
                                       "training episodes (run one step on CPU to see which)")
        if global_index is not None:
            # behaviors of one episode partition its frames in order: take the last one that starts <= frame
            f = global_index.view(-1, 1).to(self.behavior_start.device)
            later = match & (self.behavior_global_start.view(1, -1) <= f)
            match = torch.where(later.any(1, keepdim=True), later, match)
        ids = torch.arange(match.shape[1], device=match.device).view(1, -1).expand_as(match)
        return torch.where(match, ids, torch.full_like(ids, -1)).max(1).values

    def behavior_latents(self, ids: Tensor | None = None) -> Tensor:
        """z_bar = mu_phi(X(tau)) of training behaviors (all, or ``ids``); one-hot mode codes for that ablation."""
        if self.config.latent_type == "onehot":
            modes = self.behavior_mode if ids is None else self.behavior_mode[ids]
            return F.one_hot(modes, self.config.latent_dim).float()
        traces = self.behavior_traces if ids is None else self.behavior_traces[ids]
        return self.vae.encode(traces)[0]

    def batch_latents(self, batch: dict[str, Tensor], check_episodes: bool = True) -> tuple[Tensor, Tensor]:
        ids = self.behavior_ids(batch["episode_index"], batch.get("index"), check_episodes)
        with torch.no_grad():  # stop-gradient: L_DP must not shape the latent geometry
            if ids.device.type != "cpu":  # unique() has a data-dependent size: the host would wait for it
                return self.behavior_latents(ids).to(batch[ACTION].device), ids
            uniq, inverse = ids.unique(return_inverse=True)
            z = self.behavior_latents(uniq)
        return z[inverse].to(batch[ACTION].device), ids

    def obs_cond(self, batch: dict[str, Tensor]) -> Tensor:
        """The denoiser's observation condition [B, n_obs_steps * frame_dim] of observation histories."""
        return self.obs_encoder(batch).flatten(1)

    # ------------------------------------------------------------------ sampling

    @torch.no_grad()
    def generate(self, obs_cond: Tensor, z: Tensor, noise: Tensor | None = None,
                 generator: torch.Generator | None = None) -> Tensor:
        """Denoise action chunks [B, horizon, A] (normalised) for conditions ``obs_cond`` [B, C], ``z`` [B, d_z]."""
        b = obs_cond.shape[0]
        if noise is None:
            noise = torch.randn(b, self.config.horizon, self.action_dim, device=obs_cond.device,
                                generator=generator)
        n = self.config.num_inference_steps
        if obs_cond.device.type == "cuda" and self._cuda_graphs:
            try:
                return self._generate_graphed(obs_cond, z.to(obs_cond), noise.to(obs_cond), n)
            except RuntimeError as e:  # pragma: no cover - depends on the driver and torch build
                logger.warning("CUDA graph capture of the sampler failed (%r); acting eagerly", e)
                self._cuda_graphs = False
                self._graphs.clear()
        return self._sample(obs_cond, z, noise, n)

    def _sample(self, obs_cond: Tensor, z: Tensor, noise: Tensor, n: int) -> Tensor:
        steps = self.noise_schedule.timesteps(n)
        fast = self.fast_denoiser
        if self.config.compile_model:
            mod = fast.sample_modulation(obs_cond, z, steps)
            return self.compiled("sample")(noise, mod, n)
        context = fast.contexts(obs_cond, z, steps)
        return self.noise_schedule.sample(lambda x, i, k: fast.run(x, context[i]), noise, n)

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

    def _generate_graphed(self, obs_cond: Tensor, z: Tensor, noise: Tensor, n: int) -> Tensor:
        """:meth:`_sample` replayed from a CUDA graph, captured per input shape and sampler steps.

        Recaptured when the weights change (the graph reads the weight constants of the capture, and
        ``FastDenoiser.frozen`` returns a new object after an optimizer step, ``load_state_dict`` or ``.to``).
        """
        consts = self.fast_denoiser.frozen()
        key = (tuple(obs_cond.shape), tuple(z.shape), tuple(noise.shape), n, obs_cond.dtype, obs_cond.device,
               torch.is_inference_mode_enabled())
        call = self._graphs.get(key, consts, lambda o, zz, x: self._sample(o, zz, x, n),
                                (obs_cond, z, noise))
        return call(obs_cond, z, noise)
