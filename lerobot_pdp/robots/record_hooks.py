"""What ``lerobot-record`` lacks for a simulated robot, added around two of its module-level functions.

LeRobot's record loop (0.6.x) has no "episode done" signal (episodes last ``--dataset.episode_time_s`` of wall
time unless a person presses the next-episode key) and turns every float observation into one
``observation.state`` vector. For a ``pdp_sim`` robot, and only then, the hooks:

* wrap ``record_loop`` to tell the robot whether a record or a reset phase runs and hand it the keyboard
  ``events`` dict, so the robot ends the recorded episode when the env episode ends (it sets
  ``events["exit_early"]``, the flag the next-episode key sets) and holds still while "resetting";
* put the record loop back to the CPU priority the process had when the robot was made: LeRobot's AV1 encoder
  leaves the process at real-time priority after it saved an episode with cameras (:mod:`lerobot_pdp.cpu_priority`);
* wrap ``aggregate_pipeline_dataset_features`` to split ``observation.state`` into ``observation.state`` and
  ``observation.environment_state`` by name, the layout ``make-dataset`` writes (``build_dataset_frame``
  fills both by name, so frames need nothing else).

They are installed when a ``pdp_sim`` robot is created inside ``lerobot-record`` and do nothing for other robots.
"""

from __future__ import annotations

import functools
import logging
import sys
from typing import Any

from .. import cpu_priority
from .hooks import splitting_features, wrap_all
from .live import LIVE

logger = logging.getLogger(__name__)

RECORD_MODULE = "lerobot.scripts.lerobot_record"


# the process's scheduling before any episode was encoded (taken when the first pdp_sim robot installs the hooks)
_SCHEDULING: list[cpu_priority.Scheduling | None] = []


def install() -> bool:
    """Wrap the record script's functions once; False when ``lerobot-record`` is not running here."""
    if not _SCHEDULING:
        _SCHEDULING.append(cpu_priority.current())
    mod = sys.modules.get(RECORD_MODULE)
    if mod is None:
        main = sys.modules.get("__main__")
        mod = main if main is not None and hasattr(main, "record_loop") and hasattr(main, "RecordConfig") else None
    return wrap_all(mod, {"record_loop": _wrap_record_loop,
                          "aggregate_pipeline_dataset_features": splitting_features(lambda: list(LIVE.values()))},
                    "lerobot-record", "episodes will end on episode_time_s only and environment_state stays in the state")


def _wrap_record_loop(original):
    @functools.wraps(original)
    def record_loop(*args: Any, **kwargs: Any):
        robot = kwargs.get("robot", args[0] if args else None)
        events = kwargs.get("events", args[1] if len(args) > 1 else None)
        if not any(robot is r for r in LIVE.values()) or not isinstance(events, dict):  # not a pdp_sim robot
            return original(*args, **kwargs)
        dataset = kwargs.get("dataset")
        recording = dataset is not None
        fps = kwargs.get("fps")
        if recording and fps is not None and int(fps) != robot.suite.fps:
            logger.warning("pdp_sim: recording at %s fps; make-dataset writes %s fps for %s", fps,
                           robot.suite.fps, robot.suite.name)
        if _SCHEDULING and cpu_priority.restore(_SCHEDULING[0]):
            logger.info("pdp_sim: the video encoder had left this process at real-time priority: set back")
        robot.begin_phase(events, recording=recording, dataset=dataset)
        try:
            result = original(*args, **kwargs)
        except BaseException:
            robot.abort_phase()  # Ctrl-C / an error: LeRobot drops the unsaved episode, so no label for it
            raise
        robot.end_phase(events, recording=recording, dataset=dataset, single_task=kwargs.get("single_task"))
        return result

    return record_loop
