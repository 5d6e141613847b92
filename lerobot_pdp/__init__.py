"""lerobot-pdp: Parameterized Diffusion Policies as a LeRobot policy plugin.

``import lerobot_pdp`` registers ``--policy.type=pdp``, the ``lerobot_pdp/*-v0`` gym ids and the
``--env.type=pdp_*`` LeRobot env configs, plus ``--robot.type=pdp_sim`` and ``--teleop.type=pdp_waypoints``;
on LeRobot <= 0.6.1 it also makes dataset delta queries read single columns (``column_views``).
"""

from lerobot_pdp import (
    baselines,  # noqa: F401  (registers `--policy.type=mlp_bc`)
    envs,  # noqa: F401  (registers gym ids and `--env.type=pdp_*`)
    robots,  # noqa: F401  (registers `--robot.type=pdp_sim`)
    teleoperators,  # noqa: F401  (registers `--teleop.type=pdp_waypoints`)
)
from lerobot_pdp.column_views import install as _install_column_views
from lerobot_pdp.configuration_pdp import PDPConfig
from lerobot_pdp.modeling_pdp import PDPPolicy
from lerobot_pdp.processor_pdp import make_pdp_pre_post_processors

_install_column_views()  # LeRobot <= 0.6.1 reads whole rows per delta query: see column_views.py

__all__ = ["PDPConfig", "PDPPolicy", "make_pdp_pre_post_processors"]
__version__ = "0.1.0"
