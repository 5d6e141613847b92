"""Entry module that LeRobot's plugin discovery imports (it imports the distribution name).

Importing it registers ``--policy.type=pdp``; the code lives in ``lerobot_pdp``. A process started with
``LEROBOT_PDP_COLUMN_VIEWS=1`` (the benchmark's trainings) also gets LeRobot's dataset delta queries read one
column at a time on LeRobot <= 0.6.1 (``lerobot_pdp.column_views``). On a machine without FFmpeg, LeRobot's
"torchcodec cannot be loaded" warning (a hundred lines of tracebacks) is reported in one line
(``lerobot_pdp.console``); every ``lerobot-*`` command imports this module first, before it builds any config.
An error PDP raises on purpose ends those commands with its message, not under a traceback
(``lerobot_pdp.cli_errors``), and ``lerobot-rollout`` exits 1 when LeRobot's RTC engine gave up on PDP's chunks
(``lerobot_pdp.realtime_chunking.install_exit_status``), and checks a robot's values against the training data's
before the first action (``lerobot_pdp.rollout_checks``).
"""

from lerobot_pdp import *  # noqa: F401,F403
from lerobot_pdp import __all__  # noqa: F401
from lerobot_pdp import cli_errors as _cli_errors
from lerobot_pdp import column_views as _column_views
from lerobot_pdp import console as _console
from lerobot_pdp import realtime_chunking as _realtime_chunking
from lerobot_pdp import rollout_checks as _rollout_checks

_console.install()
_cli_errors.install()
_realtime_chunking.install_exit_status()
_rollout_checks.install()

if _column_views.requested():
    _column_views.install()
