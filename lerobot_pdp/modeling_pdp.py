"""Parameterized Diffusion Policy (PDP): a diffusion policy steered by a geometry-aligned behavior latent z.

The public face is :class:`PDPPolicy`, a LeRobot ``PreTrainedPolicy``:

- training runs inside ``lerobot-train`` (``forward`` returns L_DP + L_embed, see its docstring);
- ``select_action`` / ``predict_action_chunk`` act conditioned on the *active latent*;
- steering: ``encode(episode)``, ``set_latent(z)``, ``mode_latents()``, ``interpolate(z_a, z_b, n)`` and
  ``fit_latent(episode)`` (paper Alg. 3: encoder warm start, then gradient steps on z, weights frozen).

Data flows one way: dataset -> behavior traces -> trajectory encoder -> z -> FiLM denoiser -> actions.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections import deque
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from huggingface_hub.constants import SAFETENSORS_SINGLE_FILE
from huggingface_hub.serialization import save_torch_state_dict
from lerobot.configs import FeatureType
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.policies.utils import populate_queues
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE
from safetensors.torch import save_model as save_model_as_safetensor
from torch import Tensor, nn

from .atomic import staging_dir
from .behavior import (
    UNLABELED,
    BehaviorTraces,
    TrajectoryVAE,
    build_behavior_traces,
    check_finite,
    choose_kappa,
    gripper_segments,
    make_trace,
    read_episodes,
    trace_distances,
)
from .configuration_pdp import PDPConfig
from .cuda_graphs import GraphCache
from .denoiser import FiLMUnet1d, NoiseSchedule, diffusion_loss
from .latent_fitting import DemoWindows, FitResult, episode_windows, fit_latent

logger = logging.getLogger(__name__)

# Buffers whose first dimension is the number of behaviors in the training set: their size is only known
# from the dataset (at training) or from the checkpoint file (at load), see _load_as_safetensor.
_BEHAVIOR_BUFFERS = ("behavior_traces", "behavior_episode", "behavior_start", "behavior_global_start",
                     "behavior_end", "behavior_mode",
                     "trace_distance_matrix")

Episode = dict[str, Any] | tuple[Any, int]


class PDPPolicy(PreTrainedPolicy):
    """Parameterized Diffusion Policy (Parameterized Diffusion Policies, Method + Appendix A)."""

    config_class = PDPConfig
    name = "pdp"

    def __init__(self, config: PDPConfig, dataset_stats: dict[str, dict[str, Tensor]] | None = None,
                 dataset_meta: Any | None = None, **kwargs):
        """Build the networks; with ``dataset_meta`` (as ``lerobot-train`` passes it) also read every whole
        episode of the local dataset into behavior traces and compute their soft-DTW distance matrix."""
        super().__init__(config)
        config.validate_features()
        self.config = config

        cfg = config
        self.state_dim = cfg.robot_state_feature.shape[0]
        self.env_dim = cfg.env_state_feature.shape[0] if cfg.env_state_feature else 0
        self.action_dim = cfg.action_feature.shape[0]

        self.stats = _FeatureStats(cfg)
        if dataset_stats is not None:
            self.stats.load(dataset_stats)

        # Behaviors of the training set (traces, where they sit in which episode, mode labels, delta^X).
        self.register_buffer("behavior_traces", torch.zeros(0, cfg.trace_length, cfg.trace_dim))
        self.register_buffer("behavior_episode", torch.zeros(0, dtype=torch.long))
        self.register_buffer("behavior_start", torch.zeros(0, dtype=torch.long))
        self.register_buffer("behavior_global_start", torch.zeros(0, dtype=torch.long))
        self.register_buffer("behavior_end", torch.zeros(0, dtype=torch.long))
        self.register_buffer("behavior_mode", torch.zeros(0, dtype=torch.long))
        self.register_buffer("trace_distance_matrix", torch.zeros(0, 0))
        self.register_buffer("geo_kappa", torch.tensor(1.0 if cfg.geo_kappa is None else cfg.geo_kappa))

        if dataset_meta is not None and getattr(dataset_meta, "root", None) is not None:
            self._load_behaviors(dataset_meta)

        self.vae = TrajectoryVAE(cfg.trace_length, cfg.trace_dim, cfg.latent_dim, tuple(cfg.vae_hidden_dims))
        if len(self.behavior_traces):
            self.vae.set_trace_stats(self.behavior_traces)

        obs_cond_dim = (self.state_dim + self.env_dim) * cfg.n_obs_steps
        self.denoiser = FiLMUnet1d(
            self.action_dim, obs_cond_dim, cfg.latent_dim, cfg.latent_conditioning, tuple(cfg.down_dims),
            cfg.kernel_size, cfg.n_groups, cfg.diffusion_step_embed_dim, tuple(cfg.film_hidden_dims),
        )
        self.noise_schedule = NoiseSchedule(cfg.num_train_timesteps, cfg.beta_schedule, cfg.clip_sample,
                                            cfg.clip_sample_range)

        # The active latent(s): [M, d_z]; M > 1 = one per phase, advanced on gripper events.
        self.register_buffer("active_latent", torch.zeros(0, cfg.latent_dim), persistent=False)
        self._phase: Tensor | None = None  # [B] current phase of each env in a batched rollout
        self._last_gripper_closed: Tensor | None = None  # [B] gripper state of each env's current phase
        self._gripper_hold: Tensor | None = None  # [B] consecutive actions that disagree with it
        self._steering_initialised = False
        self._queues: dict[str, deque] = {}
        self._graphs = GraphCache()  # captured samplers on CUDA (see generate)
        self._cuda_graphs = True
        self.reset()

    # ------------------------------------------------------------------ training data (whole episodes)

    def _load_behaviors(self, dataset_meta: Any) -> None:
        cfg = self.config
        keys = [k for k in (OBS_STATE, OBS_ENV_STATE, ACTION, cfg.trace_key) if k in dataset_meta.features]
        episodes = read_episodes(dataset_meta.root, keys)
        min_len = cfg.n_obs_steps
        for ep, item in episodes.items():
            for k in keys:
                check_finite(k, item[k], f"episode {ep}")
        traces = build_behavior_traces(
            episodes, cfg.trace_key, cfg.trace_dims, cfg.trace_length, cfg.trace_normalize,
            cfg.segment_gripper_dim, cfg.segment_gripper_threshold, min_length=min_len,
        )
        self._set_behaviors(traces)

    def _set_behaviors(self, b: BehaviorTraces) -> None:
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
                raise ValueError("latent_type='onehot' needs a mode label ('mode <id>: ...') in every episode's task")
            if cfg.latent_dim != n_modes:
                logger.info("onehot latent: setting latent_dim = %d (number of modes)", n_modes)
                cfg.latent_dim = n_modes
            self.trace_distance_matrix = torch.zeros(len(b), len(b))
            return
        d = trace_distances(b.traces, cfg.sdtw_gamma, cfg.sdtw_normalize)
        self.trace_distance_matrix = torch.as_tensor(d, dtype=torch.float32)
        kappa = cfg.geo_kappa if cfg.geo_kappa is not None else choose_kappa(d, cfg.latent_dim)
        self.geo_kappa = torch.tensor(float(kappa))

    @classmethod
    def _load_as_safetensor(cls, model: PDPPolicy, model_file: str, map_location: str, strict: bool):
        """Resize the dataset-sized buffers to the checkpoint's shapes before loading them."""
        from safetensors import safe_open

        with safe_open(model_file, framework="pt") as f:
            keys = set(f.keys())
            for name in _BEHAVIOR_BUFFERS:
                if name in keys:
                    t = f.get_slice(name)
                    shape = t.get_shape()
                    setattr(model, name, torch.zeros(shape, dtype=getattr(model, name).dtype))
        model = super()._load_as_safetensor(model, model_file, map_location, strict)
        return model

    # ------------------------------------------------------------------ LeRobot contract

    def get_optim_params(self) -> list[dict]:
        """Two parameter groups: embedding (phi, psi) and denoiser (theta), each with its learning rate."""
        return [
            {"params": [p for p in self.vae.parameters() if p.requires_grad], "lr": self.config.embedding_lr},
            {"params": [p for p in self.denoiser.parameters() if p.requires_grad], "lr": self.config.optimizer_lr},
        ]

    def reset(self) -> None:
        """Clear the observation/action queues and restart the latent-phase sequence (call on env.reset())."""
        self._queues = {OBS_STATE: deque(maxlen=self.config.n_obs_steps),
                        ACTION: deque(maxlen=self.config.n_action_steps)}
        if self.config.env_state_feature:
            self._queues[OBS_ENV_STATE] = deque(maxlen=self.config.n_obs_steps)
        self._phase = None
        self._last_gripper_closed = None
        self._episode_latent: Tensor | None = None

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """One joint training step: ``L = L_DP(theta; sg(mu_phi(tau))) + L_embed(phi, psi)``.

        Why one summed loss reproduces the paper's alternating Algorithm 1: the two terms share no
        parameters' gradients. L_embed depends only on (phi, psi); L_DP depends only on theta because the
        latent enters it through a stop-gradient z_bar = sg(mu_phi(tau)). So the gradient of the sum is
        (grad_{phi,psi} L_embed, grad_theta L_DP), exactly Step 1 and Step 2 of Algorithm 1; LeRobot's
        optimizer applies them in one step with each group's own learning rate (get_optim_params). The
        only difference is that Step 2 sees phi before rather than after this step's Step-1 update.
        """
        loss, metrics = self.loss_terms(batch)
        # one host transfer for all logged values (each .item() would wait for the GPU on its own)
        values = torch.stack([v.detach().float() for v in metrics.values()]).tolist()
        return loss, dict(zip(metrics, values, strict=True))

    def loss_terms(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]]:
        """``forward``'s loss and its logged terms as 0-d tensors, without a single host synchronisation."""
        self._check_batch(batch)
        z_bar, behavior = self._batch_latents(batch)
        obs_cond = self._obs_cond(batch)
        actions = batch[ACTION]
        eps = torch.randn_like(actions)
        k = torch.randint(0, self.config.num_train_timesteps, (actions.shape[0],), device=actions.device)
        noisy = self.noise_schedule.add_noise(actions, eps, k)
        pred = self.denoiser(noisy, k, obs_cond, z_bar)
        is_pad = batch.get("action_is_pad") if self.config.do_mask_loss_for_padding else None
        loss_dp = diffusion_loss(pred, eps, is_pad)
        metrics: dict[str, Tensor] = {"loss_dp": loss_dp}
        loss = loss_dp
        if self.config.latent_type == "continuous" and self.training:
            loss_embed, embed_info = self._embedding_loss(actions.device)
            loss = loss + loss_embed
            metrics.update(embed_info, loss_embed=loss_embed)
        return loss, metrics

    def _embedding_loss(self, device) -> tuple[Tensor, dict]:
        n = len(self.behavior_traces)
        idx = torch.randperm(n, device=device)[: self.config.embed_batch_size]
        return self.vae.loss(
            self.behavior_traces[idx], self.trace_distance_matrix[idx][:, idx], self.geo_kappa,
            self.config.beta_kl, self.config.beta_geo,
        )

    def _check_batch(self, batch: dict[str, Tensor]) -> None:
        cfg = self.config
        expect = {OBS_STATE: (cfg.n_obs_steps, self.state_dim), ACTION: (cfg.horizon, self.action_dim)}
        if self.env_dim:
            expect[OBS_ENV_STATE] = (cfg.n_obs_steps, self.env_dim)
        for key, shape in expect.items():
            if key not in batch:
                raise KeyError(f"batch has no '{key}'; PDP needs {sorted(expect)} (got {sorted(batch)})")
            if tuple(batch[key].shape[1:]) != shape:
                raise ValueError(f"batch['{key}'] has shape {tuple(batch[key].shape)}, expected [B, {shape[0]}, {shape[1]}]")
        if "episode_index" not in batch:
            raise KeyError("batch has no 'episode_index': PDP conditions each window on its episode's latent")

    def _behavior_ids(self, episode_index: Tensor, global_index: Tensor | None) -> Tensor:
        """Behavior (episode, or gripper phase of an episode) of each training sample."""
        if len(self.behavior_episode) == 0:
            raise RuntimeError(
                "PDP has no behavior traces: build it with dataset_meta (lerobot-train does) or load a checkpoint"
            )
        ep = episode_index.view(-1, 1).to(self.behavior_episode.device)
        match = ep == self.behavior_episode.view(1, -1)
        known = match.any(1).all()
        if known.device.type == "cpu":
            if not bool(known):
                missing = episode_index.view(-1)[~match.any(1).cpu()].unique().tolist()
                raise KeyError(f"episode(s) {missing} are not among the policy's training episodes "
                               f"({self.behavior_episode.unique().numel()} episodes, "
                               f"{len(self.behavior_episode)} behaviors)")
        else:  # checked on the device: reading the flag back would stall the GPU every training step
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

    def _batch_latents(self, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        ids = self._behavior_ids(batch["episode_index"], batch.get("index"))
        with torch.no_grad():  # stop-gradient: L_DP must not shape the latent geometry
            if ids.device.type != "cpu":  # unique() has a data-dependent size: the host would wait for it
                return self.behavior_latents(ids).to(batch[ACTION].device), ids
            uniq, inverse = ids.unique(return_inverse=True)
            z = self.behavior_latents(uniq)
        return z[inverse].to(batch[ACTION].device), ids

    def _obs_cond(self, batch: dict[str, Tensor]) -> Tensor:
        feats = [batch[OBS_STATE]]
        if self.env_dim:
            feats.append(batch[OBS_ENV_STATE])
        return torch.cat(feats, dim=-1).flatten(1)

    # ------------------------------------------------------------------ acting

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

    def _sample(self, obs_cond: Tensor, z: Tensor, noise: Tensor, n: int, cache_latent: bool = True) -> Tensor:
        context = self.denoiser.make_context(obs_cond, z, self.noise_schedule.timesteps(n), cache_latent)
        return self.noise_schedule.sample(lambda x, i, k: self.denoiser.run_cached(x, context[i]), noise, n)

    def _generate_graphed(self, obs_cond: Tensor, z: Tensor, noise: Tensor, n: int) -> Tensor:
        """:meth:`_sample` replayed from a CUDA graph, captured per input shape and sampler steps.

        Recaptured when the weights change (the graph reads the weight constants of the capture, and
        ``weight_constants`` returns a new object after an optimizer step, ``load_state_dict`` or ``.to``).
        """
        consts = self.denoiser.weight_constants(self.noise_schedule.timesteps(n))
        key = (tuple(obs_cond.shape), tuple(z.shape), tuple(noise.shape), n, obs_cond.dtype, obs_cond.device,
               torch.is_inference_mode_enabled())
        call = self._graphs.get(key, consts, lambda o, zz, x: self._sample(o, zz, x, n, cache_latent=False),
                                (obs_cond, z, noise))
        return call(obs_cond, z, noise)

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], noise: Tensor | None = None, **kwargs) -> Tensor:
        """The next ``n_action_steps`` normalised actions [B, n_action_steps, A] under the active latent."""
        queues_populated = len(self._queues[OBS_STATE]) > 0
        if queues_populated:
            batch = {k: torch.stack(list(self._queues[k]), dim=1) for k in batch if k in self._queues}
        obs_cond = self._obs_cond(batch)
        z = self.current_latent(obs_cond.shape[0], obs_cond.device)
        chunk = self.generate(obs_cond, z, noise=noise)
        start = self.config.n_obs_steps - 1
        return chunk[:, start : start + self.config.n_action_steps]

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], noise: Tensor | None = None, **kwargs) -> Tensor:
        """One normalised action [B, A] per call; a new chunk is generated when the queue runs empty."""
        batch = {k: v for k, v in batch.items() if k != ACTION}
        self._queues = populate_queues(self._queues, batch)
        if len(self._queues[ACTION]) == 0:
            actions = self.predict_action_chunk(batch, noise=noise)
            self._queues[ACTION].extend(actions.transpose(0, 1))
        action = self._queues[ACTION].popleft()
        self._advance_phase(action)
        return action

    def _advance_phase(self, action: Tensor) -> None:
        """With one latent per phase, move each env to its next latent when its gripper command flips.

        Tracked per batch element: in a vectorised rollout the envs grasp at different times, and one
        env's grasp must not switch the others to their carry latent. A flip counts once the new gripper
        state has held for ``phase_switch_steps`` executed actions, so a blip does not skip a phase.
        """
        cfg = self.config
        if len(self.active_latent) <= 1 or cfg.segment_gripper_dim is None:
            return
        raw = self.stats.unnormalize(ACTION, action)[:, cfg.segment_gripper_dim]
        closed = raw > cfg.segment_gripper_threshold
        phase = self._phase_state(closed.shape[0], closed.device)
        if self._last_gripper_closed is None:  # the first action sets each env's phase-0 gripper state
            self._last_gripper_closed, self._gripper_hold = closed, torch.zeros_like(phase)
            return
        differs = closed != self._last_gripper_closed
        self._gripper_hold = torch.where(differs, self._gripper_hold + 1, 0)
        switch = (self._gripper_hold >= cfg.phase_switch_steps) & (phase < len(self.active_latent) - 1)
        if bool(switch.any()):
            self._phase = phase + switch.long()
            self._last_gripper_closed = torch.where(switch, closed, self._last_gripper_closed)
            self._gripper_hold = torch.where(switch, 0, self._gripper_hold)
            # the next chunk is generated under the new phase's latent (other envs just replan early)
            self._queues[ACTION].clear()

    def _phase_state(self, batch_size: int, device: torch.device | str) -> Tensor:
        """Per-env phase indices [batch_size]; restarts at phase 0 when the batch size changes."""
        if self._phase is None or self._phase.shape[0] != batch_size:
            self._phase = torch.zeros(batch_size, dtype=torch.long, device=device)
            self._last_gripper_closed = None
        return self._phase

    def current_latent(self, batch_size: int = 1, device: torch.device | str | None = None) -> Tensor:
        """The latent the next chunk is conditioned on, [batch_size, d_z] (each env's own phase latent)."""
        if not self._steering_initialised:
            self._init_steering_from_config()
        device = device or self.geo_kappa.device
        if len(self.active_latent):
            if len(self.active_latent) == 1:
                return self.active_latent[0].to(device).expand(batch_size, -1)
            phase = self._phase_state(batch_size, self.active_latent.device)
            return self.active_latent[phase.clamp(max=len(self.active_latent) - 1)].to(device)
        if self._episode_latent is None or self._episode_latent.shape[0] != batch_size:
            self._episode_latent = self._default_latent(batch_size).to(device)
        return self._episode_latent

    def _default_latent(self, batch_size: int) -> Tensor:
        d = self.config.latent_dim
        if self.config.inference_latent == "zero":
            return torch.zeros(batch_size, d)
        if self.config.inference_latent == "prior" or len(self.behavior_traces) == 0:
            return torch.randn(batch_size, d)
        with torch.no_grad():
            ids = torch.randint(0, len(self.behavior_traces), (batch_size,), device=self.behavior_traces.device)
            return self.behavior_latents(ids).cpu()

    def _init_steering_from_config(self) -> None:
        """Apply the config's steering fields (how ``lerobot-eval`` steers a PDP checkpoint)."""
        self._steering_initialised = True
        cfg = self.config
        if cfg.steer_latent is not None:
            self.set_latent(torch.tensor(cfg.steer_latent, dtype=torch.float32))
        elif cfg.steer_mode is not None:
            means = self.mode_latents()
            if cfg.steer_mode not in means:
                raise KeyError(f"steer_mode {cfg.steer_mode} is not a training mode; modes are {sorted(means)}")
            self.set_latent(means[cfg.steer_mode])
        elif cfg.steer_dataset_root is not None:
            res = self.fit_latent((cfg.steer_dataset_root, int(cfg.steer_episode_index)))
            logger.info("fitted latent to %s episode %d: %s", cfg.steer_dataset_root, cfg.steer_episode_index,
                        res.z.tolist())

    # ------------------------------------------------------------------ steering API

    def set_latent(self, z: Tensor | Sequence[float] | np.ndarray | None) -> None:
        """Make ``z`` ([d_z], or [M, d_z] = one latent per phase) the active latent; None = back to default."""
        self._steering_initialised = True
        if z is None:
            self.active_latent = torch.zeros(0, self.config.latent_dim, device=self.geo_kappa.device)
            return
        z = torch.as_tensor(np.asarray(z, dtype=np.float32) if not isinstance(z, Tensor) else z).float()
        if z.dim() == 1:
            z = z[None]
        if z.dim() != 2 or z.shape[1] != self.config.latent_dim:
            raise ValueError(f"latent must have shape [{self.config.latent_dim}] or [M, {self.config.latent_dim}], "
                             f"got {tuple(z.shape)}")
        if not torch.isfinite(z).all():
            raise ValueError(f"latent has non-finite values: {z.tolist()}")
        self.active_latent = z.detach().to(self.geo_kappa.device)
        self._phase = None
        self._last_gripper_closed = None

    def mode_latents(self) -> dict[int, Tensor]:
        """Per-mode mean latent (mean of its training behaviors' encoder means); mode ids from task strings.

        With gripper-segmented behaviors (several per episode) each mode gets one mean per phase,
        [n_phases, d_z], which ``set_latent`` uses in order as the phases advance (paper Eq. 12).
        """
        labeled = self.behavior_mode >= 0
        if len(self.behavior_mode) == 0 or not bool(labeled.any()):
            raise ValueError(
                "mode_latents() needs mode labels: the training episodes' task strings must look like "
                "'mode <id>: <name>' (this policy has "
                f"{len(self.behavior_mode)} behaviors, {int(labeled.sum())} labeled)"
            )
        with torch.no_grad():
            z = self.behavior_latents()
        phase = self.behavior_phase()
        out = {}
        for m in self.behavior_mode[labeled].unique():
            of_mode = self.behavior_mode == m
            if int(phase.max()) == 0:
                out[int(m)] = z[of_mode].mean(0).cpu()
            else:
                out[int(m)] = torch.stack([z[of_mode & (phase == k)].mean(0)
                                           for k in range(int(phase[of_mode].max()) + 1)]).cpu()
        return out

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

    @staticmethod
    def interpolate(z_a: Tensor, z_b: Tensor, n: int, path: str = "linear") -> Tensor:
        """``n`` latents from ``z_a`` to ``z_b`` (endpoints included), [n, *z_a.shape].

        ``linear``: straight line; between two clusters on opposite sides of the latent map it passes
        through the map's centre, i.e. through behaviors that lie between opposite routes.
        ``elliptical``: an arc around the origin in the plane of ``z_a`` and ``z_b``, angle and radius
        interpolated linearly (a sweep around the ring of clusters; for orthogonal codes of equal
        norm it is ``z_a cos(t) + z_b sin(t)``, t in [0, pi/2]). It keeps the radius between |z_a| and
        |z_b|, so it visits the clusters between the two ends instead of the centre; opposite codes span
        no plane, and the arc then turns towards the coordinate axis least aligned with ``z_a``. Each row
        of a per-phase latent [P, d_z] gets its own arc.
        """
        z_a, z_b = torch.as_tensor(z_a).float(), torch.as_tensor(z_b).float()
        if z_a.shape != z_b.shape:
            raise ValueError(f"z_a {tuple(z_a.shape)} and z_b {tuple(z_b.shape)} must have the same shape")
        if n < 2:
            raise ValueError(f"n must be >= 2 (both endpoints), got {n}")
        if path not in ("linear", "elliptical"):
            raise ValueError(f"path must be 'linear' or 'elliptical', got {path!r}")
        t = torch.linspace(0, 1, n).view(-1, *([1] * z_a.dim()))
        line = (1 - t) * z_a + t * z_b
        if path == "linear" or z_a.dim() == 0 or z_a.shape[-1] < 2:
            return line
        eps = 1e-8
        r_a, r_b = z_a.norm(dim=-1, keepdim=True), z_b.norm(dim=-1, keepdim=True)
        u = z_a / r_a.clamp_min(eps)
        w = z_b - (z_b * u).sum(-1, keepdim=True) * u  # z_b's part orthogonal to z_a
        # opposite (or parallel) codes span no plane: turn towards the basis axis least aligned with z_a
        axis = F.one_hot(u.abs().argmin(-1), u.shape[-1]).to(u)
        fallback = axis - (axis * u).sum(-1, keepdim=True) * u
        degenerate = w.norm(dim=-1, keepdim=True) < 1e-6 * r_b.clamp_min(eps)
        w = torch.where(degenerate, fallback, w)
        v = w / w.norm(dim=-1, keepdim=True).clamp_min(eps)
        phi = torch.atan2((z_b * v).sum(-1, keepdim=True).abs(), (z_b * u).sum(-1, keepdim=True))
        arc = ((1 - t) * r_a + t * r_b) * (u * torch.cos(t * phi) + v * torch.sin(t * phi))
        # a zero endpoint has no direction: the arc is the line there
        return torch.where((torch.minimum(r_a, r_b) < eps).expand_as(z_a), line, arc)

    def encode(self, episode: Episode, segments: list[tuple[int, int]] | str | None = "auto") -> Tensor:
        """z_bar = mu_phi(X(tau)) of a demonstration ([d_z]; [M, d_z] with ``segments``, see ``fit_latent``)."""
        segments = self._segments_as_trained(segments)
        ep = self._episode_arrays(episode, need_action=segments == "gripper")
        segs = self._resolve_segments(ep, segments)
        cfg = self.config
        traces = np.stack([make_trace(ep[cfg.trace_key][a:b], cfg.trace_dims, cfg.trace_length, cfg.trace_normalize)
                           for a, b in segs])
        with torch.no_grad():
            if cfg.latent_type == "onehot":
                # nearest training behavior's mode (the one-hot ablation has no encoder)
                t = torch.as_tensor(traces, dtype=torch.float32, device=self.behavior_traces.device)
                d = (t[:, None] - self.behavior_traces[None]).pow(2).flatten(2).sum(-1)
                z = F.one_hot(self.behavior_mode[d.argmin(1)], cfg.latent_dim).float()
            else:
                z = self.vae.encode(torch.as_tensor(traces, dtype=torch.float32, device=self.geo_kappa.device))[0]
        z = z.cpu()
        return z if segments is not None else z[0]

    def fit_latent(self, episode: Episode, steps: int | None = None, init: str | Tensor = "encoder",
                   lr: float | None = None, lam: float | None = None,
                   segments: list[tuple[int, int]] | str | None = "auto", seed: int | None = 0,
                   activate: bool = True, progress: bool = False) -> FitResult:
        """Fit z to one demonstration with every weight frozen (paper Alg. 3 / Eq. 11, Eq. 12 with segments).

        Args:
            episode: dict of unnormalised arrays/tensors as stored in a LeRobotDataset (``observation.*``,
                ``action``; shapes [T, ...]) or a ``(LeRobotDataset | root path, episode_index)`` pair.
            steps: gradient steps S (default ``config.fit_steps``); 0 returns the warm start.
            init: ``"encoder"`` (z0 = mu_phi(X(tau)), the semantic warm start), ``"random"`` (N(0, I)),
                ``"zero"``, or a tensor.
            lr, lam: Adam step size and the weight of lambda |z|^2.
            segments: None (one z), a list of frame ranges, or ``"gripper"`` (split on gripper events of
                ``config.segment_gripper_dim``): one z per phase, used in order during the rollout.
                ``"auto"`` (default): as the policy was trained, i.e. ``"gripper"`` when
                ``config.segment_gripper_dim`` is set, else None.
            activate: make the result the active latent.

        Returns:
            :class:`FitResult` with ``z`` ([d_z] or [M, d_z]), the initial z and the loss history.
        """
        # Gradients w.r.t. z are needed even when called under torch.inference_mode() / no_grad, e.g. when
        # lerobot-eval's first select_action triggers fitting from --policy.steer_dataset_root.
        with torch.inference_mode(False), torch.enable_grad():
            return self._fit_latent(episode, steps, init, lr, lam, segments, seed, activate, progress)

    def demo_windows(self, episode: Episode, segments: list[tuple[int, int]] | str | None = "auto") -> DemoWindows:
        """The (normalised) training-style windows of one demonstration, each tagged with its phase.

        ``segments`` as in :meth:`fit_latent`; ``windows.n_segments`` phases, ``windows.segment[t]`` the
        phase of the window at frame t. What L_fit is computed on.
        """
        ep = self._episode_arrays(episode, need_action=True)
        return self._windows(ep, self._resolve_segments(ep, self._segments_as_trained(segments)))

    def _windows(self, ep: dict[str, np.ndarray], segs: list[tuple[int, int]]) -> DemoWindows:
        cfg = self.config
        return episode_windows(self.stats.normalize_episode(ep), cfg.n_obs_steps, cfg.horizon, OBS_STATE,
                               OBS_ENV_STATE if self.env_dim else None, segs)

    def _fit_latent(self, episode, steps, init, lr, lam, segments, seed, activate, progress) -> FitResult:
        cfg = self.config
        segments = self._segments_as_trained(segments)
        ep = self._episode_arrays(episode, need_action=True)
        segs = self._resolve_segments(ep, segments)
        windows = self._windows(ep, segs)
        if not cfg.do_mask_loss_for_padding:  # fit on the same loss the denoiser was trained with
            windows = dataclasses.replace(windows, is_pad=torch.zeros_like(windows.is_pad))
        device = self.geo_kappa.device
        if isinstance(init, Tensor):
            z0 = init.float().reshape(len(segs), cfg.latent_dim)
        elif init == "encoder":
            z0 = self.encode(ep, segments=segs)
        elif init == "random":
            g = torch.Generator().manual_seed(seed if seed is not None else 0)
            z0 = torch.randn(len(segs), cfg.latent_dim, generator=g)
        elif init == "zero":
            z0 = torch.zeros(len(segs), cfg.latent_dim)
        else:
            raise ValueError(f"init must be 'encoder', 'random', 'zero' or a tensor, got {init!r}")
        was_training = self.training
        self.eval()
        try:
            result = fit_latent(
                self.denoiser, self.noise_schedule, windows, z0.to(device),
                steps=cfg.fit_steps if steps is None else steps, lr=cfg.fit_lr if lr is None else lr,
                lam=cfg.fit_lambda if lam is None else lam, batch_size=cfg.fit_batch_size,
                noise_samples=cfg.fit_noise_samples, seed=seed, progress=progress, gradient=cfg.fit_gradient,
            )
        finally:
            self.train(was_training)
        if segments is None:
            result.z, result.z_init = result.z[0], result.z_init[0]
        if activate:
            self.set_latent(result.z)
        return result

    # ------------------------------------------------------------------ episode input

    def _segments_as_trained(self, segments):
        """``"auto"``: split demonstrations the way the training behaviors were split."""
        if isinstance(segments, str) and segments == "auto":
            return "gripper" if self.config.segment_gripper_dim is not None else None
        return segments

    def _resolve_segments(self, ep: dict[str, np.ndarray], segments) -> list[tuple[int, int]]:
        T = len(ep[OBS_STATE])
        if segments is None:
            return [(0, T)]
        if isinstance(segments, str) and segments != "gripper":
            raise ValueError(f"segments must be None, 'auto', 'gripper' or a list of (start, end) frame ranges, "
                             f"got {segments!r}")
        if segments == "gripper":
            if self.config.segment_gripper_dim is None:
                raise ValueError("segments='gripper' needs config.segment_gripper_dim (the gripper action dim)")
            return gripper_segments(ep[ACTION], self.config.segment_gripper_dim,
                                    self.config.segment_gripper_threshold)
        segs = [(int(a), int(b)) for a, b in segments]
        for a, b in segs:
            if not 0 <= a < b <= T:
                raise ValueError(f"segment ({a}, {b}) is not a non-empty frame range within the episode's {T} frames")
        return segs

    def _episode_arrays(self, episode: Episode, need_action: bool) -> dict[str, np.ndarray]:
        """Validate a demonstration and return its arrays (float64, unnormalised) by feature key."""
        cfg = self.config
        where = "episode"
        if isinstance(episode, tuple):
            source, index = episode
            root = source if isinstance(source, (str, Path)) else getattr(source, "root", None)
            if root is None:
                raise TypeError(f"episode source must be a LeRobotDataset or a dataset folder, got {type(source)}")
            where = f"episode {index} of {root}"
            keys = [OBS_STATE, ACTION, cfg.trace_key] + ([OBS_ENV_STATE] if self.env_dim else [])
            eps = read_episodes(root, list(dict.fromkeys(keys)), [int(index)])
            if int(index) not in eps:
                raise KeyError(f"{root} has no episode {index}")
            episode = eps[int(index)]
        if not isinstance(episode, dict):
            raise TypeError(f"episode must be a dict of arrays or a (dataset, episode_index) pair, got {type(episode)}")
        required = {OBS_STATE: self.state_dim}
        if self.env_dim:
            required[OBS_ENV_STATE] = self.env_dim
        if need_action:
            required[ACTION] = self.action_dim
        if cfg.trace_key not in required:
            required[cfg.trace_key] = cfg.input_features[cfg.trace_key].shape[0]
        out: dict[str, np.ndarray] = {}
        lengths = {}
        for key, dim in required.items():
            if key not in episode:
                raise KeyError(f"{where}: missing '{key}'; PDP needs {sorted(required)} (got {sorted(episode)})")
            v = episode[key]
            v = v.detach().cpu().numpy() if isinstance(v, Tensor) else np.asarray(v)
            v = v.astype(np.float64)
            if v.ndim != 2 or v.shape[1] != dim:
                raise ValueError(f"{where}: '{key}' has shape {tuple(v.shape)}, expected [T, {dim}]")
            check_finite(key, v, where)
            out[key] = v
            lengths[key] = len(v)
        if len(set(lengths.values())) != 1:
            raise ValueError(f"{where}: keys have different lengths {lengths}")
        T = next(iter(lengths.values()))
        if T < cfg.horizon:
            raise ValueError(f"{where}: has {T} frames, shorter than one action chunk (horizon {cfg.horizon})")
        return out

    def _save_pretrained(self, save_directory: Path, state_dict: dict[str, Tensor] | None = None) -> None:
        """Write config + weights into a temporary folder next to ``save_directory``, then move them in,
        so a crash mid-write never leaves a half checkpoint (weights are moved last)."""
        save_directory = Path(save_directory)
        save_directory.mkdir(parents=True, exist_ok=True)
        try:
            with staging_dir(save_directory, prefix=".pdp-save-") as tmp:
                self.config._save_pretrained(tmp)
                if state_dict is None:
                    save_model_as_safetensor(self, str(tmp / SAFETENSORS_SINGLE_FILE))
                else:
                    save_torch_state_dict(state_dict, str(tmp), max_shard_size=10**12)
                names = sorted(p.name for p in tmp.iterdir())
                for name in sorted(names, key=lambda n: n.endswith(".safetensors")):
                    os.replace(tmp / name, save_directory / name)
        finally:
            if not any(save_directory.iterdir()):
                save_directory.rmdir()

    def generate_model_card(self, dataset_repo_id: str, model_type: str, license: str | None,
                            tags: list[str] | None, cfg: Any = None, dataset_meta: Any = None):
        """LeRobot's model card (same template and context) plus what PDP is and how to steer it.

        Unlike the base class it validates the card against the Hub only when online, so cards can be
        written and tested with ``HF_HUB_OFFLINE=1``.
        """
        from importlib.resources import files

        from huggingface_hub import ModelCard, ModelCardData
        from huggingface_hub.constants import HF_HUB_OFFLINE
        from lerobot.policies.pretrained import _build_card_context

        card_data = ModelCardData(
            license=license or "apache-2.0", library_name="lerobot", pipeline_tag="robotics",
            tags=sorted(set(tags or []) | {"robotics", "lerobot", model_type, "parameterized-diffusion-policy"}),
            model_name=model_type, datasets=dataset_repo_id,
        )
        context = _build_card_context(cfg, dataset_meta, self.config.input_features, self.config.output_features)
        context["policy_repo_id"] = getattr(self.config, "repo_id", None)
        context["base_model"] = None
        template = files("lerobot.templates").joinpath("lerobot_modelcard_template.md").read_text(encoding="utf-8")
        card = ModelCard.from_template(card_data, template_str=template, **context)
        card.text = card.text + MODEL_CARD_PDP
        if not HF_HUB_OFFLINE:
            card.validate()
        return card


