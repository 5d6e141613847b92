"""The benchmark suite's table of environments: one :class:`SuiteEnv` per env, looked up by CLI name.

Everything generic (dataset generation, plotting, the evaluation protocol, ``lerobot-eval`` configs)
goes through this table, so adding an env means adding one entry, not editing those tools.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np

from ..episodes import parse_task_mode  # noqa: F401  (the inverse of SuiteEnv.task_string)

NOVEL = "novel"  # what a mode classifier returns for a trajectory that matches no training mode


class Expert(Protocol):
    """A scripted demonstrator: ``reset`` with the first observation, then one action per call."""

    def reset(self, obs: dict[str, np.ndarray]) -> None: ...

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray: ...


@dataclass(frozen=True)
class SuiteEnv:
    """How generic tools drive one environment of the suite.

    Attributes:
        name: CLI name, e.g. ``"reach-around"``.
        gym_id: registered gymnasium id, e.g. ``"lerobot_pdp/ReachAround-v0"``.
        scene_key: file prefix of the shipped scenes (``scenes/<scene_key>_scene<k>.json``).
        lerobot_env_type: ``--env.type`` for ``lerobot-eval`` (``"pdp_reach_around"``).
        module: module that implements the env, the expert and the classifier (imported lazily, so that
            ``import lerobot_pdp`` stays cheap and does not import gymnasium-robotics).
        mode_names: training mode names; the mode id is the index.
        trace_dims: indices of ``observation.state`` that form the behavior trace X(tau) (positions).
        max_episode_steps: time limit of one rollout.
        fps: control frequency written into datasets.
        segment_on_gripper: index of the gripper command in ``action`` for phase segmentation, or None.
    """

    name: str
    gym_id: str
    scene_key: str
    lerobot_env_type: str
    module: str
    mode_names: tuple[str, ...]
    trace_dims: tuple[int, ...]
    max_episode_steps: int
    fps: int
    segment_on_gripper: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def n_modes(self) -> int:
        return len(self.mode_names)

    @property
    def camera_kwargs(self) -> dict[str, Any]:
        """``camera`` / ``image_size`` keywords for the env and ``make_dataset`` when this entry is the camera
        variant of an env (see :meth:`with_camera`); empty for the state-only env."""
        return dict(self.extra.get("camera_kwargs", {}))

    def with_camera(self, camera: str, image_size: int) -> SuiteEnv:
        """The same env observed through ``camera`` (``observation.images.<camera>``, ``image_size`` pixels):
        datasets, rollouts and evaluations made from the returned entry carry the image."""
        return replace(self, extra={**self.extra, "camera_kwargs": {"camera": camera, "image_size": image_size}})

    def impl(self):
        """The implementing module: exposes ``make_expert``, ``expert_from_waypoints``, ``classify_mode``."""
        return importlib.import_module(self.module)

    def make_expert(self, mode: int, rng: np.random.Generator, scene: Any = 0) -> Expert:
        return self.impl().make_expert(mode, rng, scene=scene)

    def expert_from_waypoints(self, waypoints: Any, rng: np.random.Generator, scene: Any = 0) -> Expert:
        return self.impl().expert_from_waypoints(waypoints, rng, scene=scene)

    def classify_mode(self, states: np.ndarray, scene: Any = 0) -> int | str:
        """Training mode id of a trajectory of ``observation.state`` rows, or :data:`NOVEL`."""
        return self.impl().classify_mode(states, scene=scene)

    def task_string(self, mode: int | str) -> str:
        """Episode task string that carries the mode label, e.g. ``"mode 3: left-wide"``."""
        if mode == NOVEL or not isinstance(mode, (int, np.integer)):
            return f"mode {NOVEL}: {mode}"
        return f"mode {int(mode)}: {self.mode_names[int(mode)]}"


def mode_info(label: int | str, mode_names: tuple[str, ...] | list[str]) -> dict[str, Any]:
    """``info`` fields for a classifier label: ``mode`` as an int (-1 = novel) plus ``mode_name``.

    Always an int because gymnasium's vector envs allocate each info array from the first finished
    env's value: a mix of ints and ``"novel"`` in one batch would crash ``lerobot-eval``.
    """
    if label == NOVEL or not isinstance(label, (int, np.integer)):
        return {"mode": -1, "mode_name": NOVEL}
    return {"mode": int(label), "mode_name": mode_names[int(label)]}


SUITE: dict[str, SuiteEnv] = {}


def register_suite_env(env: SuiteEnv) -> SuiteEnv:
    SUITE[env.name] = env
    return env


def get_suite_env(name: str) -> SuiteEnv:
    """Look up an env by CLI name (``reach-around``), scene key (``reach_around``) or gym id."""
    for env in SUITE.values():
        if name in (env.name, env.scene_key, env.gym_id, env.lerobot_env_type):
            return env
    raise KeyError(f"unknown env {name!r}; known: {sorted(SUITE)}")


