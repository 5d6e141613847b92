"""What the denoiser is conditioned on: each observation frame's state, environment state and cameras as
one feature vector (the observation part of c_t in the paper; z is the other conditioning input).

Cameras are encoded the way LeRobot's diffusion policy encodes them, with its own
``DiffusionRgbEncoder`` (ResNet backbone, optional resize and crop, GroupNorm option, spatial-softmax
keypoints): PDP's config carries the same fields, so the encoder is reused rather than copied, and a PDP
and a ``diffusion`` policy with the same camera settings see images identically.
"""

from __future__ import annotations

import logging
import math

import torch
from lerobot.configs import FeatureType
from torch import Tensor, nn

from .configuration_pdp import PDPConfig

logger = logging.getLogger(__name__)

# Every torchvision ResNet halves a frame five times (stem convolution, max pool, layers 2-4): its feature map is
# ceil(H / 32) x ceil(W / 32) cells.
RESNET_STRIDE = 32


def check_camera_resolution(config: PDPConfig, training: bool) -> None:
    """Frames the backbone turns into a 1x1 feature map leave the spatial-softmax keypoints the same for every image
    (the softmax's one cell is its only position): the cameras would condition nothing, silently. Refused when a
    policy is built to train (``training``); a checkpoint already trained so loads with a warning."""
    if not config.image_features:
        return
    size = config.crop_shape or config.resize_shape or next(iter(config.image_features.values())).shape[1:]
    h, w = (int(x) for x in size)
    if math.ceil(h / RESNET_STRIDE) * math.ceil(w / RESNET_STRIDE) > 1:
        return
    which = "crop_shape" if config.crop_shape else "resize_shape" if config.resize_shape else "the cameras' size"
    message = (f"camera frames of {h}x{w} ({which}) leave {config.vision_backbone} a 1x1 feature map: its "
               f"spatial-softmax keypoints are then the same for every image, so the cameras condition nothing. Give "
               f"the backbone frames of more than {RESNET_STRIDE} pixels on a side (record larger frames, or "
               f"--policy.resize_shape='[64,64]'; a crop_shape above {RESNET_STRIDE})")
    if training:
        raise ValueError(message)
    logger.warning("%s: this checkpoint was trained so and acts on its other inputs alone", message)


def check_observation(batch: dict[str, Tensor], features: dict, leading: tuple[str | int, ...]) -> None:
    """Refuse an input the policy was not trained on, naming the key and the expected shape: a missing key, a
    value that is not a tensor, a frame of another size or a history of another length would otherwise fail deep
    inside the network, or (a camera's size) act silently on features the policy never saw. ``leading``: the batch
    dims before each frame, by name (any size) or by size (the history's ``n_obs_steps``)."""
    for key, ft in features.items():
        x = batch.get(key)
        expected = f"[{', '.join(map(str, (*leading, *ft.shape)))}]"
        if x is None:
            hint = ""
            if key.startswith("observation.images.") and len(ft.shape) == 3:  # a camera checkpoint, an env without it
                h, w = ft.shape[-2:]
                cams = ",".join(k.rsplit(".", 1)[-1] for k in features if k.startswith("observation.images."))
                hint = (f": the env must give this camera (lerobot_pdp's envs: --env.camera={cams} "
                        f"--env.image_size={h if h == w else f'{h}x{w}'}, every camera the policy was trained on)")
            given = sorted(k for k in batch if k.startswith("observation."))  # not the pipeline's own entries
            raise KeyError(f"PDP conditions on {key!r} {expected}, which the observation lacks; it has {given}{hint}")
        if not isinstance(x, Tensor):
            raise TypeError(f"observation {key!r} is a {type(x).__module__}.{type(x).__name__}; PDP takes torch "
                            f"tensors {expected}, as LeRobot's preprocessor gives them (make_pre_post_processors("
                            "policy.config, pretrained_path=<checkpoint>): normalised, batched, on the policy's device)")
        sized = [(i, n) for i, n in enumerate(leading) if isinstance(n, int)]
        if x.dim() != len(leading) + len(ft.shape) or tuple(x.shape[len(leading):]) != tuple(ft.shape) \
                or any(x.shape[i] != n for i, n in sized):
            raise ValueError(f"observation {key!r} has shape {list(x.shape)}; this policy expects {expected} "
                             "(its training dataset's feature" + (f", a history of n_obs_steps = {sized[0][1]} frames"
                                                                  if sized else "") + ")")


