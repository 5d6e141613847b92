"""Entry module that LeRobot's plugin discovery imports (it imports the distribution name).

Importing it registers ``--policy.type=pdp``; the code lives in ``lerobot_pdp``. A process started with
``LEROBOT_PDP_COLUMN_VIEWS=1`` (the benchmark's trainings) also gets LeRobot's dataset delta queries read one
column at a time on LeRobot <= 0.6.1 (``lerobot_pdp.column_views``).
"""

from lerobot_pdp import *  # noqa: F401,F403
from lerobot_pdp import __all__  # noqa: F401
from lerobot_pdp import column_views as _column_views

if _column_views.requested():
    _column_views.install()
