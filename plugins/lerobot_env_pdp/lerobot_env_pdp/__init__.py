"""Registers ``--env.type=pdp_<env>`` and the ``lerobot_pdp/<Name>-v0`` gym ids (MuJoCo simulators of the PDP benchmark).

LeRobot's plugin discovery imports this module in its CLIs; the code lives in ``lerobot_pdp.envs``.
"""

import lerobot_pdp.envs  # noqa: F401
