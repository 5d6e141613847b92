"""``lerobot_pdp/ReachAround-v0``: a 3-D point end effector reaches around a box (the paper's CloseDrawer analog).

Eight training modes = 4 sides (over / left / right / under) x {tight, wide}: tight routes pass ~0.13 m off
the obstacle centre, wide ones ~0.25 m (benchmark.md reference geometry). "Left" is -x for an effector
travelling along +y. Scenes 1-3 add barriers that leave one mode (1: over-tight, 2: left-wide) or no mode
(3: only a diagonal window) feasible.

Layouts:
    observation.state (6): ee x, y, z, then ee vx, vy, vz.
    observation.environment_state (6): goal x, y, z, obstacle centre x, y, z (scene 0; same in all scenes).
    action (3): velocity fractions of 0.5 m/s along x, y, z.
    observation.images.<camera> (with ``camera=``): "top" (looking down, +y up in the image), "front"
        (from behind the start, looking along +y: shows over/under/left/right and scene 3's window) or
        "oblique"; see :data:`CAMERAS`.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from .camera import CameraSpec
from .point_mass import PointMassEnv, WaypointExpert, make_waypoint_expert, register_gym
from .scene import Barrier
from .suite import NOVEL, SuiteEnv, register_suite_env

GYM_ID = "lerobot_pdp/ReachAround-v0"
MODE_NAMES = (
    "over-tight",
    "over-wide",
    "left-tight",
    "left-wide",
    "right-tight",
    "right-wide",
    "under-tight",
    "under-wide",
)
# Direction (x, z) of each side, seen from the start looking along +y.
SIDES = {"over": (0.0, 1.0), "left": (-1.0, 0.0), "right": (1.0, 0.0), "under": (0.0, -1.0)}
OFFSETS = {"tight": 0.13, "wide": 0.25}
START = (0.0, -0.30, 0.40)
GOAL = (0.0, 0.30, 0.40)
OBSTACLE_CENTER = (0.0, 0.0, 0.40)
OBSTACLE_HALF = (0.08, 0.04, 0.08)
PASS_Y = 0.12  # template way-points sit at y = -/+ PASS_Y, well before/after the obstacle's y extent
WAYPOINT_JITTER = 0.012
MAX_STEPS = 200
CAMERAS = (
    CameraSpec("top", eye=(0.0, 0.0, 2.2), target=(0.0, 0.0, 0.4), up=(0.0, 1.0, 0.0), fovy=30.0),
    CameraSpec("front", eye=(0.0, -1.9, 0.45), target=(0.0, 0.0, 0.4), fovy=34.0),
    CameraSpec("oblique", eye=(0.9, -1.0, 1.0), target=(0.0, 0.0, 0.38), fovy=45.0),
)


class ReachAroundEnv(PointMassEnv):
    """Reach from (0, -0.3, 0.4) to (0, 0.3, 0.4) around a box centred between them."""

    dims: ClassVar[int] = 3
    scene_key: ClassVar[str] = "reach_around"
    mode_names: ClassVar[tuple[str, ...]] = MODE_NAMES
    start: ClassVar[tuple[float, ...]] = START
    goal: ClassVar[tuple[float, ...]] = GOAL
    ee_radius: ClassVar[float] = 0.015
    max_speed: ClassVar[float] = 0.5
    workspace_low: ClassVar[tuple[float, ...]] = (-0.5, -0.45, 0.02)
    workspace_high: ClassVar[tuple[float, ...]] = (0.5, 0.45, 0.8)
    default_episode_length: ClassVar[int] = MAX_STEPS
    goal_tolerance: ClassVar[float] = 0.03
    render_views: ClassVar[tuple[tuple[int, int], ...]] = ((0, 1), (0, 2))  # top (x-y), front (x-z)
    task_text: ClassVar[str] = "reach the goal around the box"
    camera_specs: ClassVar[tuple[CameraSpec, ...]] = CAMERAS

    @classmethod
    def builtin_obstacles(cls) -> tuple[Barrier, ...]:
        return (Barrier("box", OBSTACLE_CENTER, half_size=OBSTACLE_HALF, name="box"),)

    def goal_reached(self, pos: np.ndarray) -> bool:
        return bool(np.linalg.norm(np.asarray(pos) - np.asarray(GOAL)) < self.goal_tolerance)

    @classmethod
    def classify(cls, positions: np.ndarray) -> int | str:
        return classify_positions(positions)


def mode_waypoints(mode: int) -> np.ndarray:
    """Template route of a training mode: start, beside the box before and after it, goal."""
    if not isinstance(mode, (int, np.integer)) or not 0 <= int(mode) < len(MODE_NAMES):
        raise ValueError(f"reach-around mode must be an int in [0, {len(MODE_NAMES) - 1}], got {mode!r}")
    side, width = MODE_NAMES[int(mode)].split("-")
    dx, dz = SIDES[side]
    off = OFFSETS[width]
    cx, _, cz = OBSTACLE_CENTER
    a = (cx + dx * off, -PASS_Y, cz + dz * off)
    b = (cx + dx * off, PASS_Y, cz + dz * off)
    return np.array([START, a, b, GOAL], dtype=float)


def classify_positions(positions: np.ndarray) -> int | str:
    """Label a path by where it crosses the obstacle's mid-plane y = 0.

    The crossing's offset from the obstacle centre gives the side (dominant axis of (x, z)) and the
    width (< 0.19 m tight, < 0.34 m wide). A path that never crosses, crosses diagonally (both offsets
    > 0.07 m, like scene 3's window route) or crosses too far out is ``"novel"``.
    """
    p = np.asarray(positions, dtype=float)
    if p.ndim != 2 or p.shape[1] < 3:
        raise ValueError(f"expected a (T, >=3) array of positions, got shape {p.shape}")
    y = p[:, 1] - OBSTACLE_CENTER[1]
    idx = np.nonzero((y[:-1] < 0) & (y[1:] >= 0))[0]
    if len(idx) == 0:
        return NOVEL
    k = int(idx[0])
    t = -y[k] / (y[k + 1] - y[k]) if y[k + 1] != y[k] else 0.0
    cross = p[k] + t * (p[k + 1] - p[k])
    dx = cross[0] - OBSTACLE_CENTER[0]
    dz = cross[2] - OBSTACLE_CENTER[2]
    if min(abs(dx), abs(dz)) > 0.07:
        return NOVEL
    r = max(abs(dx), abs(dz))
    if abs(dx) >= abs(dz):
        side = "left" if dx < 0 else "right"
    else:
        side = "over" if dz > 0 else "under"
    if r < 0.19:
        width = "tight"
    elif r < 0.34:
        width = "wide"
    else:
        return NOVEL
    return MODE_NAMES.index(f"{side}-{width}")


# ---- module-level functions used through SuiteEnv ----------------------------------------------------


def make_expert(mode: int, rng: np.random.Generator, scene: Any = 0) -> WaypointExpert:
    """Scripted demonstrator of a training mode, with seeded way-point, speed and timing jitter."""
    return make_waypoint_expert(
        mode_waypoints(mode), rng, dims=3, max_speed=ReachAroundEnv.max_speed, dt=0.02, jitter=WAYPOINT_JITTER
    )


def expert_from_waypoints(waypoints: Any, rng: np.random.Generator, scene: Any = 0) -> WaypointExpert:
    """Demonstrator along arbitrary 3-D way-points (e.g. a scene file's ``waypoints``); ends at the goal.

    The goal is appended if the route does not end there; jitter is smaller than for templates because the
    clearances of a new route are unknown.
    """
    wps = np.asarray(waypoints, dtype=float)
    if wps.ndim != 2 or wps.shape[1] != 3 or len(wps) == 0:
        raise ValueError(f"reach-around way-points must be a list of [x, y, z] points, got {np.shape(waypoints)}")
    if np.linalg.norm(wps[-1] - np.asarray(GOAL)) > 1e-6:
        wps = np.vstack([wps, GOAL])
    return make_waypoint_expert(wps, rng, dims=3, max_speed=ReachAroundEnv.max_speed, dt=0.02, jitter=0.006)


def classify_mode(states: np.ndarray, scene: Any = 0) -> int | str:
    """Mode id of a trajectory of ``observation.state`` rows (position first), or ``"novel"``."""
    return classify_positions(np.asarray(states)[:, :3])


def static_primitives(scene: Any = 0) -> tuple[Barrier, ...]:
    """Built-in obstacles left in ``scene`` (for plotting)."""
    return ReachAroundEnv.static_primitives(scene)


LANDMARKS = {"start": START, "goal": GOAL}

SUITE_ENV = register_suite_env(
    SuiteEnv(
        name="reach-around",
        gym_id=GYM_ID,
        scene_key="reach_around",
        lerobot_env_type="pdp_reach_around",
        module=__name__,
        mode_names=MODE_NAMES,
        trace_dims=(0, 1, 2),
        max_episode_steps=MAX_STEPS,
        fps=50,
    )
)
register_gym(GYM_ID, f"{__name__}:ReachAroundEnv")
