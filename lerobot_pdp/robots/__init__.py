"""LeRobot robots of this plugin: ``--robot.type=pdp_sim`` (a suite env as a robot, no hardware)."""

from . import client_hooks
from .config_pdp_sim import PDPSimConfig
from .pdp_sim import PDPSim, find_robot

# LeRobot's async robot client loads plugins before it builds its client: wrap it now (no-op elsewhere)
client_hooks.install()

__all__ = ["PDPSim", "PDPSimConfig", "find_robot"]
