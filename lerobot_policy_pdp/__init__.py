"""Entry module that LeRobot's plugin discovery imports (it imports the distribution name).

Importing it registers ``--policy.type=pdp`` and the ``pdp_*`` env types; the code lives in ``lerobot_pdp``.
"""

from lerobot_pdp import *  # noqa: F401,F403
from lerobot_pdp import __all__  # noqa: F401
