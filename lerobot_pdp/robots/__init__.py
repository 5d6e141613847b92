"""LeRobot robots of this plugin: ``--robot.type=pdp_sim`` (a suite env as a robot, no hardware)."""

from .config_pdp_sim import PDPSimConfig
from .pdp_sim import PDPSim, find_robot

__all__ = ["PDPSim", "PDPSimConfig", "find_robot"]
