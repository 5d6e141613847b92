"""Parameterized Diffusion Policy (PDP): a diffusion policy steered by a geometry-aligned behavior latent z.

The public face is :class:`PDPPolicy`, a LeRobot ``PreTrainedPolicy``:

- training runs inside ``lerobot-train`` (``forward`` returns L_DP + L_embed, see its docstring);
- ``select_action`` / ``predict_action_chunk`` act conditioned on the *active latent*;
- steering: ``encode(episode)``, ``set_latent(z)``, ``mode_latents()``, ``interpolate(z_a, z_b, n)`` and
  ``fit_latent(episode)`` (paper Alg. 3: encoder warm start, then gradient steps on z, weights frozen) and
  ``search_latent(env_factory, score)`` (z searched by what rollouts achieve, without a demonstration).

The networks and the loss live in :class:`~lerobot_pdp.pdp_model.PDPModel`; the training behaviors, their
modes (labelled or discovered) and how far a latent lies from them in
:class:`~lerobot_pdp.behavior_bank.BehaviorBank`; the state a rollout acts under (active latent per phase, chunk
noises, phases) in :class:`~lerobot_pdp.steering_state.Steering`; reading a demonstration in
``demonstration.py``, fitting to it in ``adaptation.py``, steering from the config or a file in ``steering.py``,
the checkpoint on disk in ``checkpoint.py``. This class holds what LeRobot and a user talk to: the training
step, the action queue and the steering API, each method a thin delegator to where its work is documented.
Data flows one way: dataset -> behavior traces -> trajectory encoder -> z -> FiLM denoiser -> actions.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.policies.utils import populate_queues
from lerobot.utils.constants import ACTION
from torch import Tensor

from .adaptation import encode_demonstration, fit_provenance, fit_to_demonstration, warn_unreachable_actions
from .behavior_bank import dataset_behaviors
from .candidate_rollouts import EnvFactory
from .checkpoint import apply_adaptation, flatten_model_keys, load_weights, nest_model_keys, save_checkpoint
from .checkpoint_files import check_checkpoint_source
from .chunk_windows import DemoWindows
from .configuration_pdp import PDPConfig
from .cpu_threads import apply_cpu_threads
from .demonstration import Demonstration, Episode, demonstration_windows, read_demonstration
from .interpolation import interpolate
from .latent_fitting import FitResult
from .latent_search import SearchResult, search_latent, search_provenance
from .model_card import pdp_model_card
from .modes import DiscoveredModes, ModeLatents
from .normalization import FeatureStats
from .observation_encoder import check_camera_resolution, check_observation
from .outcome_scores import Score
from .paced_chunks import is_one_frame, paced_history
from .pdp_model import PDPModel, check_finite_actions, read_loss_terms
from .processor_pdp import CameraFrameCheck, VectorSizeCheck  # noqa: F401  (registered: checkpoints name them)
from .realtime_chunking import prepare_rtc, rtc_chunk
from .steering import apply_config_steering, config_steer_file
from .steering_state import Steering
from .taught_demos import read_taught_demos
from .teaching import TeachResult, TrainingRehearsal, teach_new_mode

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
        self.config = cfg = config
        apply_cpu_threads(cfg.cpu_threads)  # before the behavior bank's soft-DTW and any step
        self.action_dim = cfg.action_feature.shape[0]
        self.stats = FeatureStats(cfg)
        if dataset_stats is not None:
            self.stats.load(dataset_stats)
        check_camera_resolution(cfg, training=dataset_meta is not None)
        behaviors = dataset_behaviors(cfg, dataset_meta)  # read, checked, mode_names (...) set: before any build
        self.model = PDPModel(cfg, self.action_dim, behaviors)
        self.register_state_dict_post_hook(flatten_model_keys)  # the first release's keys ("vae.*", "behavior_traces")
        self.register_load_state_dict_pre_hook(nest_model_keys)
        self.steering = Steering(cfg.latent_dim, cfg)  # what the next chunk is conditioned on: steering_state.py
        self._steer_file = config_steer_file(cfg, training=dataset_meta is not None)  # None: no file
        self._train_steps = 0  # training steps of this process (named when a loss term goes non-finite)
        self.reset()  # the observation/action queues (self._queues), the steering state

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path: str | Path, **kwargs) -> PDPPolicy:
        """LeRobot's loader, then the adaptation an adapted checkpoint carries, then the config's ``steer_*``
        fields, which override it (a fit to a demonstration runs here, before any control loop starts)."""
        check_checkpoint_source(pretrained_name_or_path, need_config=kwargs.get("config") is None)
        policy = super().from_pretrained(pretrained_name_or_path, **kwargs)
        apply_adaptation(policy, pretrained_name_or_path, **kwargs)
        read_taught_demos(policy, pretrained_name_or_path, **kwargs)  # rehearsed if it is taught again
        policy.apply_config_steering(training=kwargs.get("dataset_meta") is not None)  # not in lerobot-train
        return policy

    @classmethod
    def _load_as_safetensor(cls, model: PDPPolicy, model_file: str, map_location: str, strict: bool):
        """LeRobot's load, inside PDP's checks and resizing (:func:`lerobot_pdp.checkpoint.load_weights`)."""
        load = super()._load_as_safetensor
        return load_weights(model, model_file, lambda m: load(m, model_file, map_location, strict))

    def _save_pretrained(self, save_directory: Path, state_dict: dict[str, Tensor] | None = None) -> None:
        """Config + weights written whole (temporary folder, then moved in; weights last)."""
        save_checkpoint(self, save_directory, state_dict)

    def generate_model_card(self, dataset_repo_id: str, model_type: str, license: str | None,
                            tags: list[str] | None, cfg: Any = None, dataset_meta: Any = None):
        """LeRobot's model card plus what PDP is and how to steer it (validated against the Hub only online)."""
        return pdp_model_card(self.config, dataset_repo_id, model_type, license, tags, cfg, dataset_meta)

    # The steering state, as the first release exposed it.
    @property
    def active_latent(self) -> Tensor:
        """The active latent(s) [M, d_z] (empty: the default latent); M > 1 = one per phase."""
        return self.steering.latent

    @property
    def active_noise(self) -> Tensor:
        """Sampler noises fitted with ``noise="chunks"`` [C, horizon, A], one per new chunk, in order."""
        return self.steering.noises.noise

    phases = property(lambda self: self.steering.phases, lambda self, t: setattr(self.steering, "phases", t))  # per env

    # ------------------------------------------------------------------ LeRobot contract

    def get_optim_params(self) -> list[dict]:
        """Two parameter groups, each with its learning rate: embedding (phi, psi) and denoiser (theta)."""
        return self.model.optim_groups()

    def reset(self) -> None:
        """Clear the observation/action queues and restart the latent-phase sequence (call on env.reset())."""
        self._queues = {k: deque(maxlen=self.config.n_obs_steps) for k in self.config.condition_features}
        self._queues[ACTION] = deque(maxlen=self.config.n_action_steps)
        self.steering.reset()

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """One joint training step, ``L = L_DP(theta; sg(mu_phi(tau))) + L_embed(phi, psi)``: the paper's Algorithm 1
        (why one summed loss is it: :meth:`lerobot_pdp.pdp_model.PDPModel.loss_terms`). Refuses non-finite terms."""
        loss, metrics = self.model.loss_terms(batch)
        self._train_steps += int(self.training)  # named when a loss term goes non-finite
        return loss, read_loss_terms(metrics, self._train_steps if self.training else None)

    # ------------------------------------------------------------------ acting

    @torch.no_grad()
    def generate(self, obs_cond: Tensor, z: Tensor, noise: Tensor | None = None,
                 generator: torch.Generator | None = None, guide: Callable[[Tensor], Tensor] | None = None) -> Tensor:
        """Denoise chunks [B, horizon, A] (normalised) for ``obs_cond`` [B, C], ``z`` [B, d_z]; ``guide``: an x0 edit."""
        return self.model.generate(obs_cond, z, noise, generator, guide=guide)

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], noise: Tensor | None = None, **kwargs) -> Tensor:
        """The next ``n_action_steps`` normalised actions [B, n_action_steps, A] under the active latent, from a history
        [B, n_obs_steps, *frame] or one frame joining the policy's own (paced_chunks.py; RTC: :func:`rtc_chunk`)."""
        if "inference_delay" in kwargs or "prev_chunk_left_over" in kwargs:
            return rtc_chunk(self, batch, noise=noise, **kwargs)
        one_frame = is_one_frame(batch, self.config.condition_features)
        batch = paced_history(self, batch) if one_frame else batch
        if self._steer_file is not None:  # live steering: a changed file sets z before this chunk
            self._steer_file.poll(self)
        obs_cond = self.model.acting_cond(batch)  # a history of another length or a NaN reading: named
        z = self.current_latent(obs_cond.shape[0], obs_cond.device)
        last = getattr(self, "_paced_last", None) if one_frame else None  # served: paced_chunks.LastChunk
        if last is None and noise is None:  # fitted noises: the next one, the last one repeating (None: drawn)
            noise = self.steering.next_noise(obs_cond.shape[0], obs_cond.device)
        chunk = self.generate(obs_cond, z, noise=noise) if last is None else last.sample(self, obs_cond, z, noise)
        check_finite_actions(chunk, z)  # a robot must never be sent NaN
        start = self.config.n_obs_steps - 1
        return chunk[:, start : start + self.config.n_action_steps]

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], noise: Tensor | None = None, **kwargs) -> Tensor:
        """One normalised action [B, A] per call; a new chunk is generated when the queue runs empty."""
        batch = {k: v for k, v in batch.items() if k != ACTION}
        self._queues = queue_observation(self._queues, batch, self.config.condition_features)  # checked first
        if len(self._queues[ACTION]) == 0:
            history = {k: torch.stack(list(self._queues[k]), dim=1) for k in self.config.condition_features}
            actions = self.predict_action_chunk(history, noise=noise)
            self._queues[ACTION].extend(actions.transpose(0, 1))
        action = self._queues[ACTION].popleft()
        self._advance_phase(action)
        return action

    def supports_rtc(self) -> bool:  # lerobot-rollout --inference.type=rtc: lerobot_pdp/realtime_chunking.py
        return True

    init_rtc_processor = prepare_rtc  # lerobot-rollout calls it once config.rtc_config is set

    def _advance_phase(self, action: Tensor, replan: bool = True) -> None:
        """Count each env's gripper flips in ``action`` [B, A] (phases.py); a switch replans if ``replan`` (not RTC)."""
        cfg = self.config
        if cfg.segment_gripper_dim is None:
            return
        closed = self.stats.normalized_value(ACTION, cfg.segment_gripper_dim, cfg.segment_gripper_threshold)
        if self.steering.observe(action[:, cfg.segment_gripper_dim] > closed, cfg.phase_switch_steps) and replan:
            self._queues[ACTION].clear()  # the envs that did not switch just replan early

    def current_latent(self, batch_size: int = 1, device: torch.device | str | None = None) -> Tensor:
        """The latent the next chunk is conditioned on, [batch_size, d_z] (each env's own phase latent; nothing
        active: ``config.inference_latent``, drawn once per episode). Never fits."""
        bank, vae = self.model.bank, self.model.vae
        return self.steering.latent_for(batch_size, device or self.model.device, lambda n: bank.default_latents(vae, n))

    # ------------------------------------------------------------------ steering API (docs/deploy.md)

    def set_latent(self, z: Tensor | Sequence[float] | np.ndarray | None) -> None:
        """Make ``z`` ([d_z], or [M, d_z] = one latent per phase) the active latent; None = back to default.
        Noises fitted under another latent no longer apply. A latent far outside the training latents is
        accepted with one warning (see :meth:`latent_outlier`): the policy never saw it condition an action."""
        self.steering.activate(self.model.checked_latent(z))
        if z is not None:
            self.model.bank.warn_if_far(self.model.vae, self.steering.latent)

    def latent_outlier(self, z: Tensor) -> tuple[float, float] | None:  # (distance in spreads, spread) or None
        """When a row of ``z`` lies far from every training latent: :meth:`BehaviorBank.outlier`."""
        return self.model.bank.outlier(self.model.vae, z)

    def apply_config_steering(self, training: bool = False) -> None:
        """Apply the config's ``steer_*`` fields (how ``lerobot-eval`` / ``lerobot-rollout`` steer a checkpoint;
        :meth:`from_pretrained` calls it): :func:`lerobot_pdp.steering.apply_config_steering`."""
        apply_config_steering(self, training)

    def mode_latents(self, k: int | None = None) -> ModeLatents:
        """Per-mode mean latent (one per phase for segmented policies); without mode labels, the ``k`` (None: found)
        discovered modes with a warning. See :meth:`lerobot_pdp.behavior_bank.BehaviorBank.mode_latents`."""
        return self.model.bank.mode_latents(self.model.vae, k)

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
        "elliptical": :func:`lerobot_pdp.interpolation.interpolate`."""
        return interpolate(z_a, z_b, n, path)

    def encode(self, episode: Episode, segments: list[tuple[int, int]] | str | None = "auto") -> Tensor:
        """z_bar = mu_phi(X(tau)) of a demonstration ([d_z]; [M, d_z] with ``segments``, see ``fit_latent``)."""
        demo = self._demonstration(episode, segments, need_action=False)
        z = encode_demonstration(self.model, self.config, demo)
        return z if demo.per_phase else z[0]

    def fit_latent(self, episode: Episode, steps: int | None = None, init: str | Tensor = "encoder",
                   lr: float | None = None, lam: float | None = None,
                   segments: list[tuple[int, int]] | str | None = "auto", seed: int | None = 0,
                   activate: bool = True, progress: bool = False, objective: str | None = None,
                   noise: str | None = None, optimizer: str | None = None) -> FitResult:
        """Fit z to one demonstration with every weight frozen (paper Alg. 3 / Eq. 11, Eq. 12 per segment);
        ``activate``: act under the result. ``episode``, ``segments``: :func:`lerobot_pdp.demonstration.read_demonstration`;
        the other arguments: :func:`lerobot_pdp.adaptation.fit_to_demonstration`."""
        with torch.inference_mode(False), torch.enable_grad():  # z's gradients, also in LeRobot's inference_mode loop
            demo = self._demonstration(episode, segments, need_action=True, acting=activate)  # read, validate, split
            warn_unreachable_actions(self.config, self.stats, demo)  # actions past the sampler's clip: named
            result = fit_to_demonstration(self.model, self.config, demo, self._demo_windows(demo), init=init,  # fit
                                          steps=steps, lr=lr, lam=lam, seed=seed, progress=progress,
                                          objective=objective, noise=noise, optimizer=optimizer)
        result.provenance = fit_provenance(  # where it came from (an adapted checkpoint saves it)
            episode, result, self.config, steps=steps, init=init, lr=lr, lam=lam, segments=segments, seed=seed,
            objective=objective, noise=noise, optimizer=optimizer)
        if activate:
            self.steering.activate(result.z, result.noise, result.provenance)
        return result

    def search_latent(self, env_factory: EnvFactory, score: str | Score = "success", budget: int = 200, init: Any = "modes",
                      method: str = "cma", seed: int = 0, rollouts_per_candidate: int = 2, progress: bool = True,
                      activate: bool = True, **options: Any) -> SearchResult:
        """Search z by what rollouts achieve, no demonstration needed (CMA-ES / CEM within ``budget`` rollouts);
        ``activate``: act under the best. Every argument: :func:`lerobot_pdp.latent_search.search_latent`."""
        result = search_latent(self, env_factory, score, budget=budget, init=init, method=method, seed=seed,
                               rollouts_per_candidate=rollouts_per_candidate, progress=progress, **options)
        if activate:
            self.steering.activate(result.latent, provenance=search_provenance(result))
        return result

    def teach(self, episode: Episode, training_data: str | Path | TrainingRehearsal, **settings: Any) -> TeachResult:
        """Add one demonstration of a route no latent makes as a new mode (``result.mode``), rehearsing ``training_data``
        (the policy's training dataset); ``settings``: :func:`lerobot_pdp.teaching.teach_new_mode`."""
        return teach_new_mode(self, episode, training_data, **settings)

    def demo_windows(self, episode: Episode, segments: list[tuple[int, int]] | str | None = "auto") -> DemoWindows:
        """The (normalised) training-style windows of one demonstration, each tagged with its phase, what L_fit
        is computed on; ``segments``: :func:`lerobot_pdp.demonstration.read_demonstration`."""
        return self._demo_windows(self._demonstration(episode, segments, need_action=True))

    def _demo_windows(self, demo: Demonstration) -> DemoWindows:
        return demonstration_windows(demo, self.config, self.stats, self.model.obs_encoder, self.model.device)

    def _demonstration(self, episode: Episode, segments, need_action: bool, acting: bool = False) -> Demonstration:
        return read_demonstration(episode, self.config, self.action_dim, segments, need_action, acting)


def queue_observation(queues: dict[str, deque], batch: dict[str, Tensor], features: dict) -> dict[str, deque]:
    """``select_action``'s queues with ``batch``'s observation: a key, size or type the policy was not trained on is
    named first, and so is a batch of another size than the actions still queued (they would be returned for it)."""
    check_observation(batch, features, ("B",))
    queued, first = queues[ACTION], next(iter(features))
    if queued and len(queued[0]) != len(batch[first]):
        raise ValueError(f"a batch of {len(batch[first])} observation(s) while actions for a batch of {len(queued[0])} "
                         "are still queued: call policy.reset() when the number of envs changes (as at a new episode)")
    return populate_queues(queues, batch)
