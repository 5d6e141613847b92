"""``lerobot_pdp/Avoiding-v0``: D3IL-style 2-D obstacle field with 24 routes (the paper's Avoiding24 analog).

A disc end effector starts at (0.525, -0.28) and must cross the finish line y > 0.35 through three rows of
posts (1, 2 and 3 posts at y = -0.10, 0.08, 0.26) between side walls at x = 0.14 and 0.86, so the rows
have 2, 3 and 4 gaps. A route is one gap per row: mode id = g1 * 12 + g2 * 4 + g3, with gaps counted
from the left (-x). Scenes 1 and 2 close every gap but one per row (modes 6 "L-M-3" and 23 "R-R-4");
scene 3 seals the last row and removes its middle post, opening x ~ 0.5 where no training route passes.

Layouts:
    observation.state (4): ee x, y, then ee vx, vy.
    observation.environment_state (13): finish-line y, then x, y of the six posts of scene 0
        (row by row, left to right); the same vector in every scene.
    action (2): velocity fractions of 0.8 m/s along x, y (routes are up to ~1.3 m long).
    observation.images.top (with ``camera="top"``): the field seen from above, +y up in the image.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from .camera import CameraSpec, Solid
from .point_mass import PointMassEnv, WaypointExpert, make_waypoint_expert, register_gym
from .scene import Barrier
from .suite import NOVEL, SuiteEnv, register_suite_env

GYM_ID = "lerobot_pdp/Avoiding-v0"
START = (0.525, -0.28)
FINISH_Y = 0.35
WALL_X = (0.14, 0.86)
# (row y, post radius, post x positions) from D3IL's layout (benchmark.md).
ROWS: tuple[tuple[float, float, tuple[float, ...]], ...] = (
    (-0.10, 0.03, (0.5,)),
    (0.08, 0.025, (0.425, 0.575)),
    (0.26, 0.025, (0.35, 0.5, 0.65)),
)
ROW_GAP_NAMES = (("L", "R"), ("L", "M", "R"), ("1", "2", "3", "4"))
MODE_NAMES = tuple(f"{a}-{b}-{c}" for a in ROW_GAP_NAMES[0] for b in ROW_GAP_NAMES[1] for c in ROW_GAP_NAMES[2])
ROW_OFFSET = 0.045  # template way-points at each gap centre, this far before and after the row
POST_HALF_HEIGHT = 0.05
MAX_STEPS = 200
CAMERAS = (CameraSpec("top", eye=(0.5, 0.04, 1.5), target=(0.5, 0.04, 0.0), up=(0.0, 1.0, 0.0), fovy=33.0),)


def gap_centers(row: int) -> tuple[float, ...]:
    """x of each gap centre in a row: midpoints between wall / post surfaces, left to right."""
    _, r, xs = ROWS[row]
    edges = [WALL_X[0]] + [e for x in xs for e in (x - r, x + r)] + [WALL_X[1]]
    return tuple((edges[2 * i] + edges[2 * i + 1]) / 2 for i in range(len(xs) + 1))


def decode_mode(mode: int) -> tuple[int, int, int]:
    if not isinstance(mode, (int, np.integer)) or not 0 <= int(mode) < len(MODE_NAMES):
        raise ValueError(f"avoiding mode must be an int in [0, {len(MODE_NAMES) - 1}], got {mode!r}")
    m = int(mode)
    return m // 12, (m % 12) // 4, m % 4


class AvoidingEnv(PointMassEnv):
    """Cross the finish line through three rows of posts without touching any."""

    dims: ClassVar[int] = 2
    scene_key: ClassVar[str] = "avoiding"
    mode_names: ClassVar[tuple[str, ...]] = MODE_NAMES
    start: ClassVar[tuple[float, ...]] = START
    goal: ClassVar[tuple[float, ...]] = (0.5, FINISH_Y + 0.02)  # a point beyond the line, for check_clear
    ee_radius: ClassVar[float] = 0.01
    max_speed: ClassVar[float] = 0.8
    # The desired position stays between the walls' inner faces and within their length, so no route
    # can slip around the outside of a wall past the rows.
    workspace_low: ClassVar[tuple[float, ...]] = (WALL_X[0], -0.34)
    workspace_high: ClassVar[tuple[float, ...]] = (WALL_X[1], 0.42)
    plane_z: ClassVar[float] = 0.0
    default_episode_length: ClassVar[int] = MAX_STEPS
    render_views: ClassVar[tuple[tuple[int, int], ...]] = ((0, 1),)
    task_text: ClassVar[str] = "cross the finish line between the posts"
    camera_specs: ClassVar[tuple[CameraSpec, ...]] = CAMERAS
    floor_z: ClassVar[float] = -POST_HALF_HEIGHT  # the posts stand on the floor

    @classmethod
    def builtin_obstacles(cls) -> tuple[Barrier, ...]:
        posts = tuple(
            Barrier("cylinder", (x, y), radius=r, half_height=POST_HALF_HEIGHT, name=f"post_r{i + 1}_{j}")
            for i, (y, r, xs) in enumerate(ROWS)
            for j, x in enumerate(xs)
        )
        walls = (
            Barrier("box", (WALL_X[0] - 0.01, 0.04, 0.0), half_size=(0.01, 0.38, POST_HALF_HEIGHT), name="wall_left"),
            Barrier("box", (WALL_X[1] + 0.01, 0.04, 0.0), half_size=(0.01, 0.38, POST_HALF_HEIGHT), name="wall_right"),
        )
        return posts + walls

    @classmethod
    def environment_state(cls) -> np.ndarray:
        posts = [(x, y) for y, _, xs in ROWS for x in xs]
        return np.array([FINISH_Y, *np.ravel(posts)], dtype=np.float32)

    @classmethod
    def environment_state_names(cls) -> list[str]:
        names = ["finish_y"]
        for i, (_, _, xs) in enumerate(ROWS):
            names += [f"post_r{i + 1}_{j}_{a}" for j in range(len(xs)) for a in "xy"]
        return names

    def goal_marker(self) -> Solid:
        """The finish line, a green strip on the floor between the walls."""
        half_x = (WALL_X[1] - WALL_X[0]) / 2
        return Solid("box", ((WALL_X[0] + WALL_X[1]) / 2, FINISH_Y + 0.005, self.floor_z), (half_x, 0.005, 0.001),
                     (0.15, 0.7, 0.2))

    def goal_reached(self, pos: np.ndarray) -> bool:
        return bool(pos[1] > FINISH_Y)

    @classmethod
    def classify(cls, positions: np.ndarray) -> int | str:
        return classify_positions(positions)


def mode_waypoints(mode: int) -> np.ndarray:
    """Template route: start, then each chosen gap centre ROW_OFFSET before and after its row, finish."""
    gaps = decode_mode(mode)
    pts = [START]
    for row, g in enumerate(gaps):
        x = gap_centers(row)[g]
        y = ROWS[row][0]
        pts += [(x, y - ROW_OFFSET), (x, y + ROW_OFFSET)]
    pts.append((pts[-1][0], FINISH_Y + 0.03))
    return np.array(pts, dtype=float)


def classify_positions(positions: np.ndarray) -> int | str:
    """Label a path by the gap it takes through each row of the original layout.

    At each row's first upward crossing, the gap index is the number of posts left of the crossing. A path
    that misses a row or crosses where a scene-0 post stands (only possible if a scene removed it) is
    ``"novel"``.
    """
    p = np.asarray(positions, dtype=float)
    if p.ndim != 2 or p.shape[1] < 2:
        raise ValueError(f"expected a (T, >=2) array of positions, got shape {p.shape}")
    gaps = []
    for y_row, r, xs in ROWS:
        y = p[:, 1] - y_row
        idx = np.nonzero((y[:-1] < 0) & (y[1:] >= 0))[0]
        if len(idx) == 0:
            return NOVEL
        k = int(idx[0])
        t = -y[k] / (y[k + 1] - y[k]) if y[k + 1] != y[k] else 0.0
        x = p[k, 0] + t * (p[k + 1, 0] - p[k, 0])
        if any(abs(x - xp) < r for xp in xs):
            return NOVEL
        gaps.append(sum(xp < x for xp in xs))
    return int(gaps[0] * 12 + gaps[1] * 4 + gaps[2])


# ---- module-level functions used through SuiteEnv ----------------------------------------------------


def make_expert(mode: int, rng: np.random.Generator, scene: Any = 0) -> WaypointExpert:
    """Scripted demonstrator of a training mode; way-point jitter mostly along x, within the gap."""
    return make_waypoint_expert(
        mode_waypoints(mode), rng, dims=2, max_speed=AvoidingEnv.max_speed, dt=0.02, jitter=(0.012, 0.006)
    )


def expert_from_waypoints(waypoints: Any, rng: np.random.Generator, scene: Any = 0) -> WaypointExpert:
    """Demonstrator along arbitrary 2-D way-points; a final point beyond the finish line is appended."""
    wps = np.asarray(waypoints, dtype=float)
    if wps.ndim != 2 or wps.shape[1] != 2 or len(wps) == 0:
        raise ValueError(f"avoiding way-points must be a list of [x, y] points, got shape {np.shape(waypoints)}")
    if wps[-1, 1] <= FINISH_Y:
        wps = np.vstack([wps, (wps[-1, 0], FINISH_Y + 0.03)])
    return make_waypoint_expert(wps, rng, dims=2, max_speed=AvoidingEnv.max_speed, dt=0.02, jitter=0.005)


def classify_mode(states: np.ndarray, scene: Any = 0) -> int | str:
    """Mode id of a trajectory of ``observation.state`` rows (position first), or ``"novel"``."""
    return classify_positions(np.asarray(states)[:, :2])


def static_primitives(scene: Any = 0) -> tuple[Barrier, ...]:
    """Built-in obstacles left in ``scene`` (for plotting)."""
    return AvoidingEnv.static_primitives(scene)


LANDMARKS = {"start": START}

SUITE_ENV = register_suite_env(
    SuiteEnv(
        name="avoiding",
        gym_id=GYM_ID,
        scene_key="avoiding",
        lerobot_env_type="pdp_avoiding",
        module=__name__,
        mode_names=MODE_NAMES,
        trace_dims=(0, 1),
        max_episode_steps=MAX_STEPS,
        fps=50,
        extra={"finish_y": FINISH_Y},
    )
)
register_gym(GYM_ID, f"{__name__}:AvoidingEnv")
