"""Benchmark environments (MuJoCo): each env module registers its gym id and :class:`SuiteEnv` on import.

Env modules keep heavy imports (gymnasium-robotics) inside functions, so importing this package is cheap.
"""

from __future__ import annotations

import importlib

from .scene import Barrier, Scene, SceneError, load_scene
from .suite import NOVEL, SUITE, SuiteEnv, get_suite_env, parse_task_mode

# `configs` holds the LeRobot env configs (`--env.type=pdp_*`), generic over SUITE.
ENV_MODULES = ("reach_around", "avoiding", "pick_place", "kitchen_microwave", "configs")

for _name in ENV_MODULES:
    try:
        importlib.import_module(f"{__name__}.{_name}")
    except ModuleNotFoundError as _e:  # an env module not written yet must not break the policy
        if _e.name != f"{__name__}.{_name}":
            raise

__all__ = ["NOVEL", "SUITE", "Barrier", "Scene", "SceneError", "SuiteEnv", "get_suite_env", "load_scene",
           "parse_task_mode"]
