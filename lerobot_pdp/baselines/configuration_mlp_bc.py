"""Configuration of the MLP behavior-cloning baseline, registered with LeRobot as ``--policy.type=mlp_bc``.

The baseline is deliberately plain: one MLP maps the flattened, normalised observation history to a whole
action chunk and is trained by mean-squared error. It shares PDP's observation/action windows
(``n_obs_steps``, ``horizon``, ``n_action_steps``), normalisation and optimiser defaults, and its default
hidden sizes give about as many parameters as PDP's default denoiser (~1.2 M), so differences in the
benchmark come from the objective (regression vs. diffusion + behavior latent), not from capacity.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_pdp.chunk_config import ActionChunkConfigMixin

ACTIVATIONS = ("relu", "gelu", "mish")


@PreTrainedConfig.register_subclass("mlp_bc")
@dataclass
class MLPBCConfig(ActionChunkConfigMixin, PreTrainedConfig):
    """Configuration for :class:`~lerobot_pdp.baselines.modeling_mlp_bc.MLPBCPolicy`.

    Inputs: ``observation.state`` (required) and ``observation.environment_state`` (optional, used when
    the dataset has it); output: ``action``. No images.
    """

    # ---- Inputs / outputs (same windows as PDP and LeRobot's diffusion policy) ----
    # Observation frames the MLP sees: the current one and n_obs_steps - 1 before it, flattened.
    n_obs_steps: int = 2
    # Length of the predicted action chunk, counted from the oldest observation frame (as in DP/PDP).
    horizon: int = 16
    # Actions executed from each chunk before a new one is predicted (receding horizon).
    n_action_steps: int = 8
    # Training windows whose action chunk would mostly run past the episode end are not sampled.
    drop_n_last_frames: int = 7
    # Same mapping as PDP: min-max to [-1, 1] for robot state, environment state and actions.
    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "STATE": NormalizationMode.MIN_MAX,
            "ENV": NormalizationMode.MIN_MAX,
            "ACTION": NormalizationMode.MIN_MAX,
        }
    )

    # ---- Network ----
    # Hidden layer widths. (768, 768, 768) has ~1.24 M parameters on reach-around (24 inputs, 16 x 3
    # outputs), close to PDP's default 1-D U-Net denoiser (~1.22 M).
    hidden_dims: tuple[int, ...] = (768, 768, 768)
    # Nonlinearity after every hidden layer: "relu", "gelu" or "mish".
    activation: str = "relu"
    # Dropout after every hidden activation (0 = none).
    dropout: float = 0.0
    # Clamp predicted (normalised) actions to [-1, 1] at inference: MIN_MAX maps the dataset's action
    # range there, so anything outside is extrapolation beyond every demonstration.
    clip_actions: bool = True
    # Exclude copy-padded action steps (past the episode end) from the MSE, like PDP's diffusion loss.
    mask_loss_for_padding: bool = True

    # ---- Optimisation (same defaults as PDP's denoiser) ----
    optimizer_lr: float = 1e-4
    optimizer_betas: tuple[float, float] = (0.95, 0.999)
    optimizer_eps: float = 1e-8
    optimizer_weight_decay: float = 1e-6
    optimizer_grad_clip_norm: float = 10.0
    # Linear warm-up steps before cosine annealing to zero over the remaining training steps.
    scheduler_warmup_steps: int = 100

    def __post_init__(self):
        super().__post_init__()
        errors = []
        for name in ("n_obs_steps", "horizon", "n_action_steps"):
            if getattr(self, name) < 1:
                errors.append(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.drop_n_last_frames < 0:
            errors.append(f"drop_n_last_frames must be >= 0, got {self.drop_n_last_frames}")
        if not self.hidden_dims or any(int(h) < 1 for h in self.hidden_dims):
            errors.append(f"hidden_dims must be a non-empty list of positive widths, got {self.hidden_dims}")
        if self.activation not in ACTIVATIONS:
            errors.append(f"activation must be one of {ACTIVATIONS}, got {self.activation!r}")
        if not 0.0 <= self.dropout < 1.0:
            errors.append(f"dropout must be in [0, 1), got {self.dropout}")
        if self.n_action_steps > self.horizon - self.n_obs_steps + 1:
            errors.append(
                f"n_action_steps ({self.n_action_steps}) must be <= horizon - n_obs_steps + 1 "
                f"({self.horizon - self.n_obs_steps + 1})"
            )
        if errors:
            raise ValueError("Invalid MLPBCConfig: " + "; ".join(errors))

    def validate_features(self) -> None:
        """Check the input/output features this policy needs; raise naming the key and shape."""
        if self.robot_state_feature is None:
            raise ValueError(
                f"mlp_bc needs '{OBS_STATE}' among the input features; got {sorted(self.input_features)}"
            )
        if self.action_feature is None:
            raise ValueError(
                f"mlp_bc needs '{ACTION}' among the output features; got {sorted(self.output_features)}"
            )
        if self.image_features:
            raise ValueError(
                f"mlp_bc is state-based; image inputs {sorted(self.image_features)} are not supported "
                "(use a state-only dataset)"
            )
        for key, ft in [(OBS_STATE, self.robot_state_feature), (ACTION, self.action_feature)] + (
            [(OBS_ENV_STATE, self.env_state_feature)] if self.env_state_feature else []
        ):
            if len(ft.shape) != 1:
                raise ValueError(f"'{key}' must be a flat vector, got shape {tuple(ft.shape)}")
