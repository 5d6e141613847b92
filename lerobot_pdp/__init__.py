"""lerobot-pdp: Parameterized Diffusion Policies as a LeRobot policy plugin.

LeRobot's plugin discovery imports ``lerobot_policy_pdp`` (every ``lerobot-*`` command does), which registers
``--policy.type=pdp``: the policy, its config and its processors (no simulator, robot or teleoperator, and no
change to any LeRobot class). Outside LeRobot's commands, ``from lerobot_pdp import PDPConfig`` (or
``PDPPolicy``) registers it, as does ``import lerobot_policy_pdp``. ``import lerobot_pdp`` alone is cheap: the
names below load on first use, so ``lerobot-pdp steer`` and ``--help`` start without importing LeRobot's policies
(seconds on a busy machine). The lab beside it registers through LeRobot's own plugin discovery, from its own
small distributions: ``lerobot_env_pdp`` (``--env.type=pdp_*``, ``lerobot_pdp.envs``), ``lerobot_robot_pdp``
(``--robot.type=pdp_sim``), ``lerobot_teleoperator_pdp`` (``--teleop.type=pdp_waypoints``) and
``lerobot_policy_pdp_baselines`` (``--policy.type=mlp_bc``). The faster dataset reading of ``column_views`` is
switched on explicitly. On a machine without FFmpeg, LeRobot's "torchcodec cannot be loaded" warning is
reported in one line (:mod:`lerobot_pdp.console`).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from lerobot_pdp import console as _console

_console.install()  # LeRobot's torchcodec fallback warning in one line for Python users too (a log filter: cheap)

if TYPE_CHECKING:
    from lerobot_pdp.configuration_pdp import PDPConfig
    from lerobot_pdp.modeling_pdp import PDPPolicy
    from lerobot_pdp.processor_pdp import make_pdp_pre_post_processors

__all__ = ["PDPConfig", "PDPPolicy", "make_pdp_pre_post_processors"]
__version__ = "0.1.0"

_HOME = {"PDPConfig": "configuration_pdp", "PDPPolicy": "modeling_pdp",
         "make_pdp_pre_post_processors": "processor_pdp"}


def __getattr__(name: str) -> Any:  # PEP 562: the public names load (and register pdp) on first use
    if name not in _HOME:
        raise AttributeError(f"module 'lerobot_pdp' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"lerobot_pdp.{_HOME[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
