"""What PDP's and the MLP-BC baseline's configs share: the LeRobot window layout and optimiser presets."""

from __future__ import annotations

from lerobot.optim.optimizers import AdamConfig
from lerobot.optim.schedulers import CosineAnnealingWithWarmupSchedulerConfig


class ActionChunkConfigMixin:
    """Windows of ``n_obs_steps`` observations and ``horizon`` actions starting at the oldest observation
    (as LeRobot's diffusion policy), Adam, and a multiplicative cosine schedule with warm-up.

    Expects the dataclass fields ``n_obs_steps``, ``horizon``, ``optimizer_*`` and ``scheduler_warmup_steps``.
    """

    @property
    def observation_delta_indices(self) -> list[int]:
        return list(range(1 - self.n_obs_steps, 1))

    @property
    def action_delta_indices(self) -> list[int]:
        return list(range(1 - self.n_obs_steps, 1 - self.n_obs_steps + self.horizon))

    @property
    def reward_delta_indices(self) -> None:
        return None

    def get_optimizer_preset(self) -> AdamConfig:
        # Parameter groups may carry their own "lr" (PDP's embedding vs denoiser); it wins over this one.
        return AdamConfig(
            lr=self.optimizer_lr,
            betas=self.optimizer_betas,
            eps=self.optimizer_eps,
            weight_decay=self.optimizer_weight_decay,
            grad_clip_norm=self.optimizer_grad_clip_norm,
        )

    def get_scheduler_preset(self) -> CosineAnnealingWithWarmupSchedulerConfig:
        # Multiplicative, so each parameter group keeps its own peak learning rate.
        return CosineAnnealingWithWarmupSchedulerConfig(num_warmup_steps=self.scheduler_warmup_steps)
