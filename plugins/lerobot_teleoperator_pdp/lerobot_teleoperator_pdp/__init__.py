"""Registers ``--teleop.type=pdp_waypoints``: a scripted operator that drives ``pdp_sim`` through way-points.

LeRobot's plugin discovery imports this module in its CLIs; the code lives in ``lerobot_pdp.teleoperators``.
"""

import lerobot_pdp.teleoperators  # noqa: F401