class ObservationEncoder(nn.Module):
    """Per-frame condition features: ``[state | environment state | camera 1 | camera 2 | ...]``.

    Without cameras it has no parameters and only concatenates (so state-only checkpoints keep their keys).
    """

    def __init__(self, config: PDPConfig):
        super().__init__()
        self.features = dict(config.condition_features)
        self.n_obs_steps = config.n_obs_steps  # the history every condition holds
        self.keys = list(self.features)
        self.vector_keys = [k for k in self.keys if config.condition_features[k].type is not FeatureType.VISUAL]
        self.image_keys = [k for k in self.keys if config.condition_features[k].type is FeatureType.VISUAL]
        self.vector_dim = sum(config.condition_features[k].shape[0] for k in self.vector_keys)
        self.separate = config.use_separate_rgb_encoder_per_camera
        self.rgb_encoder: nn.Module | None = None
        image_dim = 0
        if self.image_keys:
            # LeRobot's encoder reads exactly the camera fields PDPConfig shares with DiffusionConfig.
            from lerobot.policies.diffusion.modeling_diffusion import DiffusionRgbEncoder

            n = len(self.image_keys) if self.separate else 1
            encoders = [DiffusionRgbEncoder(config) for _ in range(n)]
            self.rgb_encoder = nn.ModuleList(encoders) if self.separate else encoders[0]
            image_dim = encoders[0].feature_dim * len(self.image_keys)
        self.frame_dim = self.vector_dim + image_dim

    def forward(self, batch: dict[str, Tensor]) -> Tensor:
        """Features [B, S, frame_dim] of observation histories ``batch[key]``: [B, S, dim] or [B, S, 3, H, W]."""
        check_observation(batch, self.features, ("B", self.n_obs_steps))
        b, s = batch[self.keys[0]].shape[:2]
        return self._features({k: batch[k].flatten(0, 1) for k in self.keys}).view(b, s, -1)

    def _features(self, frames: dict[str, Tensor]) -> Tensor:
        """Features [N, frame_dim] of N frames, ``frames[key]``: [N, dim] or [N, 3, H, W]."""
        feats = [frames[k].float() for k in self.vector_keys]
        if self.image_keys:
            feats.append(self.encode_images([frames[k].float() for k in self.image_keys]))
        return torch.cat(feats, dim=-1)

    def encode_images(self, images: list[Tensor]) -> Tensor:
        """Camera features [N, n_cameras * 2 * keypoints] of N frames per camera (``images[c]``: [N, 3, H, W])."""
        if self.separate:
            return torch.cat([enc(x) for enc, x in zip(self.rgb_encoder, images, strict=True)], dim=-1)
        n = images[0].shape[0]
        if len({x.shape[-2:] for x in images}) > 1:  # cameras of other sizes (resize_shape set): one size to stack
            images = [self.rgb_encoder.resize(x) for x in images]
        out = self.rgb_encoder(torch.cat(images))  # one backbone pass over all cameras
        return out.view(len(images), n, -1).transpose(0, 1).flatten(1)

    @torch.no_grad()
    def frame_features(self, frames: dict[str, Tensor], chunk: int = 64) -> Tensor:
        """Features [T, frame_dim] of every frame of one (normalised) demonstration, ``frames[key]``: [T, ...].

        Each frame is encoded once (in chunks of ``chunk`` frames, so a long episode fits in memory); latent
        fitting then windows these features instead of re-encoding every image in every window.
        """
        T = frames[self.keys[0]].shape[0]
        return torch.cat([self._features({k: frames[k][a : a + chunk] for k in self.keys}) for a in range(0, T, chunk)])
