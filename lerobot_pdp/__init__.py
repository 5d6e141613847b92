"""lerobot-pdp: Parameterized Diffusion Policies as a LeRobot policy plugin."""

from lerobot_pdp import envs  # noqa: F401  (registers gym ids and `--env.type=pdp_*`)

__all__ = ["envs"]
