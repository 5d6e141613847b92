"""What ``lerobot-record`` lacks for a simulated robot, added around two of its module-level functions.

LeRobot's record loop (0.6.x) has no "episode done" signal (episodes last ``--dataset.episode_time_s`` of wall
time unless a person presses the next-episode key) and turns every float observation into one
``observation.state`` vector. For a ``pdp_sim`` robot, and only then, the hooks:

* wrap ``record_loop`` to tell the robot whether a record or a reset phase runs and hand it the keyboard
  ``events`` dict, so the robot ends the recorded episode when the env episode ends (it sets
  ``events["exit_early"]``, the flag the next-episode key sets) and holds still while "resetting";
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

from .live import LIVE

logger = logging.getLogger(__name__)

RECORD_MODULE = "lerobot.scripts.lerobot_record"
_MARK = "_pdp_sim_hook"


def install() -> bool:
    """Wrap the record script's functions once; False when ``lerobot-record`` is not running here."""
    mod = sys.modules.get(RECORD_MODULE)
    if mod is None:
        main = sys.modules.get("__main__")
        mod = main if main is not None and hasattr(main, "record_loop") and hasattr(main, "RecordConfig") else None
    if mod is None:
        return False
    loop, agg = getattr(mod, "record_loop", None), getattr(mod, "aggregate_pipeline_dataset_features", None)
    if loop is None or agg is None:
        logger.warning("pdp_sim: this lerobot-record has no record_loop/aggregate_pipeline_dataset_features; "
                       "episodes will end on episode_time_s only and environment_state stays in the state")
        return False
    if not getattr(loop, _MARK, False):
        mod.record_loop = _wrap_record_loop(loop)
    if not getattr(agg, _MARK, False):
        mod.aggregate_pipeline_dataset_features = _wrap_aggregate(agg)
    return True


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
        robot.begin_phase(events, recording=recording, dataset=dataset)
        try:
            result = original(*args, **kwargs)
        except BaseException:
            robot.abort_phase()  # Ctrl-C / an error: LeRobot drops the unsaved episode, so no label for it
            raise
        robot.end_phase(events, recording=recording, dataset=dataset, single_task=kwargs.get("single_task"))
        return result

    setattr(record_loop, _MARK, True)
    return record_loop


def split_environment_state(features: dict[str, dict], state_names: list[str],
                            env_state_names: list[str]) -> dict[str, dict]:
    """``observation.state`` with names ``state + env_state`` -> the two features make-dataset writes."""
    state = features.get("observation.state")
    if state is None or list(state.get("names") or []) != state_names + env_state_names or not env_state_names:
        return features
    out = {k: v for k, v in features.items() if k != "observation.state"}
    out["observation.state"] = {**state, "shape": (len(state_names),), "names": list(state_names)}
    out["observation.environment_state"] = {**state, "shape": (len(env_state_names),),
                                            "names": list(env_state_names)}
    return out


def _wrap_aggregate(original):
    @functools.wraps(original)
    def aggregate_pipeline_dataset_features(*args: Any, **kwargs: Any):
        features = original(*args, **kwargs)
        for robot in list(LIVE.values()):
            features = split_environment_state(features, robot.state_names, robot.env_state_names)
        return features

    setattr(aggregate_pipeline_dataset_features, _MARK, True)
    return aggregate_pipeline_dataset_features
