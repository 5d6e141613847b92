"""What ``lerobot-rollout`` lacks for a simulated robot, added around three functions it calls.

LeRobot's rollout (0.6.x) routes only scalar features named ``*.pos`` / ``*.vel`` to the policy (the rest are
dropped silently), merges every float observation into one ``observation.state``, has no notion of an
episode (the policy is reset once, and ``--duration`` bounds the run in wall time) and gives the robot no
way to end the run. For a ``pdp_sim`` robot built by ``build_rollout_context``, and only then:

* the robot names its features ``<name>.pos`` (observations) and ``<name>.vel`` (actions)
  (:func:`building_rollout_context` tells it, see ``PDPSim.__init__``);
* ``aggregate_pipeline_dataset_features`` is wrapped to split ``observation.state`` into ``observation.state``
  and ``observation.environment_state`` by name, the layout ``make-dataset`` writes and PDP was trained on;
* ``create_inference_engine`` is wrapped to hand the robot the engine and the run's shutdown event, so it
  resets the policy when it resets its scene (a new episode) and ends the run after ``--robot.episodes``;
  a policy whose inputs the robot does not give fails there, before the first action; the features the RTC
  engine (``--inference.type=rtc``) builds its observations from are split as above;
* the episodic strategy's ``init_keyboard_listener`` is wrapped to hand the robot its flags, so a recorded
  episode ends with its env episode (``--strategy.type=episodic``: one dataset episode per env episode).

Nothing of LeRobot is changed on disk; other robots are untouched.
"""

from __future__ import annotations

import functools
import sys
from typing import Any

from ..episodes import feature_problems, policy_shape
from ..rollout_checks import CONTEXT_MODULE, preprocessor_renames, rollout_context_locals
from .hooks import split_environment_state, splitting_features, wrap_all, wrap_once
from .live import LIVE

EPISODIC_MODULE = "lerobot.rollout.strategies.episodic"


def building_rollout_context(max_depth: int = 12) -> bool:
    """True when called (within ``max_depth`` frames) from ``lerobot.rollout.context.build_rollout_context``
    (:func:`lerobot_pdp.rollout_checks.rollout_context_locals`, one frame up from here)."""
    return rollout_context_locals(max_depth + 1) is not None


def install() -> bool:
    """Wrap the context builder's functions once; False when LeRobot's rollout is not loaded."""
    if not wrap_all(sys.modules.get(CONTEXT_MODULE), {
            "aggregate_pipeline_dataset_features": splitting_features(_rollout_robots),
            "create_inference_engine": _wrap_create_engine}, "lerobot-rollout",
            "environment_state stays in the state and episodes do not reset the policy"):
        return False
    wrap_once(sys.modules.get(EPISODIC_MODULE), "init_keyboard_listener", _wrap_keyboard)
    return True


def _rollout_robots() -> list:
    """The live pdp_sim robots that ``lerobot-rollout`` built in this process."""
    return [r for r in list(LIVE.values()) if r.in_rollout]


def _wrap_create_engine(original):
    @functools.wraps(original)
    def create_inference_engine(*args: Any, **kwargs: Any):
        wrapper = kwargs.get("robot_wrapper")
        robot = getattr(wrapper, "inner", wrapper)
        ours = [r for r in _rollout_robots() if r is robot]
        policy = kwargs.get("policy")
        if ours and policy is not None:  # before the first action: a policy for another env fails here, clearly
            check_policy_inputs(getattr(policy, "config", None), kwargs.get("dataset_features") or {}, ours[0],
                                preprocessor_renames(kwargs.get("preprocessor")))
            if kwargs.get("hw_features"):  # what the RTC engine builds observations from: the same split
                kwargs["hw_features"] = split_environment_state(kwargs["hw_features"], ours[0].state_keys,
                                                                ours[0].env_state_keys)
        engine = original(*args, **kwargs)
        for live in ours:
            live.attach_rollout(engine, kwargs.get("shutdown_event"))
        return engine

    return create_inference_engine


def _wrap_keyboard(original):
    """The episodic strategy's keyboard flags go to the robot too: it ends a recorded episode when its env
    episode ends, as ``lerobot-record`` does with the record hooks."""

    @functools.wraps(original)
    def init_keyboard_listener(*args: Any, **kwargs: Any):
        listener, events = original(*args, **kwargs)
        for robot in _rollout_robots():
            robot.attach_events(events)
        return listener, events

    return init_keyboard_listener


def check_policy_inputs(policy_config: Any, dataset_features: dict[str, dict], robot: Any,
                        rename_map: dict[str, str] | None = None) -> None:
    """The robot must give every input the policy was trained on, with its shape (PDP's trace key included), under
    the names ``rename_map`` (``--rename_map``, which the preprocessor applies) gives its features.

    LeRobot would fail later, deep in the preprocessor, or not at all for a same-sized vector of another env.
    """
    renames = rename_map or {}
    dataset_features = {renames.get(k, k): v for k, v in dataset_features.items()}
    inputs = getattr(policy_config, "input_features", None) or {}
    problems = feature_problems({k: tuple(ft.shape) for k, ft in inputs.items()}, dataset_features)
    trace_key = getattr(policy_config, "trace_key", None)
    if trace_key is not None and trace_key not in inputs and trace_key not in dataset_features:
        problems.append(f"no trace key '{trace_key}' (PDP's behavior trace)")
    if problems:
        gives = {k: policy_shape(v) for k, v in dataset_features.items() if k.startswith("observation.")}
        raise ValueError(
            f"pdp_sim ({robot.suite.name}, scene {robot.config.scene}) does not give what the policy needs: "
            + "; ".join(dict.fromkeys(problems)) + f". The robot gives {gives} (cameras as (C, H, W)): was the "
            "policy trained on another env? (cameras: --robot.camera_names, their (H, W): --robot.camera_size)")

