"""Rollouts of many candidate latents at once: one gymnasium vector env, each sub-env under its own latent,
through LeRobot's own rollout loop (``lerobot.scripts.lerobot_eval.rollout``, what ``lerobot-eval`` runs).

A latent search scores a whole population per step; rolling each candidate out on its own would pay the
policy's per-chunk cost once per candidate. Here the population shares one batched forward pass: for the
duration of a rollout the policy's :class:`~lerobot_pdp.steering_state.Steering` is replaced by
:class:`PerEnvLatents`, which gives each env its own latent (and its own phase, for segmented policies).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import Tensor

from .outcome_scores import Outcome
from .steering_state import Steering

EnvFactory = Callable[[], gym.Env]  # one env; it needs ``_max_episode_steps`` (``gym.make(..., max_episode_steps=)``)


class PerEnvLatents(Steering):
    """Steering where env b of the batch acts under ``latents[b]`` ([B, M, d_z]; M > 1: one per phase)."""

    def __init__(self, latents: Tensor):
        super().__init__(latents.shape[-1])
        self.register_buffer("per_env", latents.detach().float(), persistent=False)
        self.latent = self.per_env[0]  # M phases: what phase tracking and ``per_phase`` read

    def latent_for(self, batch_size: int, device: torch.device | str, default: Callable[[int], Tensor]) -> Tensor:
        if batch_size != len(self.per_env):
            raise RuntimeError(f"rollout batch of {batch_size} envs for {len(self.per_env)} candidate latents")
        if self.per_env.shape[1] == 1:
            return self.per_env[:, 0].to(device)
        phase = self.phases.phases(batch_size, self.per_env.device).clamp(max=self.per_env.shape[1] - 1)
        return self.per_env[torch.arange(batch_size, device=self.per_env.device), phase].to(device)


class OutcomeRecorder(gym.Wrapper):
    """Keeps what a score needs of the first episode after each new rollout: states, summed reward, final info."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self.states: list[np.ndarray] = []
        self.reward = 0.0
        self.final_info: dict[str, Any] | None = None
        self._recording = False

    def reset(self, *, seed=None, options=None):
        from lerobot.envs.utils import NEW_ROLLOUT_OPTION

        obs, info = self.env.reset(seed=seed, options=options)
        # autoresets of a finished sub-env carry no option: the episodes they start are not the rollout's
        if (options or {}).get(NEW_ROLLOUT_OPTION) or (self.final_info is None and not self._recording):
            self.states, self.reward, self.final_info, self._recording = [self._state(obs)], 0.0, None, True
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if self._recording:
            self.states.append(self._state(obs))
            self.reward += float(reward)
            if terminated or truncated:
                self.final_info, self._recording = dict(info), False
        return obs, reward, terminated, truncated, info

    @staticmethod
    def _state(obs: Any) -> np.ndarray:
        pos = obs.get("agent_pos") if isinstance(obs, dict) else None
        return np.zeros(0) if pos is None else np.asarray(pos, dtype=float).reshape(-1).copy()

    def outcome(self) -> Outcome:
        info = self.final_info or {}
        states = np.asarray(self.states) if self.states and self.states[0].size else np.zeros((0, 0))
        return Outcome(success=bool(info.get("is_success", False)), reward=self.reward, states=states, info=info)


def check_env_features(config: Any, env: gym.Env) -> None:
    """The env observes and acts as the checkpoint was trained (LeRobot's key mapping: ``agent_pos`` ->
    ``observation.state``, ``environment_state`` -> ``observation.environment_state``, ``pixels/<cam>`` ->
    ``observation.images.<cam>``); else a ValueError naming the key and both shapes."""
    from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_IMAGES, OBS_STATE

    space = env.observation_space
    spaces = space.spaces if isinstance(space, gym.spaces.Dict) else {}
    have: dict[str, tuple] = {}
    if "agent_pos" in spaces:
        have[OBS_STATE] = tuple(spaces["agent_pos"].shape)
    if "environment_state" in spaces:
        have[OBS_ENV_STATE] = tuple(spaces["environment_state"].shape)
    pixels = spaces.get("pixels")
    if isinstance(pixels, gym.spaces.Dict):
        for cam, box in pixels.spaces.items():
            h, w, c = box.shape
            have[f"{OBS_IMAGES}.{cam}"] = (c, h, w)
    have[ACTION] = tuple(env.action_space.shape)
    want = {**{k: tuple(f.shape) for k, f in config.input_features.items()}, ACTION: tuple(config.action_feature.shape)}
    wrong = [f"the env does not provide '{k}' (the checkpoint's, shape {shape})" if k not in have else
             f"the env's '{k}' has shape {have[k]} but the checkpoint was trained on {shape}"
             for k, shape in want.items() if have.get(k) != shape]
    if wrong:
        raise ValueError(f"{'; '.join(wrong)}: a checkpoint of another env? (the env provides {have})")


