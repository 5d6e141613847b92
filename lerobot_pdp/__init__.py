"""lerobot-pdp: Parameterized Diffusion Policies as a LeRobot policy plugin.

``import lerobot_pdp`` registers ``--policy.type=pdp`` and nothing else: it imports the policy, its config and
its processors (no simulator, robot or teleoperator, and no change to any LeRobot class). The lab beside it
registers through LeRobot's own plugin discovery, from its own small distributions: ``lerobot_env_pdp``
(``--env.type=pdp_*``, ``lerobot_pdp.envs``), ``lerobot_robot_pdp`` (``--robot.type=pdp_sim``),
``lerobot_teleoperator_pdp`` (``--teleop.type=pdp_waypoints``) and ``lerobot_policy_pdp_baselines``
(``--policy.type=mlp_bc``). The faster dataset reading of ``column_views`` is switched on explicitly.
"""

from lerobot_pdp.configuration_pdp import PDPConfig
from lerobot_pdp.modeling_pdp import PDPPolicy
from lerobot_pdp.processor_pdp import make_pdp_pre_post_processors

__all__ = ["PDPConfig", "PDPPolicy", "make_pdp_pre_post_processors"]
__version__ = "0.1.0"
