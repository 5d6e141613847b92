"""Registers ``--policy.type=mlp_bc`` (MLP behavior cloning), a baseline of the PDP benchmark.

LeRobot's plugin discovery imports this module in its CLIs; the code lives in ``lerobot_pdp.baselines``.
"""

import lerobot_pdp.baselines  # noqa: F401
