"""LeRobot env configs (``--env.type=pdp_*``) for every env of the suite, generic over :data:`SUITE`.

``lerobot-eval --policy.path=CKPT --env.type=pdp_reach_around --env.scene=1`` builds the env with
``gym.make(<suite gym id>, scene=..., render_mode="rgb_array", max_episode_steps=...)``. ``lerobot-eval``
always renders up to 10 episodes to video, so suite envs must support ``render_mode="rgb_array"``.

Feature shapes come from the env's own spaces (the env is built once, lazily, when the config is
created), so an env module is the single source of truth for its observation layout.

``--env.camera=top --env.image_size=96`` adds camera images: the env returns ``obs["pixels"]["top"]``, the
config declares ``features["pixels/top"]`` (VISUAL, (H, W, 3)) mapped to ``observation.images.top``, as
LeRobot's own Aloha / RoboCasa configs do, so ``lerobot-eval`` feeds a policy the key a camera dataset
made by ``make-dataset --camera top`` trains it on.
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import gymnasium as gym
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_IMAGES, OBS_STATE

from .suite import SuiteEnv, get_suite_env

ENV_PACKAGE = "lerobot_pdp.envs"  # importing it registers every suite gym id


def _default_features_map() -> dict[str, str]:
    return {"agent_pos": OBS_STATE, "environment_state": OBS_ENV_STATE, ACTION: ACTION}


def _accepts_kwarg(gym_id: str, name: str) -> bool:
    """Whether the env constructor behind ``gym_id`` takes keyword ``name`` (other engineers' envs may not)."""
    creator = gym.envs.registration.load_env_creator(gym.spec(gym_id).entry_point)
    try:
        params = inspect.signature(creator).parameters
    except (TypeError, ValueError):
        return False
    return name in params or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())


def env_features(suite: SuiteEnv, scene: str | int = 0, **env_kwargs) -> dict[str, PolicyFeature]:
    """Policy features read off the env's spaces: ``agent_pos``, ``environment_state``, ``action`` and one
    ``pixels/<camera>`` per camera (``env_kwargs`` are passed to the env, e.g. ``camera``)."""
    import lerobot_pdp.envs  # noqa: F401  (registers gym ids)

    env = gym.make(suite.gym_id, scene=scene, disable_env_checker=True, **env_kwargs)
    try:
        obs_space = env.observation_space
        if not isinstance(obs_space, gym.spaces.Dict) or "agent_pos" not in obs_space.spaces:
            raise TypeError(
                f"{suite.gym_id}: expected a Dict observation space with 'agent_pos' (and "
                f"'environment_state'), got {obs_space}"
            )
        feats = {"agent_pos": PolicyFeature(type=FeatureType.STATE, shape=tuple(obs_space["agent_pos"].shape))}
        if "environment_state" in obs_space.spaces:
            feats["environment_state"] = PolicyFeature(
                type=FeatureType.ENV, shape=tuple(obs_space["environment_state"].shape)
            )
        if "pixels" in obs_space.spaces:
            for cam, box in obs_space["pixels"].spaces.items():
                feats[f"pixels/{cam}"] = PolicyFeature(type=FeatureType.VISUAL, shape=tuple(box.shape))
        feats[ACTION] = PolicyFeature(type=FeatureType.ACTION, shape=tuple(env.action_space.shape))
        return feats
    finally:
        env.close()