MODEL_CARD_PDP = """

## Parameterized Diffusion Policy (PDP)

This checkpoint is a **Parameterized Diffusion Policy**: a diffusion policy whose denoiser is FiLM-modulated
by a low-dimensional *behavior latent* `z`. A trajectory VAE trained with a soft-DTW geometry loss makes
distances in `z` match distances between demonstrated trajectories, so `z` is a steering handle.

```python
from lerobot_pdp import PDPPolicy
policy = PDPPolicy.from_pretrained("<this repo or folder>")
policy.mode_latents()                      # per-mode mean latents of the training demonstrations
policy.set_latent(policy.mode_latents()[3]) # act like mode 3
policy.fit_latent((dataset, episode_index)) # adapt to ONE new demonstration: fits z only, weights frozen
```

From the command line: `lerobot-eval --policy.path=<this> --policy.steer_mode=3 ...`, or
`--policy.steer_dataset_root=DIR --policy.steer_episode_index=0` to fit `z` to a demonstration at start-up.
Requires `pip install lerobot_policy_pdp`.
"""


class _FeatureStats(nn.Module):
    """Normalisation statistics of the policy's features, kept as buffers so the policy can normalise
    raw demonstrations (fit_latent/encode) exactly like its LeRobot preprocessor does."""

    STATS = ("min", "max", "mean", "std")

    def __init__(self, config: PDPConfig):
        super().__init__()
        self.config = config
        self.features = {k: ft for k, ft in {**config.input_features, **config.output_features}.items()
                         if ft.type in (FeatureType.STATE, FeatureType.ENV, FeatureType.ACTION)}
        for key, ft in self.features.items():
            for s in self.STATS:
                self.register_buffer(self._name(key, s), torch.zeros(ft.shape) if s != "std" else torch.ones(ft.shape))
        self.register_buffer("loaded", torch.tensor(False))

    @staticmethod
    def _name(key: str, stat: str) -> str:
        return f"{key.replace('.', '__')}__{stat}"

    def load(self, dataset_stats: dict[str, dict[str, Any]]) -> None:
        for key in self.features:
            if key not in dataset_stats:
                continue
            for s in self.STATS:
                if s in dataset_stats[key]:
                    getattr(self, self._name(key, s)).copy_(torch.as_tensor(np.asarray(dataset_stats[key][s]),
                                                                            dtype=torch.float32))
        self.loaded.fill_(True)
        self._cached_step = None

    def as_dict(self) -> dict[str, dict[str, Tensor]]:
        return {k: {s: getattr(self, self._name(k, s)) for s in self.STATS} for k in self.features}

    def _load_from_state_dict(self, *args, **kwargs):
        self._cached_step = None  # statistics change when a checkpoint is loaded
        super()._load_from_state_dict(*args, **kwargs)

    def _step(self):
        """LeRobot's normaliser over these statistics, built once (select_action may call it every step)."""
        if getattr(self, "_cached_step", None) is None:
            self._cached_step = self._build_step()
        return self._cached_step

    def _build_step(self):
        from lerobot.processor import NormalizerProcessorStep

        return NormalizerProcessorStep(features=self.features, norm_map=self.config.normalization_mapping,
                                       stats={k: {s: v.cpu() for s, v in d.items()} for k, d in self.as_dict().items()})

    def normalize_episode(self, ep: dict[str, np.ndarray]) -> dict[str, Tensor]:
        """Normalise raw episode arrays with LeRobot's own normaliser (same maths as the preprocessor)."""
        if not bool(self.loaded):
            raise RuntimeError("the policy has no dataset statistics; build it with dataset_stats or load a checkpoint")
        step = self._step()
        obs = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in ep.items() if k != ACTION}
        out = step._normalize_observation(obs, inverse=False)
        if ACTION in ep:
            out[ACTION] = step._normalize_action(torch.as_tensor(ep[ACTION], dtype=torch.float32), inverse=False)
        return out

    def unnormalize(self, key: str, x: Tensor) -> Tensor:
        """Raw values of ``x`` (normalised), on ``x``'s device (LeRobot's step moves its statistics there)."""
        step = self._step()
        if key == ACTION:
            return step._normalize_action(x, inverse=True)
        return step._normalize_observation({key: x}, inverse=True)[key]
