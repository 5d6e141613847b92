"""The benchmark's baselines and their test-time adaptation (paper appendix, "Policy Training and Baseline
Configurations", Table "baseline_compare").

- **DP** = LeRobot's own ``diffusion`` policy, configured like PDP's denoiser (:func:`dp_config_matching`),
  adapted to one new demonstration by *noise-space adaptation* (:func:`adapt_dp_noise`): the weights stay
  frozen and one initial noise tensor x_K is optimised so that deterministic DDIM generation from it
  reproduces the demonstration; rollouts then always start from that x_K (:class:`FixedNoisePolicy`).
- **BC** = ``mlp_bc`` (:mod:`lerobot_pdp.baselines`), adapted by fine-tuning all its weights on the
  demonstration with a small learning rate (:func:`finetune_bc`).
- **VQ-BeT** (camera variant only) = LeRobot's own ``vqbet``, adapted like BC by fine-tuning (its residual
  codebook takes no gradient: its codes stay the ones training learned).

Everything here takes a LeRobot policy plus its *preprocessor* and a raw demonstration, so the demo is
normalised with exactly the statistics the policy was trained with (the preprocessor's own normaliser
step) and cut into exactly the windows LeRobotDataset yields in training
(:func:`lerobot_pdp.chunk_windows.window_indices`). Nothing assumes PDP internals: any policy whose
config uses LeRobot's standard ``n_obs_steps`` / ``horizon`` delta indices and whose ``forward`` takes the
standard batch (``observation.state``, ``observation.environment_state``, ``action``, ``action_is_pad``)
works with :func:`demo_batch` and :func:`finetune_bc`; :func:`adapt_dp_noise` needs LeRobot's
``DiffusionPolicy`` layout (``policy.diffusion.conditional_sample``).
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Mapping, Sequence
from dataclasses import MISSING, asdict, fields, is_dataclass
from typing import Any

import numpy as np
import torch
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_IMAGES, OBS_STATE
from torch import Tensor, nn

from ..chunk_windows import window_indices
from ..configuration_pdp import PDPConfig, linear_beta_end
from ..steering_state import ChunkNoises

logger = logging.getLogger(__name__)

# LeRobot `diffusion` fields that must equal PDP's so that DP differs from PDP only by the behavior latent.
# Values are PDPConfig's defaults, read from the dataclass so that they cannot drift from it (LeRobot DP's own
# do_mask_loss_for_padding default is False, PDP's True); a `pdp_like` mapping overrides any of them.
DP_MATCHED_FIELDS = ("down_dims", "kernel_size", "n_groups", "diffusion_step_embed_dim", "horizon", "n_obs_steps",
                     "n_action_steps", "drop_n_last_frames", "do_mask_loss_for_padding", "num_train_timesteps",
                     "num_inference_steps", "beta_schedule", "beta_start", "beta_end", "clip_sample",
                     "clip_sample_range", "optimizer_lr", "scheduler_warmup_steps")
DP_MATCHING_DEFAULTS: dict[str, Any] = {f.name: f.default if f.default is not MISSING else f.default_factory()
                                        for f in fields(PDPConfig) if f.name in DP_MATCHED_FIELDS}
# Fixed for DP whatever PDP uses: deterministic DDIM (noise-space adaptation needs a deterministic map
# x_K -> actions).
DP_FIXED: dict[str, Any] = {"noise_scheduler_type": "DDIM"}


def dp_config_kwargs(pdp_like: Mapping[str, Any] | Any | None = None) -> dict[str, Any]:
    """Keyword arguments for LeRobot's ``DiffusionConfig`` matching PDP's backbone, windows and sampler.

    ``pdp_like``: a mapping (or a ``PDPConfig``) whose keys among :data:`DP_MATCHING_DEFAULTS` override
    the defaults; other keys are ignored, so ``asdict(pdp_config)`` can be passed as is.
    """
    if pdp_like is None:
        pdp_like = {}
    elif is_dataclass(pdp_like) and not isinstance(pdp_like, type):
        pdp_like = asdict(pdp_like)
    out = {k: pdp_like.get(k, v) for k, v in DP_MATCHING_DEFAULTS.items()}
    out["down_dims"] = tuple(int(d) for d in out["down_dims"])
    if out["beta_schedule"] != "linear":  # the betas play no part: DP's command line stays as it was before them
        del out["beta_start"], out["beta_end"]
    else:  # a legacy "linear" PDP checkpoint's beta_end None: its scaled end
        out["beta_end"] = linear_beta_end(out["beta_end"], out["num_train_timesteps"])
    out.update(DP_FIXED)
    return out


def _cli_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(_cli_value(x) for x in v) + "]"
    return str(v)


def dp_config_matching(pdp_like: Mapping[str, Any] | Any | None = None) -> list[str]:
    """``lerobot-train --policy.type=diffusion`` overrides that give DP PDP's backbone and sampler.

    Same 1-D U-Net (down_dims, kernel, groups, step-embedding width), same windows (horizon 16,
    2 observation frames, 8 executed actions), same K = 20 training steps and deterministic DDIM
    inference steps (PDP's num_inference_steps), same padding treatment and learning rate: the fair baseline the benchmark notes ask for
    (LeRobot's default DP has 248 M parameters and 100 DDPM steps, ~23 s per chunk on our CPUs).
    Returns e.g. ``["--policy.down_dims=[32,64,128]", "--policy.horizon=16", ...]``.
    """
    return [f"--policy.{k}={_cli_value(v)}" for k, v in dp_config_kwargs(pdp_like).items()]


# ----------------------------------------------------------------------------- demonstration windows


def _normalizer_step(preprocessor):
    from lerobot.processor import NormalizerProcessorStep

    steps = [s for s in getattr(preprocessor, "steps", []) if isinstance(s, NormalizerProcessorStep)]
    if not steps:
        raise ValueError("the preprocessor has no NormalizerProcessorStep; pass the policy's own preprocessor "
                         "(make_pre_post_processors / policy_preprocessor.json)")
    return steps[-1]


def normalize_episode(preprocessor, episode: Mapping[str, Any]) -> dict[str, Tensor]:
    """Normalise raw episode arrays [T, D] with the preprocessor's own normaliser step (same statistics
    and maths as at training and rollout time)."""
    from lerobot.processor import TransitionKey, create_transition

    step = _normalizer_step(preprocessor)
    obs = {k: torch.as_tensor(np.asarray(v), dtype=torch.float32) for k, v in episode.items()
           if k.startswith("observation.") and isinstance(v, (np.ndarray, Tensor))}
    action = torch.as_tensor(np.asarray(episode[ACTION]), dtype=torch.float32)
    tr = step(create_transition(observation=obs, action=action))
    out = {k: v.float().cpu() for k, v in tr[TransitionKey.OBSERVATION].items()}
    out[ACTION] = tr[TransitionKey.ACTION].float().cpu()
    return out


def demo_batch(policy, preprocessor, episode: Mapping[str, Any]) -> dict[str, Tensor]:
    """Every training-style window of one raw demonstration as one normalised LeRobot batch.

    Window at frame t: observations t-n_obs+1..t, actions t-n_obs+1..t-n_obs+horizon, indices clamped
    to the episode, ``action_is_pad`` where they were clamped: what LeRobotDataset yields with the
    policy's delta indices. Keys: ``observation.state`` [N, n_obs, S], ``observation.environment_state``
    [N, n_obs, E] (if the policy uses it), each camera [N, n_obs, 3, H, W] (if the policy has cameras),
    ``action`` [N, horizon, A], ``action_is_pad`` [N, horizon].
    """
    cfg = policy.config
    # horizon = the action window's length (VQ-BeT has no horizon field: its tokens x chunk size set it)
    n_obs, horizon = int(cfg.n_obs_steps), len(cfg.action_delta_indices)
    if list(cfg.observation_delta_indices) != list(range(1 - n_obs, 1)) or list(cfg.action_delta_indices) != list(
        range(1 - n_obs, 1 - n_obs + horizon)
    ):
        raise ValueError(f"{type(cfg).__name__} does not use the standard n_obs_steps/horizon windows")
    cameras = tuple(getattr(cfg, "image_features", {}) or {})
    for key in (OBS_STATE, ACTION) + ((OBS_ENV_STATE,) if cfg.env_state_feature is not None else ()) + cameras:
        if key not in episode:
            raise KeyError(f"episode has no '{key}'; keys are {sorted(episode)}")
    norm = normalize_episode(preprocessor, episode)
    T = norm[OBS_STATE].shape[0]
    if any(norm[k].shape[0] != T for k in norm):
        raise ValueError(f"episode keys have different lengths { {k: tuple(v.shape) for k, v in norm.items()} }")
    obs_idx, act_idx, is_pad = window_indices(T, n_obs, horizon)
    batch = {ACTION: norm[ACTION][act_idx], "action_is_pad": is_pad}
    for key in (OBS_STATE,) + ((OBS_ENV_STATE,) if cfg.env_state_feature is not None else ()) + cameras:
        batch[key] = norm[key][obs_idx]
    device = _device(policy)
    return {k: v.to(device) for k, v in batch.items()}


def _device(module: nn.Module) -> torch.device:
    p = next(module.parameters(), None)
    return p.device if p is not None else torch.device("cpu")


def _subset(batch: dict[str, Tensor], idx: Tensor) -> dict[str, Tensor]:
    return {k: v[idx.to(v.device)] for k, v in batch.items()}


def _minibatch(n: int, batch_size: int, g: torch.Generator) -> Tensor:
    return torch.randperm(n, generator=g)[: min(batch_size, n)]


# ----------------------------------------------------------------------------- DP: noise-space adaptation


def _loss_pad(policy, batch: Mapping[str, Tensor]) -> Tensor:
    """Chunk steps to leave out of the matching loss: the padded ones only if DP was trained that way."""
    is_pad = batch["action_is_pad"].bool()
    return is_pad if policy.config.do_mask_loss_for_padding else torch.zeros_like(is_pad)


def _masked_mse(pred: Tensor, target: Tensor, is_pad: Tensor) -> Tensor:
    mask = (~is_pad.bool()).unsqueeze(-1).to(pred.dtype)
    return ((pred - target).pow(2) * mask).sum() / (mask.sum() * pred.shape[-1]).clamp_min(1)


def _dp_generate(policy, global_cond: Tensor, noise: Tensor) -> Tensor:
    """DP's own sampling routine (``DiffusionModel.conditional_sample``), with autograd left on."""
    return policy.diffusion.conditional_sample(global_cond.shape[0], global_cond=global_cond,
                                               noise=noise.expand(global_cond.shape[0], -1, -1))


def _check_dp(policy) -> None:
    if not hasattr(policy, "diffusion") or not hasattr(policy.diffusion, "conditional_sample"):
        raise TypeError(f"noise-space adaptation needs LeRobot's DiffusionPolicy, got {type(policy).__name__}")
    if type(policy.diffusion.noise_scheduler).__name__ != "DDIMScheduler":
        logger.warning("DP uses %s: its sampler adds fresh noise at every step, so x_K does not determine the "
                       "actions; noise-space adaptation is meant for DDIM (dp_config_matching)",
                       type(policy.diffusion.noise_scheduler).__name__)


def _stack_cameras(policy, batch: dict[str, Tensor]) -> dict[str, Tensor]:
    """DP's own camera layout: every camera's history stacked under ``observation.images`` [N, n_obs, n_cam, ...]
    (what ``DiffusionPolicy.forward`` builds before ``_prepare_global_conditioning``)."""
    cameras = list(policy.config.image_features)
    if cameras:
        batch = {**batch, OBS_IMAGES: torch.stack([batch[k] for k in cameras], dim=-4)}
    return batch


def dp_noise_matching_loss(policy, preprocessor, episode: Mapping[str, Any], noise: Tensor) -> float:
    """MSE between DP's generation from ``noise`` and the demo's normalised action chunks, over
    ALL windows of ``episode`` (the objective :func:`adapt_dp_noise` minimises on minibatches)."""
    _check_dp(policy)
    batch = _stack_cameras(policy, demo_batch(policy, preprocessor, episode))
    with torch.no_grad():
        cond = policy.diffusion._prepare_global_conditioning(batch)
        pred = _dp_generate(policy, cond, noise.to(cond.device, cond.dtype))
        return float(_masked_mse(pred, batch[ACTION], _loss_pad(policy, batch)))


def adapt_dp_noise(policy, preprocessor, episode: dict[str, np.ndarray], steps: int = 100, lr: float = 0.05,
                   batch_size: int = 32, seed: int = 0, per_chunk: bool = False) -> Tensor:
    """Noise-space adaptation of a LeRobot ``diffusion`` policy to ONE demonstration (weights frozen).

    Optimises a single initial noise x_K [1, horizon, A] with Adam so that the deterministic DDIM chain
    started from x_K, conditioned on each demo window's observation history, reproduces that window's
    normalised action chunk (MSE; copy-padded steps past the episode end masked out only if DP was
    trained with ``do_mask_loss_for_padding``). Each step uses a
    random minibatch of ``batch_size`` windows. Gradients flow through DP's own sampler
    (``policy.diffusion.conditional_sample``; ``predict_action_chunk`` is ``no_grad``) and are taken with
    ``torch.autograd.grad`` w.r.t. x_K only, so no parameter and no ``.grad`` of the policy changes.

    Why one shared x_K: it is the only input DP has besides observations, the paper's DP adaptation
    ("optimize denoising noise seed at test time"). Roll it out with :class:`FixedNoisePolicy`.

    ``per_chunk``: one x_K per executed chunk of the demonstration instead (chunk j fitted on the windows
    starting at its n_action_steps frames), played in order during the rollout (the last one repeats):
    a noise *sequence*, as free as DP's input allows.

    Args:
        episode: raw (unnormalised) arrays [T, ...]: ``observation.state``, ``observation.environment_state``,
            ``action`` (e.g. ``read_episodes(root, keys, [i])[i]``).
    Returns:
        The optimised x_K, [1, horizon, action_dim] ([C, horizon, action_dim] with ``per_chunk``), detached,
        on the policy's device.
    """
    _check_dp(policy)
    cfg = policy.config
    batch = _stack_cameras(policy, demo_batch(policy, preprocessor, episode))
    model = policy.diffusion
    was_training = model.training
    model.eval()  # cameras: the centre crop, as when acting
    with torch.no_grad():
        cond_all = model._prepare_global_conditioning(batch)
    model.train(was_training)
    is_pad = _loss_pad(policy, batch)
    n = cond_all.shape[0]
    g = torch.Generator().manual_seed(int(seed))
    chunk_of = torch.arange(n) // cfg.n_action_steps if per_chunk else torch.zeros(n, dtype=torch.long)
    x = torch.randn(int(chunk_of.max()) + 1, cfg.horizon, cfg.action_feature.shape[0], generator=g)
    x = x.to(cond_all.device, cond_all.dtype).requires_grad_(True)
    chunk_of = chunk_of.to(cond_all.device)
    opt = torch.optim.Adam([x], lr=lr)
    params = list(model.parameters())
    flags = [p.requires_grad for p in params]
    was_training = model.training
    try:
        for p in params:  # frozen: also spares autograd the weight gradients
            p.requires_grad_(False)
        model.eval()
        for _ in range(int(steps)):
            idx = _minibatch(n, batch_size, g).to(cond_all.device)
            pred = _dp_generate(policy, cond_all[idx], x[chunk_of[idx]])
            loss = _masked_mse(pred, batch[ACTION][idx], is_pad[idx])
            (grad,) = torch.autograd.grad(loss, x)
            x.grad = grad
            opt.step()
    finally:
        for p, f in zip(params, flags, strict=True):
            p.requires_grad_(f)
        model.train(was_training)
    return x.detach()


class FixedNoisePolicy(nn.Module):
    """A DP that always starts its sampler from the same (adapted) noise x_K.

    ``select_action(batch)`` calls the wrapped policy's ``select_action(batch, noise=x_K expanded to the
    batch)``, so the action queue, observation history and postprocessing are DP's own. An ``nn.Module``
    because LeRobot's ``rollout`` asserts one; any other attribute (``config``, ``predict_action_chunk``,
    ...) is the wrapped policy's.
    """

    def __init__(self, policy: nn.Module, noise: Tensor):
        super().__init__()
        self.policy = policy
        noise = torch.as_tensor(noise).detach().float()
        if noise.dim() == 2:
            noise = noise[None]
        if noise.dim() != 3:
            raise ValueError(f"noise must have shape [C, horizon, action_dim] (C = 1, or one per chunk), "
                             f"got {tuple(noise.shape)}")
        self.noises = ChunkNoises(noise.to(_device(policy)))  # played as PDP plays its fitted chunk noises

    def _noise_for(self, batch: Mapping[str, Tensor], advance: bool) -> Tensor:
        b = batch[OBS_STATE].shape[0] if batch[OBS_STATE].dim() > 1 else 1
        return self.noises.next(b, self.noises.noise.device, advance=advance)

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        # DP generates a chunk only when its action queue is empty (vectorised envs step in lockstep)
        new_chunk = len(self.policy._queues[ACTION]) == 0
        return self.policy.select_action(batch, noise=self._noise_for(batch, advance=new_chunk))

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        return self.policy.predict_action_chunk(batch, noise=self._noise_for(batch, advance=True))

    def reset(self) -> None:
        self.noises.reset()
        self.policy.reset()

    def __getattr__(self, name: str):
        try:
            return super().__getattr__(name)
        except AttributeError:
            return getattr(super().__getattr__("policy"), name)


class PerEnvNoisePolicy(FixedNoisePolicy):
    """A DP where env b of a vectorised rollout starts every chunk's sampler from its own noise ``noises[b]``
    ([B, horizon, action_dim]): a population of candidate noises rolled out in one batch, as
    :class:`~lerobot_pdp.candidate_rollouts.PerEnvLatents` rolls out PDP's candidate latents (a search over DP's
    noise, ``benchmark/search_curves.py``). Everything else is :class:`FixedNoisePolicy`'s."""

    def __init__(self, policy: nn.Module, noises: Tensor):
        noises = torch.as_tensor(noises).detach().float()
        if noises.dim() != 3:
            raise ValueError(f"noises must have shape [B, horizon, action_dim] (one per env), got {tuple(noises.shape)}")
        super().__init__(policy, noises[:1])
        self.register_buffer("per_env", noises.to(_device(policy)), persistent=False)

    def _noise_for(self, batch: Mapping[str, Tensor], advance: bool) -> Tensor:
        b = batch[OBS_STATE].shape[0] if batch[OBS_STATE].dim() > 1 else 1
        if b != len(self.per_env):
            raise RuntimeError(f"rollout batch of {b} envs for {len(self.per_env)} candidate noises")
        return self.per_env


# ----------------------------------------------------------------------------- BC: weight fine-tuning


def finetune_bc(policy, preprocessor, episode: dict[str, np.ndarray], steps: int = 100, lr: float = 1e-5,
                batch_size: int = 32, seed: int = 0):
    """A deep copy of ``policy`` with all its trainable weights fine-tuned on one demonstration (paper: BC adapts by
    "fine-tune policy weights with small learning rate"); the original is untouched.

    Adam at ``lr`` on the policy's own training loss (``policy.forward``) over random minibatches of the
    demo's windows (:func:`demo_batch`), gradient norm clipped like in training. Works for any LeRobot
    policy with the standard batch layout (``mlp_bc``; ``vqbet`` on the camera variant). Any randomness
    inside ``forward`` is seeded by ``seed`` without disturbing the global RNG. Returns the copy in eval
    mode, queues reset.
    """
    return finetune_with_rehearsal(policy, preprocessor, episode, (), steps, lr, batch_size, 1.0, seed)


def finetune_with_rehearsal(policy, preprocessor, episode: Mapping[str, Any], rehearsal: Sequence[Mapping[str, Any]],
                            steps: int, lr: float, batch_size: int, demo_share: float, seed: int = 0):
    """A deep copy of ``policy`` with all its trainable weights fine-tuned on one demonstration, each batch
    ``demo_share`` of its windows and the rest windows of the ``rehearsal`` episodes (the training data, raw
    arrays): how a policy without a latent is taught a new route without dropping its old ones. The same
    loss, optimizer and clipping as :func:`finetune_bc` (``demo_share=1`` and no rehearsal is it)."""
    tuned = copy.deepcopy(policy)
    batch = demo_batch(tuned, preprocessor, episode)
    n = batch[ACTION].shape[0]
    old = [demo_batch(tuned, preprocessor, ep) for ep in rehearsal]
    old_batch = {k: torch.cat([b[k] for b in old]) for k in batch} if old else None
    n_demo = batch_size if old_batch is None else max(1, round(demo_share * batch_size))
    params = [p for p in tuned.parameters() if p.requires_grad]
    opt = torch.optim.Adam(params, lr=lr)
    clip = float(getattr(tuned.config, "optimizer_grad_clip_norm", 10.0) or 0.0)
    g = torch.Generator().manual_seed(int(seed))
    tuned.train()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        for _ in range(int(steps)):
            step_batch = _subset(batch, _minibatch(n, n_demo, g))
            if old_batch is not None and n_demo < batch_size:
                n_old = len(old_batch[ACTION])
                extra = _subset(old_batch, torch.randint(0, n_old, (batch_size - n_demo,), generator=g))
                step_batch = {k: torch.cat([step_batch[k], extra[k]]) for k in step_batch}
            loss, _ = tuned.forward(step_batch)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if clip > 0:
                torch.nn.utils.clip_grad_norm_(params, clip)
            opt.step()
    tuned.eval()
    tuned.reset()
    return tuned