@dataclass
class PDPSuiteEnvConfig(EnvConfig):
    """Base of the ``pdp_*`` env types: one subclass per suite env, looked up by ``lerobot_env_type``.

    ``scene`` is a shipped scene index ("0"-"3"), a shipped validation scene ("val1", ...) or a path to a scene
    file (JSON/YAML).
    ``episode_length`` defaults to the suite's ``max_episode_steps``.
    ``camera`` names the env's camera(s) ("top", or "top,front"); None = state only. ``image_size`` is
    N or HxW pixels per camera image.
    """

    lerobot_env_type: ClassVar[str] = ""

    task: str | None = None
    fps: int | None = None  # fixed by the env (suite fps); only checked if given
    episode_length: int | None = None
    scene: str = "0"
    render_mode: str = "rgb_array"
    camera: str | None = None
    image_size: str = "96"
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(default_factory=_default_features_map)

    def __post_init__(self) -> None:
        if isinstance(self.scene, Path):
            self.scene = str(self.scene)
        elif isinstance(self.scene, int) and not isinstance(self.scene, bool):
            self.scene = str(self.scene)
        if not isinstance(self.scene, str):
            raise TypeError(f"env.scene must be a scene index or a path, got {self.scene!r}")
        if self.episode_length is not None and self.episode_length <= 0:
            raise ValueError(f"env.episode_length must be positive, got {self.episode_length}")
        suite = self.suite
        if self.task is None:
            self.task = suite.gym_id.split("/", 1)[-1]
        if self.fps is None:
            self.fps = suite.fps
        elif self.fps != suite.fps:
            raise ValueError(
                f"env.fps={self.fps} but {suite.name} runs at a fixed {suite.fps} Hz; leave env.fps unset"
            )
        if isinstance(self.image_size, int) and not isinstance(self.image_size, bool):
            self.image_size = str(self.image_size)
        if isinstance(self.camera, str) and not self.camera.strip():
            self.camera = None
        if self.camera is not None and not _accepts_kwarg(suite.gym_id, "camera"):
            raise ValueError(f"--env.camera={self.camera}: {suite.name} has no camera observations")
        if not self.features:
            self.features = env_features(suite, self.scene, **self._camera_kwargs())
        for key in self.features:
            if key.startswith("pixels/"):
                self.features_map.setdefault(key, f"{OBS_IMAGES}.{key.removeprefix('pixels/')}")

    def _camera_kwargs(self) -> dict:
        return {} if self.camera is None else {"camera": self.camera, "image_size": self.image_size}

    @property
    def suite(self) -> SuiteEnv:
        import lerobot_pdp.envs  # noqa: F401  (fills SUITE)

        try:
            return get_suite_env(self.lerobot_env_type)
        except KeyError as e:
            raise KeyError(
                f"--env.type={self.lerobot_env_type}: its env module did not register a SuiteEnv "
                f"(is it installed and importable?); {e.args[0]}"
            ) from e

    @property
    def package_name(self) -> str:
        return ENV_PACKAGE

    @property
    def gym_id(self) -> str:
        return self.suite.gym_id

    @property
    def gym_kwargs(self) -> dict:
        suite = self.suite
        steps = self.episode_length or suite.max_episode_steps
        kwargs: dict = {"scene": self.scene, "render_mode": self.render_mode, "max_episode_steps": steps}
        if _accepts_kwarg(suite.gym_id, "episode_length"):
            kwargs["episode_length"] = steps  # so an env's own time limit does not cut a longer TimeLimit
        kwargs.update(self._camera_kwargs())
        return kwargs


@EnvConfig.register_subclass("pdp_reach_around")
@dataclass
class PDPReachAroundEnvConfig(PDPSuiteEnvConfig):
    lerobot_env_type: ClassVar[str] = "pdp_reach_around"


@EnvConfig.register_subclass("pdp_avoiding")
@dataclass
class PDPAvoidingEnvConfig(PDPSuiteEnvConfig):
    lerobot_env_type: ClassVar[str] = "pdp_avoiding"


@EnvConfig.register_subclass("pdp_pick_place")
@dataclass
class PDPPickPlaceEnvConfig(PDPSuiteEnvConfig):
    lerobot_env_type: ClassVar[str] = "pdp_pick_place"


@EnvConfig.register_subclass("pdp_kitchen_microwave")
@dataclass
class PDPKitchenMicrowaveEnvConfig(PDPSuiteEnvConfig):
    lerobot_env_type: ClassVar[str] = "pdp_kitchen_microwave"


ENV_CONFIGS: dict[str, type[PDPSuiteEnvConfig]] = {
    c.lerobot_env_type: c
    for c in (PDPReachAroundEnvConfig, PDPAvoidingEnvConfig, PDPPickPlaceEnvConfig, PDPKitchenMicrowaveEnvConfig)
}
