"""Registers ``--robot.type=pdp_sim``: a suite env driven as a LeRobot robot, no hardware needed.

LeRobot's plugin discovery imports this module in its CLIs; the code lives in ``lerobot_pdp.robots``.
"""

import lerobot_pdp.robots  # noqa: F401
