"""MLP behavior cloning (BC): the plain regression baseline of the PDP benchmark.

``MLPBCPolicy`` maps the flattened, normalised observation history (``observation.state`` and, when
present, ``observation.environment_state`` over ``n_obs_steps`` frames) to a whole normalised action
chunk of ``horizon`` steps, trained by mean-squared error. Acting works like LeRobot's diffusion policy:
observations are queued, a chunk is predicted when the action queue is empty, and ``n_action_steps`` of it
(starting at the current frame) are executed. A unimodal regressor averages the demonstrated modes, which is
exactly the failure mode the benchmark wants to expose; its test-time adaptation is weight fine-tuning
(:func:`lerobot_pdp.benchmark.baselines.finetune_bc`).
"""

from __future__ import annotations

from collections import deque

import torch
import torch.nn.functional as F  # noqa: N812
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.policies.utils import populate_queues
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE
from torch import Tensor, nn

from .configuration_mlp_bc import MLPBCConfig

_ACTIVATIONS = {"relu": nn.ReLU, "gelu": nn.GELU, "mish": nn.Mish}


class MLPBCPolicy(PreTrainedPolicy):
    """Action-chunk MLP regression policy (``--policy.type=mlp_bc``)."""

    config_class = MLPBCConfig
    name = "mlp_bc"

    def __init__(self, config: MLPBCConfig, **kwargs):
        """Build the MLP. ``make_policy`` also passes ``dataset_stats``/``dataset_meta``: normalisation lives
        in the pre/post-processors, so they are accepted and ignored."""
        super().__init__(config)
        config.validate_features()
        self.config = config
        self.state_dim = config.robot_state_feature.shape[0]
        self.env_dim = config.env_state_feature.shape[0] if config.env_state_feature else 0
        self.action_dim = config.action_feature.shape[0]

        in_dim = (self.state_dim + self.env_dim) * config.n_obs_steps
        layers: list[nn.Module] = []
        for width in config.hidden_dims:
            layers += [nn.Linear(in_dim, int(width)), _ACTIVATIONS[config.activation]()]
            if config.dropout > 0:
                layers.append(nn.Dropout(config.dropout))
            in_dim = int(width)
        layers.append(nn.Linear(in_dim, config.horizon * self.action_dim))
        self.mlp = nn.Sequential(*layers)

        self._queues: dict[str, deque] = {}
        self.reset()

    # ------------------------------------------------------------------ LeRobot contract

    def get_optim_params(self):
        return self.parameters()

    def reset(self) -> None:
        """Clear the observation/action queues (call on ``env.reset()``)."""
        self._queues = {
            OBS_STATE: deque(maxlen=self.config.n_obs_steps),
            ACTION: deque(maxlen=self.config.n_action_steps),
        }
        if self.env_dim:
            self._queues[OBS_ENV_STATE] = deque(maxlen=self.config.n_obs_steps)

    def _obs_cond(self, batch: dict[str, Tensor]) -> Tensor:
        """[B, n_obs_steps * (state + env)]: per frame state then env state, frames oldest first."""
        cfg = self.config
        feats = [batch[OBS_STATE]]
        if self.env_dim:
            if OBS_ENV_STATE not in batch:
                raise KeyError(f"batch has no '{OBS_ENV_STATE}' but the policy was built with it")
            feats.append(batch[OBS_ENV_STATE])
        x = torch.cat(feats, dim=-1)
        if x.dim() != 3 or x.shape[1] != cfg.n_obs_steps or x.shape[2] != self.state_dim + self.env_dim:
            raise ValueError(
                f"observations must be [B, {cfg.n_obs_steps}, {self.state_dim}(+{self.env_dim})] per key, "
                f"got '{OBS_STATE}' {tuple(batch[OBS_STATE].shape)}"
            )
        return x.flatten(1)

    def predict_chunk(self, batch: dict[str, Tensor]) -> Tensor:
        """The whole predicted chunk [B, horizon, A] (normalised), with gradients (used by ``forward``)."""
        out = self.mlp(self._obs_cond(batch))
        return out.view(out.shape[0], self.config.horizon, self.action_dim)

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """MSE between the predicted and the demonstrated chunk, ignoring copy-padded steps if configured."""
        if ACTION not in batch:
            raise KeyError(f"batch has no '{ACTION}'; got {sorted(batch)}")
        target = batch[ACTION]
        if tuple(target.shape[1:]) != (self.config.horizon, self.action_dim):
            raise ValueError(
                f"batch['{ACTION}'] has shape {tuple(target.shape)}, "
                f"expected [B, {self.config.horizon}, {self.action_dim}]"
            )
        pred = self.predict_chunk(batch)
        err = F.mse_loss(pred, target, reduction="none")
        if self.config.mask_loss_for_padding and "action_is_pad" in batch:
            mask = (~batch["action_is_pad"].bool()).unsqueeze(-1).to(err.dtype)
            loss = (err * mask).sum() / (mask.sum() * err.shape[-1]).clamp_min(1)
        else:
            loss = err.mean()
        return loss, {"mse": loss.item()}

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """The next ``n_action_steps`` normalised actions [B, n_action_steps, A].

        Uses the queued observation history when ``select_action`` filled it, else ``batch`` as given
        ([B, n_obs_steps, D] per key, e.g. a dataloader batch).
        """
        if len(self._queues[OBS_STATE]) > 0:
            batch = {k: torch.stack(list(self._queues[k]), dim=1) for k in batch if k in self._queues}
        chunk = self.predict_chunk(batch)
        if self.config.clip_actions:
            chunk = chunk.clamp(-1.0, 1.0)
        start = self.config.n_obs_steps - 1
        return chunk[:, start : start + self.config.n_action_steps]

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """One normalised action [B, A] per call; a new chunk is predicted when the queue runs empty."""
        batch = {k: v for k, v in batch.items() if k != ACTION}
        self._queues = populate_queues(self._queues, batch)
        if len(self._queues[ACTION]) == 0:
            actions = self.predict_action_chunk(batch)
            self._queues[ACTION].extend(actions.transpose(0, 1))
        return self._queues[ACTION].popleft()
