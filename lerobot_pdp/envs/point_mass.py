"""Shared base for the MuJoCo point end-effector envs (reach-around, avoiding).

The end effector is a sphere on slide joints driven by position actuators: geoms on mocap bodies produce
no contacts with static geoms (MuJoCo counts mocap bodies as static and skips static pairs), and slide
joints give real contact dynamics. Obstacles and scene barriers are static world geoms. Contacts are
filtered so that only end-effector / hazard pairs exist (end effector ``contype=1 conaffinity=0``, hazards
``contype=0 conaffinity=1``); a collision is such a contact with ``dist < 0``, checked after every physics
sub-step so a fast pass through a thin fin cannot slip between control steps.

Actions are velocity fractions in [-1, 1] of ``max_speed``, integrated into the actuators' desired
position (clipped to the workspace), so a policy cannot teleport and a zero action holds position.

Observations (LeRobot's ``preprocess_observation`` maps the keys):
    ``agent_pos``         -> ``observation.state``: end-effector position, then velocity.
    ``environment_state`` -> ``observation.environment_state``: the task layout of scene 0 (goal and
        built-in obstacle centres). It is deliberately the same vector in every scene: the constraint
        shift is not observed (as in the paper), and a fixed size lets a scene-0 policy run in scenes 1-3.
    ``pixels`` (only with ``camera=...``) -> ``observation.images.<name>``: uint8 (H, W, 3) per camera, ray
        cast from the scene (:mod:`.camera`), so a scene's barriers are seen even though the state omits them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import gymnasium as gym
import mujoco
import numpy as np

from .camera import (
    DEFAULT_IMAGE_SIZE,
    CameraSpec,
    RayCaster,
    Solid,
    barrier_solid,
    parse_image_size,
    pixels_space,
    resolve_cameras,
)
from .scene import Barrier, Scene, SceneError, load_scene
from .suite import mode_info

SUBSTEPS = 10  # physics steps per control step
TIMESTEP = 0.002  # s, so the control period is 0.02 s (50 Hz)
EE_MASS = 0.1  # kg
KP = 360.0  # N/m, natural frequency sqrt(KP / EE_MASS) = 60 rad/s
DAMPING = 12.0  # N s/m, critical damping 2 sqrt(KP * EE_MASS)


# --------------------------------------------------------------------------------------------------
# Geometry helpers
# --------------------------------------------------------------------------------------------------


class PrimitiveSet:
    """Vectorised signed distances to a fixed set of boxes and upright cylinders (cheap per step)."""

    def __init__(self, primitives: Sequence[Barrier], default_z: float):
        boxes = [p for p in primitives if p.shape == "box"]
        cyls = [p for p in primitives if p.shape == "cylinder"]
        self.box_c = np.array([b.center3(default_z) for b in boxes], dtype=float).reshape(-1, 3)
        self.box_h = np.array([b.half_size for b in boxes], dtype=float).reshape(-1, 3)
        self.cyl_c = np.array([c.center3(default_z) for c in cyls], dtype=float).reshape(-1, 3)
        self.cyl_r = np.array([c.radius for c in cyls], dtype=float)
        self.cyl_h = np.array([c.half_height for c in cyls], dtype=float)

    def signed_distance(self, p: np.ndarray) -> float:
        """Minimum signed distance from the 3-D point ``p`` to any primitive surface (inf if none)."""
        best = math.inf
        if len(self.box_c):
            q = np.abs(p - self.box_c) - self.box_h
            d = np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)
            best = min(best, float(d.min()))
        if len(self.cyl_c):
            radial = np.hypot(p[0] - self.cyl_c[:, 0], p[1] - self.cyl_c[:, 1]) - self.cyl_r
            axial = np.abs(p[2] - self.cyl_c[:, 2]) - self.cyl_h
            d = np.hypot(np.maximum(radial, 0.0), np.maximum(axial, 0.0)) + np.minimum(
                np.maximum(radial, axial), 0.0
            )
            best = min(best, float(d.min()))
        return best


def _geom_xml(b: Barrier, default_z: float, name: str, rgba: Sequence[float]) -> str:
    c = b.center3(default_z)
    pos = f"{c[0]:.6g} {c[1]:.6g} {c[2]:.6g}"
    col = " ".join(f"{v:.3g}" for v in (b.rgba or rgba))
    common = f'name="{name}" pos="{pos}" rgba="{col}" contype="0" conaffinity="1"'
    if b.shape == "box":
        hs = " ".join(f"{v:.6g}" for v in b.half_size)
        return f'<geom type="box" size="{hs}" {common}/>'
    return f'<geom type="cylinder" size="{b.radius:.6g} {b.half_height:.6g}" {common}/>'


# --------------------------------------------------------------------------------------------------
# Scripted expert
# --------------------------------------------------------------------------------------------------


@dataclass
class WaypointExpert:
    """Follows a polyline of way-points at a given speed, then settles on the last one.

    The expert integrates its own copy of the env's desired position (the "carrot") and steers it along the
    polyline, so the end effector tracks the template closely; it re-syncs to the observed position if the
    two drift apart (e.g. after an external push). ``delay`` idle steps and per-segment ``speeds`` are the
    timing/speed jitter that gives intra-mode variety.
    """

    waypoints: np.ndarray  # (K, dims), first is usually the start
    speeds: np.ndarray  # (K,) speed fraction of max_speed used while heading to waypoint k
    max_speed: float
    dt: float
    dims: int
    delay: int = 0
    switch_radius: float = 0.01
    settle_gain: float = 4.0  # 1/s: proportional slow-down on the final approach

    def reset(self, obs: dict[str, np.ndarray]) -> None:
        self._carrot = np.asarray(obs["agent_pos"][: self.dims], dtype=float).copy()
        self._k = 0
        self._t = 0

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        pos = np.asarray(obs["agent_pos"][: self.dims], dtype=float)
        self._t += 1
        if self._t <= self.delay:
            return np.zeros(self.dims, dtype=np.float32)
        if np.linalg.norm(self._carrot - pos) > 0.05:
            self._carrot = pos.copy()
        last = len(self.waypoints) - 1
        while self._k < last and np.linalg.norm(self.waypoints[self._k] - self._carrot) < self.switch_radius:
            self._k += 1
        delta = self.waypoints[self._k] - self._carrot
        dist = float(np.linalg.norm(delta))
        speed = float(self.speeds[self._k]) * self.max_speed
        if self._k == last:
            speed = min(speed, self.settle_gain * dist)
        step = min(speed * self.dt, dist)
        move = delta / dist * step if dist > 1e-9 else np.zeros(self.dims)
        self._carrot = self._carrot + move
        return np.clip(move / (self.max_speed * self.dt), -1.0, 1.0).astype(np.float32)


def make_waypoint_expert(
    waypoints: Any,
    rng: np.random.Generator,
    *,
    dims: int,
    max_speed: float,
    dt: float,
    jitter: float | Sequence[float],
    speed_range: tuple[float, float] = (0.65, 0.95),
    max_delay: int = 5,
    jitter_endpoints: bool = False,
) -> WaypointExpert:
    """Build a :class:`WaypointExpert` with seeded jitter on interior way-points, speed and start delay.

    ``jitter`` is the half-width of the uniform way-point noise (scalar or per axis). The first and last
    way-points (start and goal) are kept unless ``jitter_endpoints``.
    """
    wps = np.asarray(waypoints, dtype=float)
    if wps.ndim != 2 or wps.shape[1] < dims or len(wps) < 1:
        raise ValueError(f"way-points must be a list of points with {dims} coordinates, got shape {wps.shape}")
    if not np.all(np.isfinite(wps)):
        raise ValueError(f"way-points must be finite numbers, got {wps.tolist()}")
    wps = wps[:, :dims].copy()
    j = np.broadcast_to(np.asarray(jitter, dtype=float), (dims,))
    noise = rng.uniform(-1.0, 1.0, size=wps.shape) * j
    lo = 0 if jitter_endpoints else 1
    hi = len(wps) if jitter_endpoints else len(wps) - 1
    wps[lo:hi] += noise[lo:hi]
    base = rng.uniform(*speed_range)
    speeds = np.clip(base * rng.uniform(0.9, 1.1, size=len(wps)), 0.05, 1.0)
    delay = int(rng.integers(0, max_delay + 1)) if max_delay > 0 else 0
    return WaypointExpert(wps, speeds, max_speed=max_speed, dt=dt, dims=dims, delay=delay)


# --------------------------------------------------------------------------------------------------
# Env
# --------------------------------------------------------------------------------------------------


class PointMassEnv(gym.Env):
    """A sphere end effector among static obstacles; subclasses define layout, goal and mode labels.

    Subclasses set the class attributes below and implement :meth:`builtin_obstacles`,
    :meth:`goal_reached` and :meth:`classify` (trajectory of states -> mode id or ``"novel"``).
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 50}

    dims: ClassVar[int] = 3
    scene_key: ClassVar[str] = ""
    mode_names: ClassVar[tuple[str, ...]] = ()
    start: ClassVar[tuple[float, ...]] = ()
    goal: ClassVar[tuple[float, ...]] = ()
    ee_radius: ClassVar[float] = 0.015
    max_speed: ClassVar[float] = 0.5  # m/s at |action| = 1
    workspace_low: ClassVar[tuple[float, ...]] = ()
    workspace_high: ClassVar[tuple[float, ...]] = ()
    plane_z: ClassVar[float] = 0.0  # height of the motion plane for 2-D envs
    default_episode_length: ClassVar[int] = 200
    default_start_noise: ClassVar[float] = 0.005
    render_views: ClassVar[tuple[tuple[int, int], ...]] = ((0, 1),)  # axes pairs drawn side by side
    task_text: ClassVar[str] = ""
    camera_specs: ClassVar[tuple[CameraSpec, ...]] = ()  # cameras ``camera=`` may name
    floor_z: ClassVar[float] = 0.0  # height of the floor the cameras see

    def __init__(
        self,
        scene: int | str | Scene | dict | None = 0,
        render_mode: str | None = None,
        episode_length: int | None = None,
        start_noise: float | None = None,
        camera: str | Sequence[str] | None = None,
        image_size: int | str | Sequence[int] = DEFAULT_IMAGE_SIZE,
    ):
        """``camera``: a name of ``camera_specs`` (or several, comma-separated) adds ``obs["pixels"]``;
        ``image_size``: N or (H, W) pixels of each camera image."""
        self.cameras = resolve_cameras(camera, self.camera_specs, self.scene_key or type(self).__name__)
        self.image_size = parse_image_size(image_size)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self.scene = load_scene(scene, self.scene_key)
        self.episode_length = int(episode_length or self.default_episode_length)
        if self.episode_length <= 0:
            raise ValueError(f"episode_length must be positive, got {episode_length!r}")
        self._max_episode_steps = self.episode_length
        self.start_noise = self.default_start_noise if start_noise is None else float(start_noise)
        self.dt = TIMESTEP * SUBSTEPS
        self.task_description = self.task_text
        self.task = self.task_text

        builtins = self.builtin_obstacles()
        names = {b.name for b in builtins}
        unknown = sorted(set(self.scene.remove) - names)
        if unknown:
            raise SceneError(
                f"{self.scene.source}: 'remove' names unknown obstacle(s) {unknown}; "
                f"built-in obstacles of {self.scene_key}: {sorted(names)}"
            )
        self.obstacles = tuple(b for b in builtins if b.name not in self.scene.remove)
        self.barriers = self.scene.barriers
        if self.dims == 2:
            for i, b in enumerate(self.barriers):
                lo, hi = b.center3(self.plane_z)[2] - _half_z(b), b.center3(self.plane_z)[2] + _half_z(b)
                if not lo <= self.plane_z <= hi:
                    raise SceneError(
                        f"{self.scene.source}: barriers[{i}] spans z [{lo:.3f}, {hi:.3f}] and misses the "
                        f"motion plane z = {self.plane_z}; give a 2-D pos or a z range covering it"
                    )
        margin = self.ee_radius + self.start_noise + 0.005
        self.scene.check_clear(
            {"start": np.array(self.start), "goal": np.array(self.goal)}, margin=margin, default_z=self.plane_z
        )
        self._hazards = PrimitiveSet(self.obstacles + self.barriers, self.plane_z)

        self.model = mujoco.MjModel.from_xml_string(self._mjcf())
        self.data = mujoco.MjData(self.model)
        self._ee_geom = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, "ee")

        d = self.dims
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(d,), dtype=np.float32)
        env_state = self.environment_state()
        obs_spaces: dict[str, gym.spaces.Space] = {
            "agent_pos": gym.spaces.Box(-np.inf, np.inf, shape=(2 * d,), dtype=np.float32),
            "environment_state": gym.spaces.Box(-np.inf, np.inf, shape=env_state.shape, dtype=np.float32),
        }
        if self.cameras:
            obs_spaces["pixels"] = pixels_space(self.cameras, self.image_size)
        self.observation_space = gym.spaces.Dict(obs_spaces)
        self._casters: dict[str, RayCaster] | None = None
        self._lo = np.array(self.workspace_low, dtype=float)
        self._hi = np.array(self.workspace_high, dtype=float)
        self._desired = np.array(self.start, dtype=float)
        self._positions: list[np.ndarray] = []
        self._steps = 0
        self._collided = False
        self._done = False
        self._min_clearance = math.inf
        self._background: np.ndarray | None = None

    # ---- subclass hooks ---------------------------------------------------------------------------

    @classmethod
    def builtin_obstacles(cls) -> tuple[Barrier, ...]:
        """Named obstacles of the original layout (scenes may remove them by name)."""
        raise NotImplementedError

    @classmethod
    def static_primitives(cls, scene: Any = 0) -> tuple[Barrier, ...]:
        """Built-in obstacles that ``scene`` leaves in place (for plotting; the env itself checks names)."""
        removed = set(load_scene(scene, cls.scene_key).remove)
        return tuple(b for b in cls.builtin_obstacles() if b.name not in removed)

    def goal_reached(self, pos: np.ndarray) -> bool:
        raise NotImplementedError

    @classmethod
    def classify(cls, positions: np.ndarray) -> int | str:
        """Mode id of a trajectory of end-effector positions, or :data:`NOVEL`."""
        raise NotImplementedError

    @classmethod
    def environment_state(cls) -> np.ndarray:
        """Goal and built-in obstacle centres of the original layout (identical in every scene)."""
        parts = [np.asarray(cls.goal, dtype=float)]
        parts += [np.asarray(b.center3(cls.plane_z)[: cls.dims]) for b in cls.builtin_obstacles()]
        return np.concatenate(parts).astype(np.float32)

    @classmethod
    def environment_state_names(cls) -> list[str]:
        """Names of :meth:`environment_state` entries (written into dataset features)."""
        axes = "xyz"[: cls.dims]
        names = [f"goal_{a}" for a in axes]
        names += [f"{b.name}_{a}" for b in cls.builtin_obstacles() for a in axes]
        return names

    @classmethod
    def state_names(cls) -> list[str]:
        axes = "xyz"[: cls.dims]
        return [f"ee_{a}" for a in axes] + [f"ee_v{a}" for a in axes]

    @classmethod
    def action_names(cls) -> list[str]:
        return [f"v{a}" for a in "xyz"[: cls.dims]]

    # ---- MJCF -------------------------------------------------------------------------------------

    def _mjcf(self) -> str:
        axes = "xyz"[: self.dims]
        body_z = self.plane_z if self.dims == 2 else 0.0
        joints = "\n".join(
            f'<joint name="slide_{a}" type="slide" axis="{" ".join("1" if a == b else "0" for b in "xyz")}" '
            f'damping="{DAMPING}"/>'
            for a in axes
        )
        acts = "\n".join(f'<position name="act_{a}" joint="slide_{a}" kp="{KP}"/>' for a in axes)
        geoms = [_geom_xml(b, self.plane_z, f"obstacle_{b.name}", (0.35, 0.35, 0.4, 1)) for b in self.obstacles]
        geoms += [
            _geom_xml(b, self.plane_z, f"barrier_{i}" + (f"_{b.name}" if b.name else ""), (0.85, 0.45, 0.2, 1))
            for i, b in enumerate(self.barriers)
        ]
        return f"""
<mujoco model="{self.scene_key}">
  <option timestep="{TIMESTEP}" gravity="0 0 0" integrator="implicitfast"/>
  <worldbody>
    <body name="ee_body" pos="0 0 {body_z}">
      {joints}
      <geom name="ee" type="sphere" size="{self.ee_radius}" mass="{EE_MASS}" rgba="0.9 0.1 0.1 1"
            contype="1" conaffinity="0"/>
    </body>
    {chr(10).join("    " + g for g in geoms)}
  </worldbody>
  <actuator>
    {acts}
  </actuator>
</mujoco>"""

    # ---- gym API ----------------------------------------------------------------------------------

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        start = np.array(self.start, dtype=float)
        if self.start_noise > 0:
            start = start + self.np_random.uniform(-self.start_noise, self.start_noise, size=self.dims)
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] = self._joint_coords(start)
        self.data.ctrl[:] = self.data.qpos
        mujoco.mj_forward(self.model, self.data)
        self._desired = start.copy()
        self._positions = [self.ee_pos()]
        self._steps = 0
        self._collided = False
        self._done = False
        self._min_clearance = self.clearance(self._positions[0])
        return self._obs(), self._info(success=False)

    def step(self, action):
        if self._done:
            raise RuntimeError("step() called after the episode ended; call reset() first")
        a = np.asarray(action, dtype=float).reshape(-1)
        if a.shape != (self.dims,):
            raise ValueError(f"action must have shape ({self.dims},), got {np.shape(action)}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action must be finite, got {a.tolist()}")
        a = np.clip(a, -1.0, 1.0)
        self._desired = np.clip(self._desired + a * self.max_speed * self.dt, self._lo, self._hi)
        self.data.ctrl[:] = self._joint_coords(self._desired)
        for _ in range(SUBSTEPS):
            mujoco.mj_step(self.model, self.data)
            if self.data.ncon and self._in_collision():
                self._collided = True
                break
        pos = self.ee_pos()
        self._positions.append(pos)
        self._steps += 1
        self._min_clearance = min(self._min_clearance, self.clearance(pos))
        success = (not self._collided) and self.goal_reached(pos)
        terminated = self._collided or success
        truncated = (not terminated) and self._steps >= self.episode_length
        self._done = terminated or truncated
        info = self._info(success=success)
        if self._done:
            info.update(mode_info(self.classify(np.asarray(self._positions)), self.mode_names))
        return self._obs(), float(success), terminated, truncated, info

    # ---- state ------------------------------------------------------------------------------------

    def _joint_coords(self, p: np.ndarray) -> np.ndarray:
        return np.asarray(p, dtype=float)[: self.dims]

    def ee_pos(self) -> np.ndarray:
        return self.data.qpos[: self.dims].copy()

    def ee_pos3(self, p: np.ndarray | None = None) -> np.ndarray:
        p = self.ee_pos() if p is None else np.asarray(p, dtype=float)
        return p if self.dims == 3 else np.array([p[0], p[1], self.plane_z])

    def clearance(self, pos: np.ndarray) -> float:
        """Signed distance from the end-effector surface to the nearest obstacle or barrier."""
        return self._hazards.signed_distance(self.ee_pos3(pos)) - self.ee_radius

    def _in_collision(self) -> bool:
        for i in range(self.data.ncon):
            c = self.data.contact[i]
            if c.dist < 0 and self._ee_geom in (c.geom1, c.geom2):
                return True
        return False

    def _obs(self) -> dict[str, np.ndarray]:
        state = np.concatenate([self.data.qpos[: self.dims], self.data.qvel[: self.dims]]).astype(np.float32)
        obs = {"agent_pos": state, "environment_state": self.environment_state()}
        if self.cameras:
            obs["pixels"] = self.camera_images()
        return obs

    # ---- cameras ----------------------------------------------------------------------------------

    def goal_marker(self) -> Solid | None:
        """A small green solid marking the goal in camera images (subclasses may override)."""
        return Solid("sphere", tuple(map(float, self.ee_pos3(np.asarray(self.goal)))), (0.6 * self.ee_radius,),
                     (0.15, 0.7, 0.2))

    def camera_images(self) -> dict[str, np.ndarray]:
        """What each of ``self.cameras`` sees now: the scene and the end effector (not its past path)."""
        if self._casters is None:
            static = [Solid("floor", (0.0, 0.0, self.floor_z), (), (0.78, 0.78, 0.74))]
            static += [barrier_solid(b, self.plane_z, (0.35, 0.35, 0.4)) for b in self.obstacles]
            static += [barrier_solid(b, self.plane_z, (0.85, 0.45, 0.2)) for b in self.barriers]
            marker = self.goal_marker()
            static += [marker] if marker is not None else []
            specs = {s.name: s for s in self.camera_specs}
            self._casters = {n: RayCaster(specs[n], self.image_size, static) for n in self.cameras}
        ee = Solid("sphere", tuple(map(float, self.ee_pos3())), (self.ee_radius,), (0.9, 0.1, 0.1))
        return {n: c.render([ee]) for n, c in self._casters.items()}

    def _info(self, success: bool) -> dict[str, Any]:
        return {
            "is_success": bool(success),
            "collided": bool(self._collided),
            "min_clearance": float(self._min_clearance),
        }

    # ---- rendering (numpy raster, no GL) ------------------------------------------------------------

    RENDER_PX: ClassVar[int] = 160

    def render(self) -> np.ndarray | None:
        """Orthographic projections (one panel per ``render_views`` pair) with the path so far."""
        if self.render_mode != "rgb_array":
            return None
        if self._background is None:
            self._background = self._draw_background()
        img = self._background.copy()
        n = self.RENDER_PX
        for v, (i, j) in enumerate(self.render_views):
            lo, hi = self._lo - 0.02, self._hi + 0.02
            scale = (n - 1) / max(hi[i] - lo[i], hi[j] - lo[j])
            pts = np.asarray(self._positions)
            cols = np.clip(((pts[:, i] - lo[i]) * scale).astype(int), 0, n - 1) + v * n
            rows = np.clip((n - 1 - (pts[:, j] - lo[j]) * scale).astype(int), 0, n - 1)
            img[rows, cols] = (200, 40, 40)
            r = max(2, int(self.ee_radius * scale))
            yy, xx = np.ogrid[:n, :n]
            disc = (yy - rows[-1]) ** 2 + (xx - (cols[-1] - v * n)) ** 2 <= r * r
            img[:, v * n : (v + 1) * n][disc] = (220, 0, 0)
        return img

    def _draw_background(self) -> np.ndarray:
        n = self.RENDER_PX
        img = np.full((n, n * len(self.render_views), 3), 245, dtype=np.uint8)
        for v, (i, j) in enumerate(self.render_views):
            lo, hi = self._lo - 0.02, self._hi + 0.02
            scale = (n - 1) / max(hi[i] - lo[i], hi[j] - lo[j])
            u = lo[i] + np.arange(n) / scale
            w = lo[j] + (n - 1 - np.arange(n)) / scale
            U, W = np.meshgrid(u, w)
            panel = img[:, v * n : (v + 1) * n]
            for prims, col in ((self.obstacles, (90, 90, 100)), (self.barriers, (215, 120, 50))):
                for b in prims:
                    panel[_footprint(b, i, j, U, W, self.plane_z)] = col
            g = np.asarray(self.goal, dtype=float)
            if len(g) > max(i, j):
                gr = (U - g[i]) ** 2 + (W - g[j]) ** 2 <= 0.03**2
                panel[gr] = (60, 180, 60)
        return img


def _half_z(b: Barrier) -> float:
    return float(b.half_size[2]) if b.shape == "box" else float(b.half_height)


def _footprint(b: Barrier, i: int, j: int, U: np.ndarray, W: np.ndarray, default_z: float) -> np.ndarray:
    """Boolean mask of the projection of ``b`` onto the (axis i, axis j) plane."""
    c = b.center3(default_z)
    if b.shape == "box":
        return (np.abs(U - c[i]) <= b.half_size[i]) & (np.abs(W - c[j]) <= b.half_size[j])
    half = [b.radius, b.radius, b.half_height]
    if {i, j} == {0, 1}:
        return (U - c[i]) ** 2 + (W - c[j]) ** 2 <= b.radius**2
    return (np.abs(U - c[i]) <= half[i]) & (np.abs(W - c[j]) <= half[j])


def register_gym(gym_id: str, entry_point: str, max_episode_steps: int | None = None) -> None:
    """Register a gym id once (importing a module twice, e.g. via reload, must not warn or fail)."""
    if gym_id not in gym.envs.registry:
        gym.register(id=gym_id, entry_point=entry_point, max_episode_steps=max_episode_steps)
