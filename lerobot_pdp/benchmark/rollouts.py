"""Rollouts for the evaluation protocol, through LeRobot's own ``lerobot_eval.rollout``.

Each batch of rollouts runs in a gymnasium ``SyncVectorEnv`` of suite envs, with the policy's saved pre/post
processors and the env config's processors, exactly as ``lerobot-eval`` would. The package's
``OutcomeRecorder`` (what a latent search scores) records what ``rollout`` does not return: the first episode's
final ``info`` (success, collision, clearance, mode) and its states, whose trace dims the plots draw.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from ..candidate_rollouts import OutcomeRecorder, quiet_rollout_bar
from ..envs.suite import SuiteEnv


@dataclass
class RolloutResult:
    """Outcome of one rollout."""

    success: bool
    collided: bool
    min_clearance: float
    mode: int  # classifier label, -1 = novel / unfinished
    trace: np.ndarray
    label: str = ""  # what it was conditioned on (e.g. "mode 3"), for plots


@dataclass
class RolloutBatch:
    results: list[RolloutResult] = field(default_factory=list)

    def extend(self, other: RolloutBatch) -> None:
        self.results.extend(other.results)

    @property
    def success_rate(self) -> float:
        return float(np.mean([r.success for r in self.results])) if self.results else 0.0

    @property
    def collision_rate(self) -> float:
        return float(np.mean([r.collided for r in self.results])) if self.results else 0.0

    def mode_stats(self, n_modes: int) -> dict[str, float]:
        """Coverage (fraction of training modes reached by a successful rollout) and normalised entropy."""
        modes = [r.mode for r in self.results if r.success and r.mode >= 0]
        if not modes:
            return {"coverage": 0.0, "entropy": 0.0}
        counts = Counter(modes)
        p = np.array(list(counts.values()), dtype=float) / len(modes)
        entropy = float(-(p * np.log(p)).sum() / math.log(n_modes)) if n_modes > 1 else 0.0
        return {"coverage": len(counts) / n_modes, "entropy": entropy}


def make_vector_env(suite: SuiteEnv, scene: Any, n_envs: int) -> gym.vector.SyncVectorEnv:
    """``n_envs`` suite envs of one scene (max episode length from the suite table), each recording its first
    episode's states and final info."""
    import lerobot_pdp.envs  # noqa: F401  (registers gym ids)

    def make():
        env = gym.make(suite.gym_id, scene=scene, max_episode_steps=suite.max_episode_steps,
                       disable_env_checker=True, **suite.camera_kwargs)
        return OutcomeRecorder(env)

    return gym.vector.SyncVectorEnv([make for _ in range(n_envs)])


def run_rollouts(suite: SuiteEnv, scene: Any, policy, preprocessor, postprocessor, n: int, seed: int,
                 label: str = "", env_processors=None, batch_size: int = 10) -> RolloutBatch:
    """``n`` rollouts of ``policy`` in ``scene`` with LeRobot's rollout loop, ``batch_size`` envs at a time."""
    from lerobot.processor import PolicyProcessorPipeline
    from lerobot.scripts import lerobot_eval

    if env_processors is None:
        identity = PolicyProcessorPipeline(steps=[])
        env_processors = (identity, identity)
    out = RolloutBatch()
    done = 0
    while done < n:
        b = min(batch_size, n - done)
        venv = make_vector_env(suite, scene, b)
        try:
            torch.manual_seed(seed + done)
            with quiet_rollout_bar(lerobot_eval):
                lerobot_eval.rollout(venv, policy, env_processors[0], env_processors[1], preprocessor,
                                     postprocessor, seeds=list(range(seed + done, seed + done + b)))
            for sub in venv.envs:
                info, states = sub.final_info or {}, np.asarray(sub.states)
                out.results.append(RolloutResult(
                    success=bool(info.get("is_success", False)), collided=bool(info.get("collided", False)),
                    min_clearance=float(info.get("min_clearance", float("nan"))), mode=int(info.get("mode", -1)),
                    trace=states[:, list(suite.trace_dims)], label=label,
                ))
        finally:
            venv.close()
        done += b
    return out
