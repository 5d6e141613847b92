"""Configuration of Parameterized Diffusion Policies (PDP), registered with LeRobot as ``--policy.type=pdp``.

Defaults follow the paper (Table "Training hyperparameters": d_z = 2, beta_KL = 1e-3, beta_geo = 1.0,
soft-DTW gamma = 1e-5, K = 20 diffusion steps, modulation MLP hidden [16, 32]), with a denoiser small enough
to train on a CPU in minutes. The learning rates (1e-3 where the paper has 1e-4) were chosen on validation scenes.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass, field

from lerobot.configs import FeatureType, NormalizationMode, PolicyFeature, PreTrainedConfig
from lerobot.policies.rtc.configuration_rtc import RTCConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_pdp.checkpoint_files import check_checkpoint_source
from lerobot_pdp.chunk_config import ActionChunkConfigMixin
from lerobot_pdp.config_errors import config_error

LATENT_CONDITIONING = ("film", "concat", "input", "none")
LATENT_TYPES = ("continuous", "onehot")
INFERENCE_LATENTS = ("episode", "prior", "zero")
TRACE_NORMALIZE = ("none", "start", "endpoints")
COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")  # torch.compile
# the fields that steer a checkpoint as it loads (instructions run once by from_pretrained, not properties of the
# weights): a checkpoint saved while acting under their result keeps that result as its adaptation instead
STEERING_FIELDS = ("steer_latent", "steer_mode", "steer_dataset_root", "steer_episode_index", "steer_file")

logger = logging.getLogger(__name__)

# Fields whose default changed, with the value a checkpoint saved before the field existed was made with:
# such a checkpoint (its config.json lacks the key) keeps sampling as it did (see apply_legacy_defaults).
LEGACY_DEFAULTS = {"timestep_spacing": "even", "use_clipped_model_output": True, "beta_end": None}
# Legacy defaults that matter only under another field's value (beta_end: the "linear" schedule's).
LEGACY_ONLY_WITH = {"beta_end": ("beta_schedule", "linear")}


def linear_beta_end(beta_end: float | None, num_train_timesteps: int) -> float:
    """The "linear" schedule's last beta: ``beta_end``, or for None (a checkpoint saved before the field) the end
    it was made with, 0.02 scaled by 100 / K."""
    return 0.02 * 100 / num_train_timesteps if beta_end is None else beta_end


@PreTrainedConfig.register_subclass("pdp")
@dataclass
class PDPConfig(ActionChunkConfigMixin, PreTrainedConfig):
    """Configuration for :class:`~lerobot_pdp.modeling_pdp.PDPPolicy`.

    Inputs: any of ``observation.state``, ``observation.environment_state`` and one or several cameras
    ``observation.images.*`` condition the denoiser (as LeRobot's diffusion policy); ``trace_key`` (a
    state-like vector, ``observation.state`` by default) forms the behavior trace; output: ``action``. The
    behavior encoder reads whole demonstrations from the training dataset on disk.
    """

    # ---- Inputs / outputs (same meaning as LeRobot's diffusion policy) ----
    # Observation frames that condition the denoiser (the current one and n_obs_steps - 1 before it).
    n_obs_steps: int = 2
    # Length of the generated action chunk; must be a multiple of 2 ** len(down_dims).
    horizon: int = 16
    # Actions executed from each chunk before a new one is generated (receding horizon).
    n_action_steps: int = 8
    # Training windows whose action chunk would mostly run past the episode end are not sampled.
    drop_n_last_frames: int = 7
    # Leave copy-padded actions (chunk positions past the episode end) out of the denoising loss and of
    # latent fitting. LeRobot's diffusion policy trains on the copies (False there); PDP masks them by
    # default, which kept pick-place's final release precise (docs/experiments.md).
    do_mask_loss_for_padding: bool = True
    # How each feature type is normalised (LeRobot's NormalizationMode): min-max to [-1, 1] for states, env
    # states and actions (the sampler clips to that range), mean-std for cameras.
    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "VISUAL": NormalizationMode.MEAN_STD,
            "STATE": NormalizationMode.MIN_MAX,
            "ENV": NormalizationMode.MIN_MAX,
            "ACTION": NormalizationMode.MIN_MAX,
        }
    )
    # Condition the denoiser on observation.state. False = on cameras and/or observation.environment_state
    # only (the behavior trace is still read from trace_key, which may be observation.state).
    condition_on_state: bool = True

    # ---- Cameras (same fields and meaning as LeRobot's diffusion policy, whose encoder PDP reuses) ----
    # torchvision ResNet that encodes each image into spatial-softmax keypoints.
    vision_backbone: str = "resnet18"
    # torchvision weights to start the backbone from, e.g. "ResNet18_Weights.IMAGENET1K_V1". None (default):
    # random initialisation, because pretrained weights would be downloaded at start-up.
    pretrained_backbone_weights: str | None = None
    # (H, W) every image is resized to before cropping; None = keep the dataset's size.
    resize_shape: tuple[int, int] | None = None
    # (H, W) crop taken after resizing: random while training, centred at inference; None = no crop.
    crop_shape: tuple[int, int] | None = None
    # Random crops while training (centred at inference), as LeRobot's diffusion policy.
    crop_is_random: bool = True
    # Replace the backbone's BatchNorm by GroupNorm (needs random initialisation; small batches train better).
    use_group_norm: bool = True
    # Keypoints of the spatial-softmax head: each camera adds 2 * this many features per observation frame.
    spatial_softmax_num_keypoints: int = 32
    # One backbone per camera (True) or one shared by all cameras (False, fewer weights, faster on a CPU).
    use_separate_rgb_encoder_per_camera: bool = False

    # ---- Behavior trace X(tau) and its geometry ----
    # The training dataset's episodes the behavior bank reads (None: every episode). LeRobot does not tell a
    # policy which episodes it trains on: under lerobot-train, --dataset.episodes is read from its command line
    # when this is unset, so held-out episodes never shape the latent space (recorded here for teaching).
    dataset_episodes: list[int] | None = None
    # Feature whose dims form the behavior trace (positions work best: DTW compares paths).
    trace_key: str = OBS_STATE
    # Indices into `trace_key` that form X(tau); None = all dims.
    trace_dims: list[int] | None = None
    # Every trace is resampled (linear in time) to this many points before encoding and soft-DTW, so
    # episodes of any length share one encoder input; DTW already factors out speed.
    trace_length: int = 64
    # "none": absolute positions; "start": subtract the start point (shape, not location); "endpoints":
    # also divide by the start-to-end distance (paper: phases "normalized by their start and end positions").
    trace_normalize: str = "none"
    # Split every episode into phases at gripper open/close events of this action dim (one latent per
    # phase, paper Eq. 12). None = one behavior per episode.
    segment_gripper_dim: int | None = None
    # Raw (unnormalised) action value separating "open" (<=) from "closed" (>).
    segment_gripper_threshold: float = 0.0
    # At inference, a phase ends once the executed gripper command has held its new state for this many
    # consecutive actions (debounce: a blip in a generated chunk must not switch latents).
    phase_switch_steps: int = 3
    # Soft-DTW smoothing gamma for the trace distances delta^X (paper: 1e-5, i.e. essentially DTW).
    sdtw_gamma: float = 1e-5
    # Use the soft-DTW divergence (subtracts self-similarity terms) instead of the raw value.
    sdtw_normalize: bool = False
    # Geometry scale kappa in (|z_i - z_j| - kappa * delta^X_ij)^2. None = automatic: kappa makes the mean
    # trace distance equal the mean distance of two draws from the N(0, I) prior, so the geometry term
    # and the KL term agree on the latent scale (see behavior.choose_kappa).
    geo_kappa: float | None = None

    # ---- Behavior latent and trajectory VAE ----
    # d_z, the size of the behavior latent z (paper: 2, so that the latent map can be drawn).
    latent_dim: int = 2
    # "continuous" = the paper's VAE latent; "onehot" = ablation with a discrete one-hot mode latent (its
    # latent_dim is then the dataset's number of modes, set before the model is built:
    # behavior_bank.resolve_dataset_config).
    latent_type: str = "continuous"
    # Hidden layer sizes of the trace encoder E_phi (the decoder D_psi mirrors them).
    vae_hidden_dims: tuple[int, ...] = (256, 256)
    # Weight of the KL term of L_embed (paper: 1e-3).
    beta_kl: float = 1e-3
    # Weight of the geometry term L_geo that aligns latent distances with trace distances (paper: 1.0;
    # 0 is the "unaligned" ablation).
    beta_geo: float = 1.0
    # Behaviors per embedding step (all pairs among them enter L_geo).
    embed_batch_size: int = 64
    # How L_rec reduces a trace's squared error: "mean" over its elements (every reported run), or the
    # paper's "sum" (||tau - D(z)||^2), which weighs reconstruction trace_length x trace dims (128-192) times
    # more against beta_kl and beta_geo (compared on validation in docs/experiments.md).
    embed_rec_reduction: str = "mean"

    # ---- Denoiser: 1-D conditional U-Net with FiLM ----
    # "film": gamma(z) * h + beta(z) in every residual block (the paper); "concat": z appended to the
    # global condition, so it reaches every block through the condition's FiLM (ablation); "input": z appended
    # to the denoiser's input channels (the paper's shallow concatenation ablation); "none": unconditioned
    # diffusion policy (ablation).
    latent_conditioning: str = "film"
    # Channels of the U-Net's levels (as LeRobot's diffusion policy; a small backbone trains on a CPU).
    down_dims: tuple[int, ...] = (32, 64, 128)
    # Temporal convolution kernel size of the residual blocks.
    kernel_size: int = 5
    # Groups of the GroupNorm layers.
    n_groups: int = 8
    # Size of the sinusoidal diffusion-step embedding.
    diffusion_step_embed_dim: int = 64
    # Hidden sizes of the per-block MLPs that map z to (gamma, beta) (paper: [16, 32]). () = an affine
    # map, so modulations combine linearly in z (a latent between two modes mixes theirs): the benchmark
    # uses it for pick-place (benchmark/settings.py FILM; why: docs/experiments.md).
    film_hidden_dims: tuple[int, ...] = (16, 32)

    # ---- Diffusion ----
    # K: diffusion steps of the training forward process (paper: 20).
    num_train_timesteps: int = 20
    # Deterministic DDIM steps at inference. 20 = the whole chain, the sampler the benchmark's validation
    # kept at the full budget on reach-around and kitchen (docs/results.md, "Validation"). 5 samples a new
    # chunk 3.2x faster (9 against 29 ms on one CPU core, docs/performance.md) and is less precise where actions
    # must be exact (grasps, narrow openings).
    num_inference_steps: int = 20
    # Noise schedule of the forward process: "squaredcos_cap_v2" (cosine, as LeRobot) or "linear".
    beta_schedule: str = "squaredcos_cap_v2"
    # The "linear" schedule's first beta (LeRobot diffusion's and diffusers' default).
    beta_start: float = 1e-4
    # The "linear" schedule's last beta (LeRobot diffusion's and diffusers' default). None = 0.02 * 100 /
    # num_train_timesteps, the end a "linear" checkpoint saved before this field was made with.
    beta_end: float | None = 0.02
    # Clip the predicted clean action chunk to [-clip_sample_range, clip_sample_range] at every DDIM step
    # (actions are min-max normalised to [-1, 1]).
    clip_sample: bool = True
    # The clip's bound (actions are normalised to [-1, 1]).
    clip_sample_range: float = 1.0
    # Grid of the DDIM steps: diffusers' DDIMScheduler spacings "leading" (LeRobot diffusion's) / "trailing"
    # (steps of K // n), or "even" (evenly spaced from K-1 to 0, each step to the next grid point: PDP's first
    # sampler). All three visit every step when num_inference_steps = K.
    timestep_spacing: str = "leading"
    # After clipping the clean chunk, re-derive the predicted noise from it (diffusers'
    # use_clipped_model_output). LeRobot's diffusion does not, and neither does the default: with it, kitchen's
    # validation success fell from 73.1 to 68.1 percent at 20 steps (reach-around: equal). "leading" + False is
    # LeRobot diffusion's DDIM sampler exactly.
    use_clipped_model_output: bool = False

    # ---- Optimisation (one optimizer, two parameter groups) ----
    # Adam learning rate of the denoiser (theta). Both learning rates were chosen on reach-around's validation
    # scenes at 6000 steps (seed 100): 1e-3 steered better than the paper's 1e-4 (val scenes 100 / 100 / 2.5 /
    # 92.5 against 100 / 95 / 12.5 / 40 percent, docs/results.md "Validation"); every benchmark run trains at
    # 1e-3. For runs far longer than a few thousand steps the paper's 1e-4 is the alternative (not measured).
    optimizer_lr: float = 1e-3
    # Adam learning rate of the behavior encoder and decoder (phi, psi), chosen with optimizer_lr (above).
    embedding_lr: float = 1e-3
    # Adam's other settings (weight_decay is Adam's L2 term: LeRobot's AdamConfig, torch.optim.Adam) and the
    # gradient clip, as LeRobot's diffusion policy.
    optimizer_betas: tuple[float, float] = (0.95, 0.999)
    # Adam's epsilon.
    optimizer_eps: float = 1e-8
    # Adam's L2 weight decay.
    optimizer_weight_decay: float = 1e-6
    # Gradients are clipped to this total norm before each step.
    optimizer_grad_clip_norm: float = 10.0
    # Linear warm-up steps of the cosine learning-rate schedule.
    scheduler_warmup_steps: int = 100
    # lerobot-train on a taught checkpoint (--policy.path or --resume): the taught modes' share of each batch, windows
    # of the demonstrations the checkpoint keeps appended at their taught latents, so the modes are rehearsed as teach
    # rehearses them (the share: teach's --demo-share); 0: they are dropped (taught_rehearsal.py).
    taught_rehearsal_share: float = 0.25
    # torch.compile the denoiser (as LeRobot's diffusion does; lerobot-rollout's --use_torch_compile sets
    # it): fuses the many small kernels of its blocks (GroupNorm, Mish, FiLM) for the training step and the
    # sampler. Off by default: the first step and the first chunk compile for tens of seconds, and it needs
    # Triton on CUDA (a C++ compiler on CPU). Measured in docs/performance.md "On a GPU".
    compile_model: bool = False
    # torch.compile mode of the training step ("default", "reduce-overhead", "max-autotune",
    # "max-autotune-no-cudagraphs"). The sampler is compiled without CUDA graphs in any mode: on CUDA it is
    # replayed from PDP's own captured graph already.
    compile_mode: str = "default"
    # On CUDA, replay the training step's forward and backward from two captured CUDA graphs (one pair per
    # batch shape) instead of launching its ~5000 small kernels one by one: at these model sizes a step is
    # bound by kernel launches, not arithmetic. Off, or automatically eager, under compile_model, automatic
    # mixed precision, several processes, or a random image crop (its offsets are drawn on the host).
    train_cuda_graphs: bool = True
    # Torch's CPU threads in the process that builds the policy (lerobot-train, lerobot-eval, lerobot-rollout,
    # fits). None = half the usable cores, at least one (left alone when OMP_NUM_THREADS / MKL_NUM_THREADS is
    # set): torch's default of one spinning thread per core stalls beside the loader workers or any other job
    # (on 2 cores lerobot-train ran 2.3x faster alone with one, docs/performance.md "Threads"). 0 = torch's
    # default; N = N threads.
    cpu_threads: int | None = None

    # ---- Latent fitting defaults (policy.fit_latent) ----
    # Gradient steps S on z after the encoder warm start (0 = the warm start alone).
    fit_steps: int = 100
    # Step size on z (of fit_optimizer).
    fit_lr: float = 0.05
    # How z takes its steps: "adam", returning the mean of the last 20 percent of iterates (L_fit is a Monte-Carlo
    # estimate, so they jitter around the optimum), or the paper's plain "gradient" steps z <- z - fit_lr *
    # grad, returning the last (its step size is on another scale: compared on validation in
    # docs/experiments.md).
    fit_optimizer: str = "adam"
    # lambda in L_fit = E|eps - eps_theta(A~^k, k, c~, z)|^2 + lambda |z|^2.
    fit_lambda: float = 1e-3
    # What z is fitted to: "denoise" (the paper's L_fit, the noise-prediction error at random diffusion
    # steps) or "sample" (the error of the chunks the policy samples under z with its own DDIM sampler,
    # num_inference_steps forward passes per fitting step instead of one).
    fit_objective: str = "denoise"
    # After z, also fit the sampler's starting noise: "chunks" optimises one initial DDIM noise per executed
    # chunk of the demonstration (z fixed, through the policy's own sampler, as DP's per-chunk noise
    # adaptation) and the rollout plays them in order, one per new chunk; the adapted policy then replays
    # the demonstration deterministically. "none": z alone (the paper's adaptation). On the validation runs
    # it opened zero-mode scenes where the fitted latent failed (docs/experiments.md, "z plus one sampler noise per chunk").
    fit_noise: str = "none"
    # Adam steps and step size of that noise fit (DP's noise adaptation defaults).
    fit_noise_steps: int = 100
    # Adam step size of the noise fit.
    fit_noise_lr: float = 0.05
    # Demonstration chunks per fitting step (sampled from all chunks of the demonstration). Fitting is
    # compute-bound (a U-Net forward + input-backward per chunk), so this sets its cost; 16 fitted as
    # well as 32 and 64 on reach-around (docs/experiments.md).
    fit_batch_size: int = 16
    # Noise draws (k, eps) per chunk per fitting step.
    fit_noise_samples: int = 1
    # How the fitting gradient in z is computed: "autograd" (backward pass), "finite_difference" (d_z + 1
    # forward evaluations on the same noise, no backward) or "auto" (finite differences for d_z <= 3,
    # ~30 percent faster per step on CPU at d_z = 2; same success, docs/performance.md).
    fit_gradient: str = "auto"
    # After a fit, L_fit at the fitted latent is compared with the training demonstrations' own denoising
    # error (tracked while training); fit_latent warns when the ratio reaches this. On the validation scenes
    # of the four envs a ratio below 2 went with 50-100 percent success and above 2 with 0-35 percent (docs/experiments.md).
    fit_warn_ratio: float = 2.0
    # Demonstration chunks that score the fitted latent for that report, at least one per window (one no-grad
    # batch, steps stratified: ~33 ms on the 2-core CPU, ~3.5 percent of the default 100-step fit, relative spread
    # ~4 percent on the validation scenes; docs/performance.md). 0 skips the report (FitResult.fit_error /
    # error_ratio stay None) and its warning, e.g. for the fastest short fits.
    fit_report_chunks: int = 256

    # ---- Inference-time steering (also settable from lerobot-eval: --policy.steer_latent=[..]) ----
    # A fixed latent for every rollout.
    steer_latent: list[float] | None = None
    # Condition on the mean latent of this training mode: its id (from the episodes' task strings, or a
    # discovered cluster's) or its name (--policy.steer_mode='around the crate', as mode_names holds it).
    steer_mode: int | str | None = None
    # Fit z at start-up to this episode of this local LeRobotDataset (one new demonstration): when the
    # checkpoint is loaded (PDPPolicy.from_pretrained), before LeRobot's control loop starts.
    steer_dataset_root: str | None = None
    # The episode of steer_dataset_root to fit z to (None: episode 0, as `lerobot-pdp adapt --episode` and a
    # steer file's {"dataset": DIR} default to).
    steer_episode_index: int | None = None
    # Live steering: a JSON file polled at every new action chunk; when it changes, its request
    # ({"mode": 3}, {"latent": [..]}, {"dataset": DIR, "episode": 0}) sets the active latent without
    # reloading the policy (lerobot_pdp/steering.py). Its request, once read, overrides the fields above.
    steer_file: str | None = None
    # An adapted checkpoint (`lerobot-pdp adapt`, or save_pretrained after fit_latent / set_latent) carries
    # its latent and chunk noises in adaptation.safetensors (provenance in adaptation.json) and acts adapted
    # from the first action; false: load the base behaviour (`--policy.use_adaptation=false`). The steering
    # fields above override it.
    use_adaptation: bool = True
    # With no steering set: "episode" = a random training behavior's latent per reset (multimodal, like
    # DP); "prior" = a draw from N(0, I); "zero" = the prior mean.
    inference_latent: str = "episode"
    # Real-time chunking: lerobot-rollout --inference.type=rtc sets it from --inference.rtc.* (how a new chunk's first
    # actions continue the previous chunk's unexecuted ones: lerobot_pdp/realtime_chunking.py); None elsewhere.
    rtc_config: RTCConfig | None = None
    # Under RTC, a new chunk replaces the engine's queue less the actions the robot executed since the chunk's
    # observation, continuing the previous chunk from that step; false: LeRobot's rule, ceil(latency * fps), with the
    # prefix from the engine's read, a step off for PDP's short chunks (realtime_chunking.py).
    rtc_consumed_delay: bool = True
    # Under RTC, each chunk is conditioned on the last n_obs_steps observations the control loop published up to the
    # chunk's own (the history select_action keeps); false: on the chunk's observation repeated (the engine passes
    # only that one), what PDP was not trained on (realtime_chunking.py; docs/performance.md).
    rtc_observation_history: bool = True
    # Served by `python -m lerobot_pdp.policy_server` (LeRobot's async inference): plan each chunk just in time, from
    # the observation sent when the client holds no more actions than a chunk takes to plan, so the robot does not
    # wait for it (and executes the chunk's later actions); false: only when the client's queue is empty, the robot
    # waiting for each chunk and executing it whole (paced_chunks.JustInTime; docs/deploy.md).
    async_just_in_time: bool = True
    # Served so: how many of a new chunk's first actions are held to the last chunk's the client still holds (weight
    # 1 over those it executes while the new one is planned, then fading to 0), so the robot keeps its route where
    # chunks are spliced, as lerobot-rollout's --inference.rtc.execution_horizon holds them; 0: none, each chunk a
    # fresh sample (paced_chunks.LastChunk; chosen on validation scenes: docs/performance.md).
    async_execution_horizon: int = 5
    # Served so: each chunk's sampler noise is the last chunk's, shifted by the steps between them (fresh only for
    # the steps the last did not reach), another way to keep the route (measured beside the hold, not better);
    # false: fresh noise per chunk.
    async_carry_noise: bool = False

    # ---- Filled in at training time from the dataset, before the model is built (saved with the checkpoint;
    # behavior_bank.resolve_dataset_config) ----
    # Mode names by mode id, from meta/mode_labels.json or task strings "mode <id>: <name>"; teach adds one.
    mode_names: dict[str, str] | None = None
    # The training dataset's frame rate: a demonstration recorded at another rate is refused (its actions span
    # another time per frame; episodes.recording_problems). None: not recorded (checkpoints from before it).
    dataset_fps: float | None = None
    # The names of the training dataset's vector values by key (observation.state, action, ...), in its order: a
    # demonstration or robot naming the same values in another order is refused, not fitted position by position.
    dataset_feature_names: dict[str, list[str]] | None = None

    def __post_init__(self):
        super().__post_init__()
        errors = []
        if self.latent_dim < 1:
            errors.append(f"latent_dim must be >= 1, got {self.latent_dim}")
        if self.dataset_episodes is not None and (
                not self.dataset_episodes or any(isinstance(e, bool) or not isinstance(e, int) or e < 0
                                                 for e in self.dataset_episodes)
                or len(set(self.dataset_episodes)) != len(self.dataset_episodes)):
            errors.append(f"dataset_episodes must be distinct episode indices >= 0 (or None: all), "
                          f"got {self.dataset_episodes}")
        if self.drop_n_last_frames < 0:  # else LeRobot's sampler says it, without the option's --policy. name
            errors.append(f"drop_n_last_frames must be >= 0, got {self.drop_n_last_frames}")
        if self.cpu_threads is not None and self.cpu_threads < 0:
            errors.append(f"cpu_threads must be >= 0 (0: torch's default) or None (auto), got {self.cpu_threads}")
        if not self.sdtw_gamma > 0:
            errors.append(f"sdtw_gamma must be > 0, got {self.sdtw_gamma}")
        if self.latent_conditioning not in LATENT_CONDITIONING:
            errors.append(f"latent_conditioning must be one of {LATENT_CONDITIONING}, got {self.latent_conditioning!r}")
        if self.latent_type not in LATENT_TYPES:
            errors.append(f"latent_type must be one of {LATENT_TYPES}, got {self.latent_type!r}")
        if self.inference_latent not in INFERENCE_LATENTS:
            errors.append(f"inference_latent must be one of {INFERENCE_LATENTS}, got {self.inference_latent!r}")
        if self.trace_normalize not in TRACE_NORMALIZE:
            errors.append(f"trace_normalize must be one of {TRACE_NORMALIZE}, got {self.trace_normalize!r}")
        if self.embed_rec_reduction not in ("mean", "sum"):
            errors.append(f"embed_rec_reduction must be 'mean' or 'sum', got {self.embed_rec_reduction!r}")
        if self.beta_schedule not in ("squaredcos_cap_v2", "linear"):
            errors.append(f"beta_schedule must be 'squaredcos_cap_v2' or 'linear', got {self.beta_schedule!r}")
        if not 0 < self.beta_start <= linear_beta_end(self.beta_end, self.num_train_timesteps) < 1:
            errors.append(f"beta_start and beta_end must satisfy 0 < beta_start <= beta_end < 1, "
                          f"got {self.beta_start} and {self.beta_end}")
        for name in ("beta_kl", "beta_geo", "fit_lambda", "async_execution_horizon"):
            if getattr(self, name) < 0:
                errors.append(f"{name} must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.taught_rehearsal_share < 1:
            errors.append(f"taught_rehearsal_share must be in [0, 1), got {self.taught_rehearsal_share}")
        for name in ("n_obs_steps", "horizon", "n_action_steps", "trace_length", "num_train_timesteps",
                     "num_inference_steps", "embed_batch_size", "fit_batch_size", "fit_noise_samples",
                     "phase_switch_steps"):
            if getattr(self, name) < 1:
                errors.append(f"{name} must be >= 1, got {getattr(self, name)}")
        # layer widths: () is a valid film_hidden_dims (an affine FiLM), a 0-wide layer never is (it would
        # silently cut z off from the denoiser)
        for name in ("down_dims", "vae_hidden_dims", "film_hidden_dims"):
            if any(int(d) < 1 for d in getattr(self, name)):
                errors.append(f"every entry of {name} must be >= 1, got {tuple(getattr(self, name))}")
        if not self.down_dims:
            errors.append("down_dims must list at least one U-Net level, got ()")
        if self.fit_gradient not in ("auto", "autograd", "finite_difference"):
            errors.append(f"fit_gradient must be 'auto', 'autograd' or 'finite_difference', got {self.fit_gradient!r}")
        if self.trace_length < 2:
            errors.append(f"trace_length must be >= 2, got {self.trace_length}")
        if self.fit_steps < 0:
            errors.append(f"fit_steps must be >= 0, got {self.fit_steps}")
        if not self.fit_warn_ratio > 0:
            errors.append(f"fit_warn_ratio must be > 0, got {self.fit_warn_ratio}")
        if self.fit_report_chunks < 0:
            errors.append(f"fit_report_chunks must be >= 0 (0: no fit report), got {self.fit_report_chunks}")
        if self.fit_noise not in ("none", "chunks"):
            errors.append(f"fit_noise must be 'none' or 'chunks', got {self.fit_noise!r}")
        if self.fit_noise_steps < 1 or not self.fit_noise_lr > 0:
            errors.append(f"fit_noise_steps must be >= 1 and fit_noise_lr > 0, got {self.fit_noise_steps}, "
                          f"{self.fit_noise_lr}")
        if self.fit_optimizer not in ("adam", "gradient"):
            errors.append(f"fit_optimizer must be 'adam' or 'gradient', got {self.fit_optimizer!r}")
        if self.fit_objective not in ("denoise", "sample"):
            errors.append(f"fit_objective must be 'denoise' or 'sample', got {self.fit_objective!r}")
        if self.compile_mode not in COMPILE_MODES:
            errors.append(f"compile_mode must be one of {COMPILE_MODES}, got {self.compile_mode!r}")
        if self.timestep_spacing not in ("even", "leading", "trailing"):
            errors.append(f"timestep_spacing must be 'even', 'leading' or 'trailing', got {self.timestep_spacing!r}")
        if self.num_inference_steps > self.num_train_timesteps:
            errors.append(
                f"num_inference_steps ({self.num_inference_steps}) must be <= num_train_timesteps "
                f"({self.num_train_timesteps})"
            )
        if self.horizon % (2 ** len(self.down_dims)) != 0:
            errors.append(
                f"horizon ({self.horizon}) must be a multiple of 2 ** len(down_dims) = {2 ** len(self.down_dims)}"
            )
        if self.n_action_steps > self.horizon - self.n_obs_steps + 1:
            errors.append(
                f"n_action_steps ({self.n_action_steps}) must be <= horizon - n_obs_steps + 1 "
                f"({self.horizon - self.n_obs_steps + 1})"
            )
        if self.steer_latent is not None and len(self.steer_latent) != self.latent_dim:
            errors.append(f"steer_latent has {len(self.steer_latent)} values, latent_dim is {self.latent_dim}")
        for name in ("resize_shape", "crop_shape"):
            shape = getattr(self, name)
            if shape is not None and (len(shape) != 2 or any(int(d) < 1 for d in shape)):
                errors.append(f"{name} must be a pair of positive integers (H, W) or None, got {shape}")
        if not self.vision_backbone.startswith("resnet"):
            errors.append(f"vision_backbone must be a torchvision ResNet (resnet18, resnet34, ...), got "
                          f"{self.vision_backbone!r}")
        if self.use_group_norm and self.pretrained_backbone_weights:
            errors.append("use_group_norm=True replaces the backbone's BatchNorm, which would ruin pretrained "
                          f"weights {self.pretrained_backbone_weights!r}: set use_group_norm=false with them")
        if self.spatial_softmax_num_keypoints < 1:
            errors.append(f"spatial_softmax_num_keypoints must be >= 1, got {self.spatial_softmax_num_keypoints}")
        if self.steer_episode_index is not None and self.steer_dataset_root is None:
            errors.append(f"steer_episode_index={self.steer_episode_index} names an episode of no dataset: give "
                          "steer_dataset_root (the recording to fit z to) too")
        if self.steer_episode_index is not None and not (isinstance(self.steer_episode_index, int)
                                                         and self.steer_episode_index >= 0):
            errors.append(f"steer_episode_index must be an episode index >= 0, got {self.steer_episode_index!r}")
        if errors:
            raise config_error("Invalid PDPConfig: " + "; ".join(errors))  # --policy.* named on LeRobot's command line

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path, **kwargs):  # noqa: ANN001, ANN206 - LeRobot's signature
        """LeRobot's loader, after naming a missing checkpoint folder or a damaged config.json."""
        check_checkpoint_source(pretrained_name_or_path, need_weights=False)
        return super().from_pretrained(pretrained_name_or_path, **kwargs)

    def validate_features(self) -> None:
        """Check the input/output features this policy needs; raise naming the key and shape."""
        have = sorted(self.input_features)
        if self.action_feature is None:
            raise ValueError(f"PDP needs '{ACTION}' among the output features; got {sorted(self.output_features)}")
        trace_ft = self.input_features.get(self.trace_key)
        if trace_ft is None:
            raise ValueError(
                f"PDP reads its behavior trace from trace_key '{self.trace_key}', which is not an input feature; "
                f"the input features are {have}. Set --policy.trace_key to a state-like vector among them "
                "(e.g. joint or end-effector positions); the denoiser is conditioned on 'observation.state' whatever "
                "the trace_key, so store the robot's state under that key"
            )
        if len(trace_ft.shape) != 1:
            raise ValueError(f"trace_key '{self.trace_key}' must be a flat vector, got shape {tuple(trace_ft.shape)}")
        if not self.condition_features:
            raise ValueError(
                "PDP needs something to condition on: observation.state (with condition_on_state=true), "
                f"observation.environment_state or a camera observation.images.*; got {have}"
            )
        other_states = [k for k, ft in self.input_features.items() if ft.type is FeatureType.STATE and k != OBS_STATE]
        if self.condition_on_state and OBS_STATE not in self.input_features and other_states:
            logger.warning(
                "the state input(s) %s condition nothing: PDP, as LeRobot's policies, conditions its denoiser on "
                "'%s' (with %s and cameras), and this data has none, so the policy does not see the robot's "
                "state%s. Store the robot's state as '%s' (as lerobot-record does) to condition on it",
                other_states, OBS_STATE, OBS_ENV_STATE,
                f" (it reads only its behavior trace from trace_key '{self.trace_key}')" if self.trace_key in
                other_states else "", OBS_STATE)
        flat = [(ACTION, self.action_feature)] + [(k, ft) for k, ft in self.condition_features.items()
                                                  if ft.type is not FeatureType.VISUAL]
        for key, ft in flat:
            if len(ft.shape) != 1:
                raise ValueError(f"'{key}' must be a flat vector, got shape {tuple(ft.shape)}")
        self._validate_images()
        if self.trace_dims is not None:
            bad = [d for d in self.trace_dims if not 0 <= d < trace_ft.shape[0]]
            if bad or not self.trace_dims:
                raise ValueError(
                    f"trace_dims {self.trace_dims} must be a non-empty list of indices into '{self.trace_key}' "
                    f"of shape {tuple(trace_ft.shape)}"
                )
        if self.segment_gripper_dim is not None and not 0 <= self.segment_gripper_dim < self.action_feature.shape[0]:
            raise ValueError(
                f"segment_gripper_dim {self.segment_gripper_dim} is out of range for '{ACTION}' of shape "
                f"{tuple(self.action_feature.shape)}"
            )

    def _validate_images(self) -> None:
        images = self.image_features
        if not images:
            return
        shapes = {k: tuple(ft.shape) for k, ft in images.items()}
        for key, shape in shapes.items():
            if len(shape) != 3 or shape[0] != 3:
                raise ValueError(f"camera '{key}' must have shape (3, H, W) (channel first, RGB), got {shape}")
        if len(set(shapes.values())) > 1 and self.resize_shape is None:
            raise ValueError(f"all cameras must have the same shape (one encoder input size); got {shapes}. "
                             "Resize them when recording, or set --policy.resize_shape")
        size = self.resize_shape or next(iter(shapes.values()))[1:]
        if self.crop_shape is not None and (self.crop_shape[0] > size[0] or self.crop_shape[1] > size[1]):
            raise ValueError(f"crop_shape {tuple(self.crop_shape)} does not fit in the images of "
                             f"{', '.join(repr(k) for k in shapes)} "
                             f"({'resized to ' if self.resize_shape else ''}{tuple(size)}): give a smaller "
                             "--policy.crop_shape, or none")

    @property
    def condition_features(self) -> dict[str, PolicyFeature]:
        """The observations the denoiser is conditioned on, in the order their features are concatenated
        per frame: state (if ``condition_on_state``), environment state, then the cameras."""
        out: dict[str, PolicyFeature] = {}
        if self.condition_on_state and self.robot_state_feature is not None:
            out[OBS_STATE] = self.robot_state_feature
        if self.env_state_feature is not None:
            out[OBS_ENV_STATE] = self.env_state_feature
        out.update(self.image_features)
        return out

    @property
    def trace_dim(self) -> int:
        """Dimension d of the behavior trace X(tau)."""
        if self.trace_dims is not None:
            return len(self.trace_dims)
        return self.input_features[self.trace_key].shape[0]


def apply_legacy_defaults(config: PDPConfig, saved: dict, given: Iterable[str] = ()) -> list[str]:
    """Give ``config`` (parsed from a checkpoint's ``saved`` config.json) the values of :data:`LEGACY_DEFAULTS`
    for the fields that file lacks, so that a checkpoint written before a default changed samples as it did.
    A field named in ``given`` (the command line's ``--policy.<field>``) or holding another value than today's
    default was set on purpose and is kept; otherwise it cannot be told from a missing key and gets the legacy
    value. A field that has no effect under the config (:data:`LEGACY_ONLY_WITH`) is left as it is. Returns the
    fields changed."""
    changed = []
    for name, old in LEGACY_DEFAULTS.items():
        field, value = LEGACY_ONLY_WITH.get(name, (None, None))
        if field is not None and getattr(config, field) != value:
            continue
        if (name not in saved and name not in given
                and getattr(config, name) == PDPConfig.__dataclass_fields__[name].default):
            setattr(config, name, old)
            changed.append(name)
    return changed