def env_camera_kwargs(config: Any) -> dict[str, str]:
    """The ``camera`` / ``image_size`` keywords of a suite env that observes as the checkpoint's cameras do
    (``observation.images.<camera>`` of shape (3, H, W)); empty for a state-only checkpoint."""
    cams = {k.removeprefix("observation.images."): tuple(f.shape) for k, f in config.input_features.items()
            if k.startswith("observation.images.")}
    if not cams:
        return {}
    return {"camera": ",".join(cams), "image_size": "x".join(map(str, next(iter(cams.values()))[1:]))}


@contextlib.contextmanager
def quiet_rollout_bar(module: Any) -> Iterator[None]:
    """LeRobot's rollout draws one progress bar per batch; hundreds of them would drown the caller's own."""
    original = module.trange
    module.trange = lambda *a, **kw: original(*a, **{**kw, "disable": True})
    try:
        yield
    finally:
        module.trange = original


@contextlib.contextmanager
def acting_under(policy: Any, steering: Steering) -> Iterator[None]:
    """``policy`` acts under ``steering`` (no live steering file polled), in eval mode; restored afterwards."""
    saved, steer_file, training = policy.steering, getattr(policy, "_steer_file", None), policy.training
    policy.steering, policy._steer_file = steering.to(saved.latent.device), None
    policy.eval()
    try:
        yield
    finally:
        policy.steering, policy._steer_file = saved, steer_file
        policy.train(training)
        policy.reset()


class CandidateRollouts:
    """Rolls out candidate latents, ``rollouts`` each, in vector envs of up to ``max_envs`` sub-envs (kept
    open between calls: a search calls it once per population). Close it (or use ``with``) when done."""

    def __init__(self, policy: Any, env_factory: EnvFactory, rollouts: int, seed: int, processors: tuple,
                 env_processors: tuple | None = None, max_envs: int = 16):
        from lerobot.processor import PolicyProcessorPipeline

        self.policy, self.env_factory, self.rollouts, self.seed = policy, env_factory, rollouts, seed
        self.processors = processors
        identity = PolicyProcessorPipeline(steps=[])
        self.env_processors = env_processors or (identity, identity)
        self.max_envs = max(max_envs, rollouts)
        self._venvs: dict[int, gym.vector.SyncVectorEnv] = {}
        self.batches = 0  # rollout batches run: seeds the sampler of the next one

    def __enter__(self) -> CandidateRollouts:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        for venv in self._venvs.values():
            venv.close()
        self._venvs.clear()

    def _venv(self, n: int) -> gym.vector.SyncVectorEnv:
        from lerobot.envs.utils import FreezeAfterEpisodeEnd

        if n not in self._venvs:
            made = [self.env_factory() for _ in range(n)]
            try:
                check_env_features(self.policy.config, made[0])
            except ValueError:
                for env in made:
                    env.close()
                raise
            self._venvs[n] = gym.vector.SyncVectorEnv(
                [lambda env=env: FreezeAfterEpisodeEnd(OutcomeRecorder(env)) for env in made])
        return self._venvs[n]

    @contextlib.contextmanager
    def acting(self, per_env: Tensor) -> Iterator[Any]:
        """The policy to roll out with env b under candidate ``per_env[b]``: here a latent ([B, M, d_z]) through
        :class:`PerEnvLatents`. A subclass steers by something else (the benchmark's DP by its sampler noise)."""
        with acting_under(self.policy, PerEnvLatents(per_env)):
            yield self.policy

    def candidates_per_batch(self, rollouts: int | None = None) -> int:
        return max(1, self.max_envs // (rollouts or self.rollouts))

    def __call__(self, latents: Sequence[Tensor], first: int = 0, count: int | None = None) -> list[list[Outcome]]:
        """Each latent's outcomes, in order: ``count`` rollouts (default ``rollouts``) from its ``first``-th on.
        Every candidate meets the same env seeds (its j-th rollout resets with seed ``seed + j``), so candidates
        differ by their latent, not by their luck with the scene, and a candidate rolled out again on more seeds
        (``first`` = the rollouts it had) meets new ones; the sampler's noise is seeded per batch."""
        from lerobot.scripts import lerobot_eval

        out: list[list[Outcome]] = []
        k = count or self.rollouts
        per = self.candidates_per_batch(k)
        for i in range(0, len(latents), per):
            group = [torch.as_tensor(z, dtype=torch.float32) for z in latents[i:i + per]]
            group = [z[None] if z.dim() == 1 else z for z in group]
            if len({tuple(z.shape) for z in group}) > 1:  # different phase counts: one batch per shape
                for z in group:
                    out.extend(self([z], first, k))
                continue
            venv = self._venv(len(group) * k)
            per_env = torch.stack(group).repeat_interleave(k, dim=0)
            with torch.random.fork_rng(devices=None if torch.cuda.is_available() else []), \
                    self.acting(per_env) as actor, quiet_rollout_bar(lerobot_eval):
                torch.manual_seed(self.seed * 100_003 + self.batches)
                lerobot_eval.rollout(venv, actor, *self.env_processors, *self.processors,
                                     seeds=[self.seed + first + j for _ in group for j in range(k)])
            self.batches += 1
            outcomes = [sub.env.outcome() for sub in venv.envs]
            out.extend(outcomes[c * k:(c + 1) * k] for c in range(len(group)))
        return out
