"""Wrapping a LeRobot script's module-level functions once, and the feature split both scripts need.

``lerobot-record`` and ``lerobot-rollout`` look their helpers up as module globals at call time, so a
``pdp_sim`` robot adds what they lack for a simulator by replacing those globals with wrappers
(:mod:`.record_hooks`, :mod:`.rollout_hooks`). Nothing of LeRobot is changed on disk, a wrapper is installed at
most once per function, and every wrapper passes other robots' calls through unchanged.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Iterable
from types import ModuleType
from typing import Any

logger = logging.getLogger(__name__)

_MARK = "_pdp_sim_hook"


def wrap_once(module: ModuleType | None, name: str, make_wrapper: Callable[[Callable], Callable]) -> bool:
    """Replace ``module.name`` by ``make_wrapper(original)`` unless already wrapped; False if it is missing."""
    original = getattr(module, name, None)
    if original is None:
        return False
    if not getattr(original, _MARK, False):
        wrapper = make_wrapper(original)
        setattr(wrapper, _MARK, True)
        setattr(module, name, wrapper)
    return True


def wrap_all(module: ModuleType | None, wrappers: dict[str, Callable[[Callable], Callable]], script: str,
             lost: str) -> bool:
    """Wrap each function ``wrappers`` names in ``module`` once (name -> wrapper factory). False, wrapping
    nothing, when ``module`` is not loaded; or when it lacks one of them (another LeRobot): a warning names
    ``script``, what it lacks and what is ``lost``."""
    if module is None:
        return False
    missing = [name for name in wrappers if not hasattr(module, name)]
    if missing:
        logger.warning("pdp_sim: this %s has no %s; %s", script, "/".join(missing), lost)
        return False
    for name, make in wrappers.items():
        wrap_once(module, name, make)
    return True


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


def splitting_features(robots: Callable[[], Iterable[Any]]) -> Callable[[Callable], Callable]:
    """A wrapper factory for ``aggregate_pipeline_dataset_features``: LeRobot merges every float observation
    into ``observation.state``; split it back by the names of each of ``robots()`` (``state_keys`` /
    ``env_state_keys``, the names LeRobot sees), the layout PDP's datasets and checkpoints use."""

    def make(original: Callable) -> Callable:
        @functools.wraps(original)
        def aggregate_pipeline_dataset_features(*args: Any, **kwargs: Any):
            features = original(*args, **kwargs)
            for robot in robots():
                features = split_environment_state(features, robot.state_keys, robot.env_state_keys)
            return features

        return aggregate_pipeline_dataset_features

    return make
