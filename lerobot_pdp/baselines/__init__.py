"""Baseline policies of the PDP benchmark that LeRobot does not ship.

Importing this package registers ``--policy.type=mlp_bc`` (MLP behavior cloning). LeRobot then finds
``MLPBCPolicy`` in ``modeling_mlp_bc`` and ``make_mlp_bc_pre_post_processors`` in ``processor_mlp_bc`` by
its naming convention (``MLPBCConfig`` -> ``MLPBC`` + ``Policy``; ``configuration_`` -> ``modeling_`` /
``processor_``). The DP baseline is LeRobot's own ``diffusion`` policy (see ``lerobot_pdp.benchmark.baselines``).
"""

from .configuration_mlp_bc import MLPBCConfig
from .modeling_mlp_bc import MLPBCPolicy
from .processor_mlp_bc import make_mlp_bc_pre_post_processors

__all__ = ["MLPBCConfig", "MLPBCPolicy", "make_mlp_bc_pre_post_processors"]
