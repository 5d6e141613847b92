"""Benchmark environments (MuJoCo): each env module registers its gym id and :class:`SuiteEnv` on import.

Env modules keep heavy imports (gymnasium-robotics) inside functions, so importing this package is cheap.
"""

from __future__ import annotations

import importlib
import os
import sys


def _headless_gl_default() -> None:
    """MuJoCo picks its OpenGL backend from ``MUJOCO_GL`` when it is imported, GLFW by default, which needs a
    display: on a Linux machine without one, pick-place's and kitchen's pictures (lerobot-eval's videos, their
    cameras) failed at the first frame, in lerobot-train at its first evaluation. There, with EGL installed and
    MuJoCo not imported yet, EGL is chosen; a ``MUJOCO_GL`` the user set is kept."""
    import ctypes.util
    import importlib.util

    if (sys.platform.startswith("linux") and "MUJOCO_GL" not in os.environ and "mujoco" not in sys.modules
            and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY")
            and ctypes.util.find_library("EGL") and importlib.util.find_spec("OpenGL") is not None):
        os.environ["MUJOCO_GL"] = "egl"


_headless_gl_default()

from .scene import Barrier, Scene, SceneError, load_scene  # noqa: E402 (after the GL default)
from .suite import NOVEL, SUITE, SuiteEnv, get_suite_env, parse_task_mode  # noqa: E402

# `configs` holds the LeRobot env configs (`--env.type=pdp_*`), generic over SUITE.
ENV_MODULES = ("reach_around", "avoiding", "pick_place", "kitchen_microwave", "configs")

for _name in ENV_MODULES:  # each registers its gymnasium id (and configs its LeRobot env configs) on import
    importlib.import_module(f"{__name__}.{_name}")

__all__ = ["NOVEL", "SUITE", "Barrier", "Scene", "SceneError", "SuiteEnv", "get_suite_env", "load_scene",
           "parse_task_mode"]
