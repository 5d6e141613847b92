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
import json
import logging
import sys
from pathlib import Path
from typing import Any

from .episodes import feature_problems, order_problems, simulated_robot

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


def rollout_context_locals(max_depth: int = 16) -> dict[str, Any] | None:
    """The locals of ``lerobot.rollout.context.build_rollout_context`` when it is up the call stack (within
    ``max_depth`` frames of the caller: its ``cfg`` is the run's ``RolloutConfig``), else None. Precise where a
    ``sys.modules`` test is not: a test process may have imported LeRobot's rollout package without running it."""
    frame = sys._getframe(1)
    for _ in range(max_depth):
        if frame is None:
            return None
        if frame.f_code.co_name == "build_rollout_context" and frame.f_globals.get("__name__") == CONTEXT_MODULE:
            return frame.f_locals
        frame = frame.f_back
    return None


def robot_cameras(robot_config: Any) -> dict[str, dict] | None:
    """The cameras a robot config will give, as dataset features ((H, W, 3)), read before the robot connects:
    ``pdp_sim``'s ``camera_names`` / ``camera_size``, or LeRobot's ``cameras`` (each with its width and height);
    None when the config does not say."""
    names, size = getattr(robot_config, "camera_names", None), getattr(robot_config, "camera_size", None)
    if names is not None and size is not None:
        return {f"observation.images.{n}": {"dtype": "video", "shape": (size[0], size[1], 3)} for n in names}
    cams = getattr(robot_config, "cameras", None)
    if isinstance(cams, dict) and all(getattr(c, "width", None) and getattr(c, "height", None) for c in cams.values()):
        return {f"observation.images.{n}": {"dtype": "video", "shape": (c.height, c.width, 3)} for n, c in cams.items()}
    return None


def check_rollout_cameras(policy_config: Any) -> None:
    """Under ``lerobot-rollout``, before a start-up fit: the robot's cameras (from its config; LeRobot connects it
    after loading the policy) must be the policy's, else the fit's seconds to minutes end in that refusal anyway.
    Not checked under ``--rename_map`` or where the robot's config does not say (the full check comes later)."""
    cfg = (rollout_context_locals() or {}).get("cfg")
    need = {k: tuple(ft.shape) for k, ft in (getattr(policy_config, "image_features", None) or {}).items()}
    if cfg is None or not need or getattr(cfg, "rename_map", None) or _saved_renames(cfg):
        return
    have = robot_cameras(getattr(cfg, "robot", None))
    problems = [] if have is None else feature_problems(need, have)
    if problems:
        robot = getattr(getattr(cfg, "robot", None), "type", "the robot")
        raise ValueError(f"the robot ({robot}) does not give the cameras the policy needs: {'; '.join(problems)}; "
                         "refused before the start-up fit (its cameras: --robot.camera_names / --robot.camera_size "
                         "for pdp_sim, --robot.cameras otherwise)")


def _saved_renames(cfg: Any) -> bool:
    """Whether the checkpoint's own preprocessor renames features (a training run's ``--rename_map``), or cannot be
    read here: then the robot's camera names are not the policy's, and only the later check can tell."""
    path = getattr(getattr(cfg, "policy", None), "pretrained_path", None)
    try:
        steps = json.loads((Path(path) / "policy_preprocessor.json").read_text())["steps"]
        return any((step.get("config") or {}).get("rename_map") for step in steps)
    except (OSError, TypeError, ValueError, KeyError, AttributeError):
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
