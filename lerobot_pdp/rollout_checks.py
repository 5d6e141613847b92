"""``lerobot-rollout`` on any robot: the robot's values checked against the data the PDP policy was trained on.

LeRobot checks a robot's features against the policy's by key and shape at most; a robot whose joints are listed in
another order than the training dataset's (another robot config, a driver update) is read position by position,
each joint taken for another, and a loop run at another ``--fps`` than the data was recorded at moves the robot
faster or slower than demonstrated, both without a word. Checkpoints keep the training data's value names and frame
rate (``PDPConfig.dataset_feature_names``, ``dataset_fps``); :func:`install` wraps the rollout context's
``create_inference_engine``, which sees the robot's dataset features and ``--fps`` before the first action. Other
policies' runs are untouched; checkpoints without these fields are not checked.
"""

from __future__ import annotations

import functools
import logging
import sys
from typing import Any

from .episodes import order_problems, simulated_robot

logger = logging.getLogger(__name__)

CONTEXT_MODULE = "lerobot.rollout.context"


def check_robot_against_training_data(policy_config: Any, dataset_features: dict[str, dict], fps: float | None,
                                      robot: str, rename_map: dict[str, str] | None = None) -> None:
    """The robot's values named in another order than the training data's are refused (a ValueError naming both);
    a loop ``fps`` other than the training data's warns (the robot moves fps / dataset_fps as fast as demonstrated).
    ``dataset_features``: the robot's, in dataset format, under the names ``rename_map`` gives them."""
    renames = rename_map or {}
    features = {renames.get(k, k): v for k, v in dataset_features.items()}
    problems = order_problems(getattr(policy_config, "dataset_feature_names", None) or {}, features)
    if problems:
        raise ValueError(f"the robot ({robot}) does not give its values as the policy was trained on them: "
                         + "; ".join(problems))
    warn_other_fps(policy_config, fps, robot, "lerobot-rollout")


def warn_other_fps(policy_config: Any, fps: float | None, robot: str, command: str) -> bool:
    """Warn (and return True) when a control loop at ``fps`` drives a real robot with a policy whose training data
    was recorded at another rate: the robot moves fps / dataset_fps as fast as demonstrated. Simulated robots step
    once per action whatever the pace; checkpoints without ``dataset_fps`` are not checked."""
    trained_fps = getattr(policy_config, "dataset_fps", None)
    if simulated_robot(robot) or not trained_fps or not fps or abs(float(fps) - float(trained_fps)) <= 1e-6:
        return False
    logger.warning("%s runs at --fps=%g, the policy's training data was recorded at %g fps: an action is sent every "
                   "1/%g s, so the robot moves %.2fx as fast as demonstrated (--fps=%g runs it as trained)", command,
                   fps, trained_fps, fps, fps / trained_fps, trained_fps)
    return True


def preprocessor_renames(preprocessor: Any) -> dict[str, str]:
    """``--rename_map`` as the rollout's preprocessor applies it (its rename step's map; {} without one)."""
    steps = getattr(preprocessor, "steps", [])
    return next((s.rename_map for s in steps if isinstance(getattr(s, "rename_map", None), dict)), {})


def _checking(original: Any) -> Any:
    @functools.wraps(original)
    def create_inference_engine(*args: Any, **kwargs: Any):
        policy = kwargs.get("policy")
        if getattr(getattr(policy, "config", None), "type", None) == "pdp":
            wrapper = kwargs.get("robot_wrapper")
            robot = getattr(wrapper, "inner", wrapper)
            check_robot_against_training_data(policy.config, kwargs.get("dataset_features") or {}, kwargs.get("fps"),
                                              str(getattr(robot, "name", type(robot).__name__)),
                                              preprocessor_renames(kwargs.get("preprocessor")))
        return original(*args, **kwargs)

    create_inference_engine.pdp_checks_training_data = True
    return create_inference_engine


def install() -> bool:
    """Wrap ``create_inference_engine`` once; False when LeRobot's rollout is not loaded (any other command)."""
    context = sys.modules.get(CONTEXT_MODULE)
    original = getattr(context, "create_inference_engine", None)
    if original is None:
        return False
    if not getattr(original, "pdp_checks_training_data", False):
        context.create_inference_engine = _checking(original)
    return True
