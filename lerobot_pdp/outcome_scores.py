"""What a rollout achieved, and the scores a latent search maximises: task success, summed reward, or way-points
passed in order.

A score is any ``Callable[[Outcome], float]`` (higher is better); a candidate latent's score is the mean over
its rollouts. Way-points steer without a demonstration: the user says where the agent should pass, not how to
move, and :func:`waypoint_progress` turns a path into a graded score so a search can climb towards them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .search_defaults import WAYPOINT_RADIUS


@dataclass(frozen=True)
class Outcome:
    """One rollout, as a score sees it."""

    success: bool  # the env's final info["is_success"]
    reward: float  # summed over the episode
    states: np.ndarray  # [T + 1, S] the env's ``agent_pos`` from the reset on ([0, 0]: the env has none)
    info: dict[str, Any] = field(default_factory=dict)  # the final info


Score = Callable[[Outcome], float]


def success(outcome: Outcome) -> float:
    """1 for a rollout the env counts as a success, else 0."""
    return float(outcome.success)


def total_reward(outcome: Outcome) -> float:
    """The episode's summed reward."""
    return float(outcome.reward)


SCORES: dict[str, Score] = {"success": success, "reward": total_reward}


def waypoint_progress(path: np.ndarray, waypoints: np.ndarray, radius: float) -> float:
    """How far ``path`` [T, D] gets through ``waypoints`` [K, D], passed in order within ``radius``: in [0, 1].

    Each way-point counts once the path comes within ``radius`` of it after passing the previous one (its first
    such time: the earliest pass leaves the most path for the rest); 1.0 = all K passed. The first way-point not
    reached adds ``radius / closest distance`` (< 1) from that time on, so a path that comes closer scores higher
    and a search has a slope to climb; passing one more way-point always beats coming close to it.
    """
    p, w = np.asarray(path, dtype=float), np.asarray(waypoints, dtype=float)
    if w.ndim != 2 or len(w) == 0:
        raise ValueError(f"way-points must be a non-empty [K, D] array, got shape {w.shape}")
    if p.ndim != 2 or p.shape[1] != w.shape[1]:
        raise ValueError(f"path must be [T, {w.shape[1]}] (the way-points' dims), got shape {p.shape}")
    if not radius > 0:
        raise ValueError(f"radius must be > 0, got {radius}")
    start = 0
    for k, point in enumerate(w):
        d = np.linalg.norm(p[start:] - point, axis=1)
        if len(d) == 0:
            return k / len(w)
        hit = np.flatnonzero(d <= radius)
        if len(hit) == 0:
            return (k + radius / float(d.min())) / len(w)
        start += int(hit[0])
    return 1.0


class WaypointScore:
    """Score a rollout by :func:`waypoint_progress` of its path: the ``dims`` of ``agent_pos`` (default the
    first D, D = the way-points' width; positions come first in every suite env).

    ``finish``: a rollout that passes every way-point and then succeeds (the env's own success) scores 2, one
    that passes them all and fails 1: way-point progress ranks routes, not whether they end in the task done, and
    a search by progress alone can trade a finishing route for one that passes the points and stops short."""

    def __init__(self, waypoints: Sequence[Sequence[float]] | np.ndarray, radius: float = WAYPOINT_RADIUS,
                 dims: Sequence[int] | None = None, finish: bool = False):
        w = np.asarray(waypoints, dtype=float)
        if w.ndim != 2 or len(w) == 0 or not np.all(np.isfinite(w)):
            raise ValueError(f"way-points must be a non-empty list of finite points of one size, got {waypoints!r}")
        if not (isinstance(radius, (int, float)) and math.isfinite(radius) and radius > 0):
            raise ValueError(f"way-point radius must be a finite number > 0, got {radius!r}")
        self.dims = list(range(w.shape[1])) if dims is None else [int(d) for d in dims]
        if len(self.dims) != w.shape[1]:
            raise ValueError(f"way-points have {w.shape[1]} coordinates but the path has {len(self.dims)} "
                             f"(dims {self.dims})")
        self.waypoints, self.radius, self.finish = w, float(radius), bool(finish)

    def __call__(self, outcome: Outcome) -> float:
        s = outcome.states
        if s.ndim != 2 or len(s) == 0 or s.shape[1] <= max(self.dims):
            raise ValueError(f"the way-point score reads the agent's positions (dims {self.dims} of the env's "
                             f"'agent_pos'); this env's rollout recorded states of shape {s.shape}")
        progress = waypoint_progress(s[:, self.dims], self.waypoints, self.radius)
        return progress + float(self.finish and progress >= 1.0 and bool(outcome.success))

    def check_env(self, env: Any) -> None:
        """Way-points the agent of ``env`` can pass: inside its workspace where it declares one (the suite envs'
        ``workspace_low`` / ``workspace_high``, one bound per path dim); else a ValueError naming the point."""
        low, high = getattr(env.unwrapped, "workspace_low", None), getattr(env.unwrapped, "workspace_high", None)
        if low is None or high is None:
            return
        low, high = np.asarray(low, float), np.asarray(high, float)
        if len(low) != len(self.dims) or len(high) != len(self.dims):
            raise ValueError(f"way-points have {len(self.dims)} coordinates; this env's path has {len(low)} (its "
                             f"workspace {low.tolist()} .. {high.tolist()})")
        for i, p in enumerate(self.waypoints):
            if np.any(p < low) or np.any(p > high):
                raise ValueError(f"way-point {i} {p.tolist()} lies outside the env's workspace {low.tolist()} .. "
                                 f"{high.tolist()}: the agent can never pass it")

    def describe(self) -> dict[str, Any]:
        d: dict[str, Any] = {"waypoints": self.waypoints.tolist(), "radius": self.radius, "dims": self.dims}
        if self.finish:  # absent otherwise: searches recorded before the option existed keep their provenance
            d["finish"] = True
        return d


def resolve_score(score: str | Score) -> tuple[Score, Any]:
    """The score callable and how it is recorded in a search's provenance."""
    if isinstance(score, str):
        if score not in SCORES:
            raise ValueError(f"score must be one of {sorted(SCORES)}, a WaypointScore or a callable, got {score!r}")
        return SCORES[score], score
    if not callable(score):
        raise TypeError(f"score must be one of {sorted(SCORES)}, a WaypointScore or a callable, got "
                        f"{type(score).__name__}")
    describe = getattr(score, "describe", None)
    return score, describe() if callable(describe) else getattr(score, "__name__", type(score).__name__)
