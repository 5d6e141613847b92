"""Parameterized Diffusion Policy (PDP): a diffusion policy steered by a geometry-aligned behavior latent z.

The public face is :class:`PDPPolicy`, a LeRobot ``PreTrainedPolicy``:

- training runs inside ``lerobot-train`` (``forward`` returns L_DP + L_embed, see its docstring);
- ``select_action`` / ``predict_action_chunk`` act conditioned on the *active latent*;
- steering: ``encode(episode)``, ``set_latent(z)``, ``mode_latents()``, ``interpolate(z_a, z_b, n)`` and
  ``fit_latent(episode)`` (paper Alg. 3: encoder warm start, then gradient steps on z, weights frozen) and
  ``search_latent(env_factory, score)`` (z searched by what rollouts achieve, without a demonstration).

The networks, the training behaviors and the loss live in :class:`~lerobot_pdp.pdp_model.PDPModel`; the
state a rollout acts under (active latent per phase, chunk noises, phases) in
:class:`~lerobot_pdp.steering_state.Steering`; reading a demonstration in ``demonstration.py``, fitting to it
in ``adaptation.py``, the checkpoint on disk in ``checkpoint.py``. This class holds what LeRobot and a user
talk to: the training step, the action queue and the steering API. Data flows one way: dataset -> behavior
traces -> trajectory encoder -> z -> FiLM denoiser -> actions.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.policies.utils import populate_queues
from lerobot.utils.constants import ACTION
from torch import Tensor

from .adaptation import encode_demonstration, fit_demonstration, fit_provenance, initial_latent
from .behavior import read_training_behaviors, warn_few_episodes
from .behavior_bank import resolve_dataset_config
from .candidate_rollouts import EnvFactory
from .checkpoint import (
    apply_saved_config,
    check_finite_weights,
    check_weight_shapes,
    flatten_model_keys,
    nest_model_keys,
    read_adaptation,
    resize_to_checkpoint,
    save_checkpoint,
)
from .checkpoint_files import check_checkpoint_source, damaged_weights, read_weight_shapes
from .configuration_pdp import PDPConfig
from .cpu_threads import apply_cpu_threads
from .demonstration import Demonstration, Episode, demonstration_windows, read_demonstration
from .interpolation import interpolate
from .latent_fitting import DemoWindows, FitResult
from .latent_search import SearchResult, search_latent, search_provenance
from .model_card import pdp_model_card
from .modes import DiscoveredModes, ModeLatents
from .normalization import FeatureStats
from .outcome_scores import Score
from .pdp_model import PDPModel
from .steering import SteerFile
from .steering_state import Steering
from .teaching import TEACH_DEMO_SHARE, TEACH_LR, TEACH_STEPS, TeachResult, teach_new_mode

logger = logging.getLogger(__name__)


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
        apply_cpu_threads(config.cpu_threads)  # before the behavior bank's soft-DTW and any step

        cfg = config
        self.action_dim = cfg.action_feature.shape[0]

        self.stats = FeatureStats(cfg)
        if dataset_stats is not None:
            self.stats.load(dataset_stats)

        behaviors = None
        if dataset_meta is not None and getattr(dataset_meta, "root", None) is not None:
            behaviors = read_training_behaviors(config, dataset_meta.root, dataset_meta.features)
            warn_few_episodes(behaviors, dataset_meta.root, config.beta_geo)
            resolve_dataset_config(config, behaviors)  # mode_names, one-hot latent_dim: before anything is built
        self.model = PDPModel(cfg, self.action_dim, behaviors)
        # Checkpoints keep the flat key names of the first release ("vae.*", "behavior_traces", ...).
        self.register_state_dict_post_hook(flatten_model_keys)
        self.register_load_state_dict_pre_hook(nest_model_keys)

        # What the next chunk is conditioned on (active latent per phase, chunk noises, phases): see
        # steering_state.py. The config's steering fields are applied when a checkpoint is loaded.
        self.steering = Steering(cfg.latent_dim)
        self._steer_file = SteerFile(config.steer_file) if config.steer_file else None
        self._queues: dict[str, deque] = {}
        self._train_steps = 0  # training steps of this process (named when a loss term goes non-finite)
        self.reset()

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path: str | Path, **kwargs) -> PDPPolicy:
        """LeRobot's loader; then the adaptation an adapted checkpoint carries (unless
        ``config.use_adaptation`` is false), then the config's steering (``steer_latent`` / ``steer_mode`` /
        ``steer_dataset_root``, which override it): a fit to a demonstration runs here, before any control
        loop starts."""
        check_checkpoint_source(pretrained_name_or_path, need_config=kwargs.get("config") is None)
        policy = super().from_pretrained(pretrained_name_or_path, **kwargs)
        adaptation = read_adaptation(pretrained_name_or_path, **kwargs) if policy.config.use_adaptation else None
        if adaptation is not None:
            tensors, info = adaptation
            policy.steering.load_state_tensors(tensors, info)
            logger.info("adapted checkpoint %s: latent %s, %d chunk noise(s) (%s)", pretrained_name_or_path,
                        tensors["latent"].tolist(), len(tensors.get("noise", ())), info.get("source", "?"))
        policy.apply_config_steering()
        return policy

    # The steering state, as the first release exposed it.
    @property
    def active_latent(self) -> Tensor:
        """The active latent(s) [M, d_z] (empty: the default latent); M > 1 = one per phase."""
        return self.steering.latent

    @property
    def active_noise(self) -> Tensor:
        """Sampler noises fitted with ``noise="chunks"`` [C, horizon, A], one per new chunk, in order."""
        return self.steering.noises.noise

    @property
    def phases(self):
        return self.steering.phases

    @phases.setter
    def phases(self, tracker) -> None:
        self.steering.phases = tracker

    @classmethod
    def _load_as_safetensor(cls, model: PDPPolicy, model_file: str, map_location: str, strict: bool):
        """LeRobot's load, with the dataset-sized buffers resized to the checkpoint's and the legacy sampler
        defaults of checkpoints written before a config field existed."""
        from safetensors import SafetensorError

        shapes = read_weight_shapes(model_file)  # a damaged file: an error naming it
        resize_to_checkpoint(model.model, shapes)
        check_weight_shapes(model, model_file, shapes)  # e.g. latent_dim edited in config.json
        try:
            model = super()._load_as_safetensor(model, model_file, map_location, strict)
        except SafetensorError as e:
            raise damaged_weights(model_file, e) from e
        check_finite_weights(model, model_file)
        apply_saved_config(model, model_file)
        return model

    # ------------------------------------------------------------------ LeRobot contract

    def get_optim_params(self) -> list[dict]:
        """Two parameter groups: embedding (phi, psi) and denoiser (theta, with its camera encoders), each
        with its learning rate."""
        theta = [*self.model.denoiser.parameters(), *self.model.obs_encoder.parameters()]
        return [
            {"params": [p for p in self.model.vae.parameters() if p.requires_grad], "lr": self.config.embedding_lr},
            {"params": [p for p in theta if p.requires_grad], "lr": self.config.optimizer_lr},
        ]

    def reset(self) -> None:
        """Clear the observation/action queues and restart the latent-phase sequence (call on env.reset())."""
        self._queues = {k: deque(maxlen=self.config.n_obs_steps) for k in self.config.condition_features}
        self._queues[ACTION] = deque(maxlen=self.config.n_action_steps)
        self.steering.reset()

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """One joint training step: ``L = L_DP(theta; sg(mu_phi(tau))) + L_embed(phi, psi)``.

        Why one summed loss reproduces the paper's alternating Algorithm 1: the two terms share no
        parameters' gradients. L_embed depends only on (phi, psi); L_DP depends only on theta because the
        latent enters it through a stop-gradient z_bar = sg(mu_phi(tau)). So the gradient of the sum is
        (grad_{phi,psi} L_embed, grad_theta L_DP), exactly Step 1 and Step 2 of Algorithm 1; LeRobot's
        optimizer applies them in one step with each group's own learning rate (get_optim_params). The
        only difference is that Step 2 sees phi before rather than after this step's Step-1 update.
        """
        loss, metrics = self.model.loss_terms(batch)
        # one host transfer for all logged values (each .item() would wait for the GPU on its own)
        values = torch.stack([v.detach().float() for v in metrics.values()]).tolist()
        if self.training:
            self._train_steps += 1
            bad = {k: v for k, v in zip(metrics, values, strict=True) if not math.isfinite(v)}
            if bad:  # stop before the optimizer writes non-finite weights into the next checkpoint
                raise FloatingPointError(
                    f"PDP training step {self._train_steps} of this process: non-finite loss term(s) {bad} (all terms: "
                    f"{dict(zip(metrics, values, strict=True))}); the weights were not updated by it. Check the "
                    "dataset for non-finite values and the soft-DTW cache (LEROBOT_PDP_CACHE), or lower the lr")
        return loss, dict(zip(metrics, values, strict=True))

    # ------------------------------------------------------------------ acting

    @torch.no_grad()
    def generate(self, obs_cond: Tensor, z: Tensor, noise: Tensor | None = None,
                 generator: torch.Generator | None = None) -> Tensor:
        """Denoise action chunks [B, horizon, A] (normalised) for conditions ``obs_cond`` [B, C], ``z`` [B, d_z]."""
        return self.model.generate(obs_cond, z, noise, generator)

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], noise: Tensor | None = None, **kwargs) -> Tensor:
        """The next ``n_action_steps`` normalised actions [B, n_action_steps, A] under the active latent."""
        if any(len(q) for k, q in self._queues.items() if k != ACTION):  # online: the observation history
            batch = {k: torch.stack(list(q), dim=1) for k, q in self._queues.items() if k != ACTION}
        if self._steer_file is not None:  # live steering: a changed file sets z before this chunk
            self._steer_file.poll(self)
        obs_cond = self.model.obs_cond(batch)
        z = self.current_latent(obs_cond.shape[0], obs_cond.device)
        if noise is None:  # fitted noises: the next one, the last one repeating (None: drawn)
            noise = self.steering.next_noise(obs_cond.shape[0], obs_cond.device)
        chunk = self.generate(obs_cond, z, noise=noise)
        if not bool(torch.isfinite(chunk).all()):  # one check per chunk: a robot must never be sent NaN
            raise FloatingPointError(
                f"PDP generated non-finite actions (latent {z[0].tolist()}, observation condition finite: "
                f"{bool(torch.isfinite(obs_cond).all())}): check the observation and the checkpoint; no action is "
                "returned")
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
        """With one latent per phase, move each env to its next latent when its gripper command flips
        (see :class:`~lerobot_pdp.phases.PhaseTracker`); the next chunk is then generated under it."""
        cfg = self.config
        if not self.steering.per_phase or cfg.segment_gripper_dim is None:
            return
        raw = self.stats.unnormalize(ACTION, action)[:, cfg.segment_gripper_dim]
        if self.steering.observe(raw > cfg.segment_gripper_threshold, cfg.phase_switch_steps):
            self._queues[ACTION].clear()  # the envs that did not switch just replan early

    def current_latent(self, batch_size: int = 1, device: torch.device | str | None = None) -> Tensor:
        """The latent the next chunk is conditioned on, [batch_size, d_z] (each env's own phase latent; nothing
        active: ``config.inference_latent``, drawn once per episode). Never fits."""
        bank, vae = self.model.bank, self.model.vae
        return self.steering.latent_for(batch_size, device or self.model.device, lambda n: bank.default_latents(vae, n))

    def apply_config_steering(self) -> None:
        """Apply the config's steering fields (how ``lerobot-eval`` / ``lerobot-rollout`` steer a checkpoint);
        :meth:`from_pretrained` calls it. A fit to ``steer_dataset_root`` runs now, not in the control loop."""
        cfg = self.config
        if cfg.steer_latent is not None:
            self.set_latent(torch.tensor(cfg.steer_latent, dtype=torch.float32))
        elif cfg.steer_mode is not None:
            means = self.mode_latents()
            if cfg.steer_mode not in means:
                raise KeyError(f"steer_mode {cfg.steer_mode} is not a training mode; modes are {sorted(means)}")
            self.steering.activate(means[cfg.steer_mode], provenance={"source": "mode", "mode": cfg.steer_mode})
        elif cfg.steer_dataset_root is not None:
            t0 = time.perf_counter()
            res = self.fit_latent((cfg.steer_dataset_root, int(cfg.steer_episode_index)))
            logger.info("fitted latent to %s episode %d in %.1f s: %s (error ratio %s; from %g at risk)",
                        cfg.steer_dataset_root, cfg.steer_episode_index, time.perf_counter() - t0, res.z.tolist(),
                        "n/a" if res.error_ratio is None else f"{res.error_ratio:.2f}", cfg.fit_warn_ratio)

    # ------------------------------------------------------------------ steering API

    def set_latent(self, z: Tensor | Sequence[float] | np.ndarray | None) -> None:
        """Make ``z`` ([d_z], or [M, d_z] = one latent per phase) the active latent; None = back to default.
        Noises fitted under another latent no longer apply. A latent far outside the training latents is
        accepted with one warning (see :meth:`latent_outlier`): the policy never saw it condition an action."""
        self.steering.activate(z)
        if z is not None:
            self.model.bank.warn_if_far(self.model.vae, self.steering.latent)

    def latent_outlier(self, z: Tensor) -> tuple[float, float] | None:
        """(distance in spreads, spread) when a row of ``z`` lies far from every training latent: :meth:`BehaviorBank.outlier`."""
        return self.model.bank.outlier(self.model.vae, z)

    def mode_latents(self) -> ModeLatents:
        """Per-mode mean latent (one per phase for segmented policies); without mode labels, the discovered modes
        with a warning. See :meth:`lerobot_pdp.behavior_bank.BehaviorBank.mode_latents`."""
        return self.model.bank.mode_latents(self.model.vae)

    def discover_modes(self, k: int | None = None, max_k: int | None = None, seed: int = 0,
                       space: str = "traces") -> DiscoveredModes:
        """Cluster the training episodes, the modes of a dataset without mode labels (``space`` "traces" or
        "latents"). Every argument: :meth:`lerobot_pdp.behavior_bank.BehaviorBank.discover_modes`."""
        return self.model.bank.discover_modes(self.model.vae, k, max_k, seed, space)

    def behavior_latents(self, ids: Tensor | None = None) -> Tensor:
        """z_bar = mu_phi(X(tau)) of training behaviors (all, or ``ids``); one-hot codes for that ablation."""
        return self.model.behavior_latents(ids)

    def behavior_phase(self) -> Tensor:
        """Phase index of each training behavior within its episode (0 when episodes are not segmented)."""
        return self.model.bank.phase()

    def behavior_table(self) -> dict[str, np.ndarray]:
        """Latent of every training behavior with its episode, frame range and mode (for maps/plots)."""
        return self.model.bank.table(self.model.vae)

    @staticmethod
    def interpolate(z_a: Tensor, z_b: Tensor, n: int, path: str = "linear") -> Tensor:
        """``n`` latents from ``z_a`` to ``z_b`` (endpoints included), [n, *z_a.shape]; ``path`` "linear" or
        "elliptical" (an arc around the origin that visits the clusters between the two ends): see
        :func:`lerobot_pdp.interpolation.interpolate`."""
        return interpolate(z_a, z_b, n, path)

    def encode(self, episode: Episode, segments: list[tuple[int, int]] | str | None = "auto") -> Tensor:
        """z_bar = mu_phi(X(tau)) of a demonstration ([d_z]; [M, d_z] with ``segments``, see ``fit_latent``)."""
        demo = self._demonstration(episode, segments, need_action=False)
        z = self._encode_demo(demo)
        return z if demo.per_phase else z[0]

    def _encode_demo(self, demo: Demonstration) -> Tensor:
        return encode_demonstration(self.model, self.config, demo)

    def fit_latent(self, episode: Episode, steps: int | None = None, init: str | Tensor = "encoder",
                   lr: float | None = None, lam: float | None = None,
                   segments: list[tuple[int, int]] | str | None = "auto", seed: int | None = 0,
                   activate: bool = True, progress: bool = False, objective: str | None = None,
                   noise: str | None = None) -> FitResult:
        """Fit z to one demonstration with every weight frozen (paper Alg. 3 / Eq. 11, Eq. 12 with segments).

        Args:
            episode: dict of unnormalised arrays/tensors as stored in a LeRobotDataset (``observation.*``,
                ``action``; shapes [T, ...]) or a ``(LeRobotDataset | root path, episode_index)`` pair.
            steps: gradient steps S (default ``config.fit_steps``); 0 returns the warm start.
            init: ``"encoder"`` (z0 = mu_phi(X(tau)), the semantic warm start), ``"random"`` (N(0, I)),
                ``"zero"``, or a tensor.
            lr, lam: Adam step size and the weight of lambda |z|^2.
            objective: "denoise" or "sample" (default ``config.fit_objective``, which documents both).
            segments: None (one z), a list of frame ranges, or ``"gripper"`` (split on gripper events of
                ``config.segment_gripper_dim``): one z per phase, used in order during the rollout.
                ``"auto"`` (default): as the policy was trained, i.e. ``"gripper"`` when
                ``config.segment_gripper_dim`` is set, else None.
            activate: make the result the active latent (and its noises, with ``noise="chunks"``, the
                sampler's starting noises of the next episodes, one per new chunk; ``set_latent`` drops them).
            noise: "chunks" or "none" (default ``config.fit_noise``, which documents both): also fit one
                initial sampler noise per executed chunk, z fixed (``FitResult.noise``).

        Returns:
            :class:`FitResult` with ``z`` ([d_z] or [M, d_z]), the initial z and the loss history.
        """
        # Gradients w.r.t. z are needed even when called under torch.inference_mode() / no_grad, e.g. from a
        # live steering request polled inside LeRobot's control loop.
        with torch.inference_mode(False), torch.enable_grad():
            demo = self._demonstration(episode, segments, need_action=True)  # prepare: read, validate, split
            windows = self._demo_windows(demo)
            z0 = initial_latent(self.model, self.config, demo, init, seed)
            result = fit_demonstration(self.model, self.config, demo, windows, z0, steps, lr, lam, seed,  # fit
                                       progress, objective, noise)
        if activate:
            self.steering.activate(result.z, result.noise, fit_provenance(
                episode, result, self.config, steps=steps, init=init, lr=lr, lam=lam, segments=segments, seed=seed,
                objective=objective, noise=noise))
        return result

    def search_latent(self, env_factory: EnvFactory, score: str | Score = "success", budget: int = 200, init: Any = "modes",
                      method: str = "cma", seed: int = 0, rollouts_per_candidate: int = 2, progress: bool = True,
                      activate: bool = True, **options: Any) -> SearchResult:
        """Search z by what rollouts achieve (task success, a reward, way-points passed in order): no
        demonstration needed. ``budget`` rollouts in all, CMA-ES or CEM, deterministic under ``seed``; Ctrl-C
        returns the best so far. See :func:`lerobot_pdp.latent_search.search_latent` for every argument.
        ``activate``: make the best latent the active one (``save_pretrained`` then keeps it, with its search)."""
        result = search_latent(self, env_factory, score, budget=budget, init=init, method=method, seed=seed,
                               rollouts_per_candidate=rollouts_per_candidate, progress=progress, **options)
        if activate:
            self.steering.activate(result.latent, provenance=search_provenance(result))
        return result

    def teach(self, episode: Episode, training_data: str | Path, steps: int = TEACH_STEPS, lr: float = TEACH_LR,
              demo_share: float = TEACH_DEMO_SHARE, seed: int = 0, name: str | None = None,
              progress: bool = False) -> TeachResult:
        """Add one demonstration of a route no latent makes as a new mode (its id: ``result.mode``).

        The encoder stays frozen (every old latent keeps its place) and the new mode's latent is the encoder's
        mean of the demonstration; the denoiser alone is fine-tuned for ``steps`` Adam steps at ``lr``, each batch
        ``demo_share`` demonstration windows and the rest rehearsing the windows of ``training_data`` (the dataset
        the policy was trained on, checked against its behaviour bank). See :mod:`lerobot_pdp.teaching`.
        """
        return teach_new_mode(self, episode, training_data, steps=steps, lr=lr, demo_share=demo_share, seed=seed,
                              name=name, progress=progress)

    def demo_windows(self, episode: Episode, segments: list[tuple[int, int]] | str | None = "auto") -> DemoWindows:
        """The (normalised) training-style windows of one demonstration, each tagged with its phase.

        ``segments`` as in :meth:`fit_latent`; ``windows.n_segments`` phases, ``windows.segment[t]`` the
        phase of the window at frame t. What L_fit is computed on.
        """
        return self._demo_windows(self._demonstration(episode, segments, need_action=True))

    def _demo_windows(self, demo: Demonstration) -> DemoWindows:
        return demonstration_windows(demo, self.config, self.stats, self.model.obs_encoder, self.model.device)

    def _demonstration(self, episode: Episode, segments, need_action: bool) -> Demonstration:
        return read_demonstration(episode, self.config, self.action_dim, segments, need_action)

    def _save_pretrained(self, save_directory: Path, state_dict: dict[str, Tensor] | None = None) -> None:
        """Config + weights written whole (temporary folder, then moved in; weights last)."""
        save_checkpoint(self, save_directory, state_dict)

    def generate_model_card(self, dataset_repo_id: str, model_type: str, license: str | None,
                            tags: list[str] | None, cfg: Any = None, dataset_meta: Any = None):
        """LeRobot's model card plus what PDP is and how to steer it (validated against the Hub only online)."""
        return pdp_model_card(self.config, dataset_repo_id, model_type, license, tags, cfg, dataset_meta)
