"""LeRobot teleoperators of this plugin: ``--teleop.type=pdp_waypoints`` (a scripted operator for pdp_sim)."""

from .config_pdp_waypoints import PDPWaypointsConfig
from .pdp_waypoints import PDPWaypoints

__all__ = ["PDPWaypoints", "PDPWaypointsConfig"]
