"""PickPlace-v0: reach around obstacle A to an object, grasp it, carry it around obstacle B, release it.

Analog of the paper's PlaceBlock / MeatOffGrill: a two-phase task whose mode is the pair
(reach route, carry route), 8 x 8 = 64 training modes, with the gripper command marking the phase change.

Layout (world coordinates, metres; everything lies on the line x = 0, z = 0.40 and progresses along +y)::

    start (0, -0.50, 0.40) -> obstacle A (0, -0.25, 0.40) -> object (0, 0, 0.40)
                           -> obstacle B (0, +0.25, 0.40) -> target (0, +0.50, 0.40)

Both obstacles are boxes with half-sizes (0.08, 0.04, 0.08), named ``obstacle_a`` / ``obstacle_b`` (a scene
may ``remove`` them by name). Each phase passes its obstacle on one of 4 sides -- over (+z), left (-x),
right (+x), under (-z) -- at a tight (0.13 m off the obstacle centre) or wide (0.25 m) distance, as in
reach-around (same phase-mode ids: side * 2 + (0 tight | 1 wide)); env mode = reach_mode * 8 + carry_mode.

Physics (real MuJoCo, gravity off so the object rests where it is put, as if on an invisible shelf):
- end effector: a sphere (r 0.015) on three slide joints driven by position actuators; an action's first three
  values are velocity fractions of 0.5 m/s integrated (dt 0.02 s) into the desired position.
- object: a cube (half-size 0.015) on its own three damped slide joints.
- grasp: closing the gripper (action[3] > 0) within 0.03 m of the object activates a ``connect`` equality
  constraint anchored at the end effector's centre, so the object is pulled to the centre within a few
  steps (as closing parallel fingers centre an object) and moves with the end effector only while the
  gripper stays closed; opening deactivates it.
  A constraint (rather than teleporting the object) keeps the carried object a physical body, so its
  contacts with obstacles are real and count as collisions.
- collisions: end effector and object have ``contype=1 conaffinity=0``, obstacles ``contype=0
  conaffinity=1`` (so the two moving bodies never touch each other). Obstacles carry ``gap = 0.1`` m
  (MuJoCo 3.x: detection buffer beyond ``margin = 0``): contacts within 0.1 m are reported but exert no
  force, which yields the clearance for free; a contact with ``dist < 0`` is a collision and ends the episode.

Observation (float32): ``agent_pos`` = [ee x, y, z, gripper closed (0/1)] (-> ``observation.state``);
``environment_state`` = [object xyz, target xyz, obstacle A centre, obstacle B centre]
(-> ``observation.environment_state``). A removed obstacle keeps its nominal centre in the observation.

Camera (``camera="top" | "side" | "oblique"``, ``image_size`` default 96): ``obs["pixels"][name]`` uint8
(H, W, 3) -> ``observation.images.<name>``, ray cast from the scene (:mod:`.camera`; no OpenGL, identical
pixels on every machine): floor, obstacles, barriers, target marker, object and end effector.

Success: the object was grasped, then released (gripper open) with its centre within 0.03 m of the
target, without any collision.

Shipped scenes (``scenes/pick_place_scene{0..4}.json``):
- 0: original, all 64 modes feasible.
- 1: slabs left/right/under A and a ceiling slab above A (blocks over-wide) -> reach only over-tight;
  slabs right/over/under B and a thin fin on B's left face (blocks left-tight) -> carry only left-wide.
  Only mode 0*8+3 = 3 ("reach over-tight / carry left-wide") is feasible.
- 2: slabs left/right/over A and a fin under A (blocks under-tight) -> reach only under-wide; slabs
  left/over/under B and a wall beyond B's right face (blocks right-wide) -> carry only right-tight.
  Only mode 7*8+4 = 60 ("reach under-wide / carry right-tight") is feasible.
- 3: a wall at y = 0.25 around B with one 0.12 x 0.12 window centred at (+0.19, +0.19) (x, z) off B's centre;
  no training carry route fits, the shipped way-points carry the object diagonally through the window.
- 4 (a zero-mode test scene for teaching, outside the benchmark's scenes 1-3): a wall at y = 0.25 around B filling
  the workspace, with one window 0.51 m up and left of B's centre (the widest carry routes pass at 0.25 m); the
  shipped way-points carry the object up and left through it.

Way-points for :func:`expert_from_waypoints` (JSON-friendly), either
- a dict ``{"reach": [[x, y, z], ...], "carry": [[x, y, z], ...]}`` of via-points only: the expert appends
  the object to the reach list and the target to the carry list; or
- a flat list of via-points ``[[x, y, z], ...]`` (the form a scene file's ``waypoints`` takes): the first
  point within 0.03 m of the object is the grasp point, the last point must lie within 0.03 m of the target
  (the release point); points in between are carry via-points.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces

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
from .suite import NOVEL, SuiteEnv, mode_info, register_suite_env

ENV_NAME = "pick_place"
GYM_ID = "lerobot_pdp/PickPlace-v0"
TASK_DESCRIPTION = "Reach around obstacle A, grasp the object, carry it around obstacle B and place it on the target."

START = np.array([0.0, -0.50, 0.40])
OBSTACLE_A = np.array([0.0, -0.25, 0.40])
OBJECT = np.array([0.0, 0.0, 0.40])
OBSTACLE_B = np.array([0.0, 0.25, 0.40])
TARGET = np.array([0.0, 0.50, 0.40])
OBSTACLE_HALF = (0.08, 0.04, 0.08)
OBSTACLE_NAMES = ("obstacle_a", "obstacle_b")
WORKING_Z = 0.40  # 2-D cylinder positions in scene files stand centred at this height

EE_RADIUS = 0.015
OBJECT_HALF = 0.015
MAX_SPEED = 0.5  # m/s at |action| = 1
DT = 0.02  # control period (s)
TIMESTEP = 0.002  # physics step (s)
N_SUBSTEPS = round(DT / TIMESTEP)
GRASP_RADIUS = 0.03
SUCCESS_TOL = 0.03
CLEARANCE_MARGIN = 0.1  # contacts closer than this are reported (inactive) to measure clearance
SCENE_CLEAR_MARGIN = 0.05  # barriers must stay this far from start, object and target
MAX_EPISODE_STEPS = 300
# Expert's braking onto the grasp / release point: speed fraction <= BRAKE_GAIN * distance (m), i.e. the gap
# shrinks ~BRAKE_GAIN * 1 % per step. A gentle 8 left 18 steps of creeping at 0.5-2 mm/step in the last 3 cm,
# speeds within a learned policy's action error: policies stalled 3-8 cm short and closed there.
BRAKE_GAIN = 25.0
WORKSPACE_LOW = np.array([-0.6, -0.7, 0.0])
WORKSPACE_HIGH = np.array([0.6, 0.7, 0.85])

SIDES = ("over", "left", "right", "under")  # same phase-mode order as reach-around
DISTANCES = ("tight", "wide")
SIDE_DIRS = {"over": (0.0, 1.0), "left": (-1.0, 0.0), "right": (1.0, 0.0), "under": (0.0, -1.0)}  # (x, z)
OFFSETS = {"tight": 0.13, "wide": 0.25}
PHASE_MODE_NAMES = tuple(f"{s}-{d}" for s in SIDES for d in DISTANCES)
N_PHASE_MODES = len(PHASE_MODE_NAMES)
MODE_NAMES = tuple(f"reach {r} / carry {c}" for r in PHASE_MODE_NAMES for c in PHASE_MODE_NAMES)
VIA_DY = 0.06  # via-points sit this far before / after the obstacle's centre plane (face is at 0.04)

# Classifier thresholds on the (x, z) offset from the obstacle centre while crossing its y-slab.
TIGHT_WIDE_SPLIT = 0.19
MIN_OFFSET = 0.09
MAX_OFFSET = 0.34
MAX_OFF_AXIS = 0.08  # beyond the obstacle's half-width the route rounds a corner: not a training mode

# "top" looks down (+y up in the image); "side" looks along -x, seeing over / under routes and the phases'
# progress along y; "oblique" is close to render()'s view.
CAMERAS = (
    CameraSpec("top", eye=(0.0, 0.0, 2.4), target=(0.0, 0.0, 0.4), up=(0.0, 1.0, 0.0), fovy=34.0),
    CameraSpec("side", eye=(2.0, 0.0, 0.45), target=(0.0, 0.0, 0.4), fovy=36.0),
    CameraSpec("oblique", eye=(1.0, -1.2, 1.1), target=(0.0, 0.0, 0.35), fovy=50.0),
)


# --------------------------------------------------------------------------------------------- env


def _box_xml(name: str, pos: Sequence[float], half: Sequence[float], rgba: Sequence[float]) -> str:
    return (f'<geom name="{name}" type="box" pos="{_fmt(pos)}" size="{_fmt(half)}" rgba="{_fmt(rgba)}" '
            f'class="hazard"/>')


def _fmt(v: Sequence[float]) -> str:
    return " ".join(f"{float(x):.6g}" for x in v)


def build_mjcf(scene: Scene) -> str:
    """MJCF of the scene: built-in obstacles minus ``scene.remove`` plus ``scene.barriers``."""
    unknown = sorted(set(scene.remove) - set(OBSTACLE_NAMES))
    if unknown:
        raise SceneError(f"{scene.source}: 'remove' names unknown obstacle(s) {unknown}; "
                         f"built-in obstacles are {list(OBSTACLE_NAMES)}")
    hazards = []
    for name, centre in zip(OBSTACLE_NAMES, (OBSTACLE_A, OBSTACLE_B), strict=True):
        if name not in scene.remove:
            hazards.append(_box_xml(name, centre, OBSTACLE_HALF, (0.6, 0.3, 0.2, 1)))
    used = set(OBSTACLE_NAMES)
    for i, b in enumerate(scene.barriers):
        name = b.name or f"barrier_{i}"
        if name in used:
            raise SceneError(f"{scene.source}: barriers[{i}] name {name!r} is already used")
        used.add(name)
        rgba = b.rgba or (0.5, 0.5, 0.55, 0.8)
        if b.shape == "box":
            hazards.append(_box_xml(name, b.center3(WORKING_Z), b.half_size, rgba))
        else:
            hazards.append(f'<geom name="{name}" type="cylinder" pos="{_fmt(b.center3(WORKING_Z))}" '
                           f'size="{b.radius:.6g} {b.half_height:.6g}" rgba="{_fmt(rgba)}" class="hazard"/>')
    slides = "".join(
        f'<joint name="{{b}}_{ax}" type="slide" axis="{axis}" damping="{{damp}}"/>'
        for ax, axis in (("x", "1 0 0"), ("y", "0 1 0"), ("z", "0 0 1"))
    )
    actuators = "".join(
        f'<position name="ee_{ax}" joint="ee_{ax}" kp="800" kv="20" ctrllimited="false"/>' for ax in "xyz"
    )
    return f"""
<mujoco model="pdp_pick_place">
  <option timestep="{TIMESTEP}" gravity="0 0 0" integrator="implicitfast"/>
  <visual><global offwidth="640" offheight="480"/></visual>
  <default>
    <default class="hazard"><geom contype="0" conaffinity="1" margin="0"
      gap="{CLEARANCE_MARGIN}"/></default>
  </default>
  <worldbody>
    <light pos="0 0 2" dir="0 0 -1" castshadow="false"/>
    <geom name="floor" type="plane" size="1 1 0.01" rgba="0.85 0.85 0.85 1" contype="0" conaffinity="0"/>
    {"".join(hazards)}
    <site name="target" pos="{_fmt(TARGET)}" size="{SUCCESS_TOL}" rgba="0.1 0.8 0.1 0.3"/>
    <body name="ee" pos="{_fmt(START)}">
      {slides.format(b="ee", damp=0)}
      <geom name="ee" type="sphere" size="{EE_RADIUS}" mass="0.1" contype="1" conaffinity="0"
        rgba="0.2 0.4 0.9 1"/>
    </body>
    <body name="object" pos="{_fmt(OBJECT)}">
      {slides.format(b="obj", damp=2)}
      <geom name="object" type="box" size="{OBJECT_HALF} {OBJECT_HALF} {OBJECT_HALF}" mass="0.02"
        contype="1" conaffinity="0" rgba="0.9 0.7 0.1 1"/>
    </body>
  </worldbody>
  <equality>
    <connect name="grasp" body1="object" body2="ee" anchor="0 0 0" active="false" solref="0.005 1"/>
  </equality>
  <actuator>{actuators}</actuator>
</mujoco>
"""


class PickPlaceEnv(gym.Env):
    """Two-phase pick-and-place around two obstacles; see the module docstring for layout and physics."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": round(1 / DT)}
    workspace_low: ClassVar[tuple[float, ...]] = tuple(WORKSPACE_LOW)  # the end effector's clamp
    workspace_high: ClassVar[tuple[float, ...]] = tuple(WORKSPACE_HIGH)

    def __init__(self, scene: Any = 0, render_mode: str | None = None,
                 max_episode_steps: int = MAX_EPISODE_STEPS, camera: str | Sequence[str] | None = None,
                 image_size: int | str | Sequence[int] = DEFAULT_IMAGE_SIZE) -> None:
        """``camera``: one of :data:`CAMERAS` (or several, comma-separated) adds ``obs["pixels"]``;
        ``image_size``: N or (H, W) pixels of each camera image."""
        self.cameras = resolve_cameras(camera, CAMERAS, "pick-place")
        self.image_size = parse_image_size(image_size)
        self.scene = load_scene(scene, ENV_NAME)
        self.scene.check_clear({"start": START, "object": OBJECT, "target": TARGET}, SCENE_CLEAR_MARGIN,
                               default_z=WORKING_Z)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self._max_episode_steps = int(max_episode_steps)
        self.task_description = TASK_DESCRIPTION
        self.task = TASK_DESCRIPTION
        self.model = mujoco.MjModel.from_xml_string(build_mjcf(self.scene))
        self.data = mujoco.MjData(self.model)
        m = self.model
        self._ee_qpos = np.array([m.jnt_qposadr[m.joint(f"ee_{a}").id] for a in "xyz"])
        self._obj_qpos = np.array([m.jnt_qposadr[m.joint(f"obj_{a}").id] for a in "xyz"])
        self._obj_qvel = np.array([m.jnt_dofadr[m.joint(f"obj_{a}").id] for a in "xyz"])
        self._grasp_eq = m.equality("grasp").id
        self._renderer: mujoco.Renderer | None = None
        self.action_space = spaces.Box(-1.0, 1.0, shape=(4,), dtype=np.float32)
        obs_spaces: dict[str, spaces.Space] = {
            # Positions stay inside the workspace clamp (|coord| < 0.85 m); 1 m bounds leave room for lag.
            "agent_pos": spaces.Box(-1.0, 1.0, shape=(4,), dtype=np.float32),
            "environment_state": spaces.Box(-1.0, 1.0, shape=(12,), dtype=np.float32),
        }
        if self.cameras:
            obs_spaces["pixels"] = pixels_space(self.cameras, self.image_size)
        self.observation_space = spaces.Dict(obs_spaces)
        self._casters: dict[str, RayCaster] | None = None
        self._reset_state()

    # state helpers ---------------------------------------------------------------------------------
    def _reset_state(self) -> None:
        mujoco.mj_resetData(self.model, self.data)
        self.data.eq_active[self._grasp_eq] = 0
        self.data.ctrl[:] = 0.0
        mujoco.mj_forward(self.model, self.data)
        self._desired = START.copy()
        self._gripper_closed = False
        self._grasped = False
        self._ever_grasped = False
        self._steps = 0
        self._collided = False
        self._success = False
        self._min_clearance = float(CLEARANCE_MARGIN)
        self._states: list[np.ndarray] = []

    @property
    def ee_pos(self) -> np.ndarray:
        return START + self.data.qpos[self._ee_qpos]

    @property
    def object_pos(self) -> np.ndarray:
        return OBJECT + self.data.qpos[self._obj_qpos]

    @property
    def grasped(self) -> bool:
        return self._grasped

    # Feature names written into datasets (read by ``recording``).
    def state_names(self) -> list[str]:
        return ["ee_x", "ee_y", "ee_z", "gripper_closed"]

    def environment_state_names(self) -> list[str]:
        return [f"{what}_{ax}" for what in ("object", "target", "obstacle_a", "obstacle_b") for ax in "xyz"]

    def action_names(self) -> list[str]:
        return ["vx", "vy", "vz", "gripper"]

    def _obs(self) -> dict[str, np.ndarray]:
        agent = np.concatenate([self.ee_pos, [float(self._gripper_closed)]]).astype(np.float32)
        env_state = np.concatenate([self.object_pos, TARGET, OBSTACLE_A, OBSTACLE_B]).astype(np.float32)
        obs = {"agent_pos": agent, "environment_state": env_state}
        if self.cameras:
            obs["pixels"] = self.camera_images()
        return obs

    def camera_images(self) -> dict[str, np.ndarray]:
        """What each of ``self.cameras`` sees now: the scene, the object and the end effector."""
        if self._casters is None:
            static = [Solid("floor", (0.0, 0.0, 0.0), (), (0.85, 0.85, 0.85))]
            static += [barrier_solid(b, WORKING_Z, (0.6, 0.3, 0.2)) for b in static_primitives(self.scene)]
            static += [barrier_solid(b, WORKING_Z, (0.5, 0.5, 0.55)) for b in self.scene.barriers]
            static.append(Solid("sphere", tuple(map(float, TARGET)), (0.6 * OBJECT_HALF,), (0.1, 0.8, 0.1)))
            specs = {s.name: s for s in CAMERAS}
            self._casters = {n: RayCaster(specs[n], self.image_size, static) for n in self.cameras}
        obj = Solid("box", tuple(map(float, self.object_pos)), (OBJECT_HALF,) * 3, (0.9, 0.7, 0.1))
        ee = Solid("sphere", tuple(map(float, self.ee_pos)), (EE_RADIUS,), (0.2, 0.4, 0.9))
        return {n: c.render([obj, ee]) for n, c in self._casters.items()}

    def _phase(self) -> str:
        if self._success:
            return "done"
        return "carry" if self._grasped else "reach"

    def _info(self, done: bool) -> dict[str, Any]:
        info: dict[str, Any] = {
            "is_success": bool(self._success),
            "collided": bool(self._collided),
            "min_clearance": float(self._min_clearance),
            "phase": self._phase(),
            "grasped": bool(self._grasped),
        }
        if done:
            info.update(mode_info(classify_mode(np.asarray(self._states)), MODE_NAMES))
        return info

    def _check_contacts(self) -> None:
        n = self.data.ncon
        if n:
            dist = float(np.min(self.data.contact.dist[:n]))
            self._min_clearance = min(self._min_clearance, dist)
            if dist < 0.0:
                self._collided = True

    def _set_gripper(self, close: bool) -> None:
        if close and not self._gripper_closed:
            self._gripper_closed = True
            offset = self.object_pos - self.ee_pos
            if np.linalg.norm(offset) < GRASP_RADIUS:
                # Anchor = the end effector's centre: closing fingers centre the object between them,
                # so a grasp a little off-centre still carries the object where the gripper goes.
                self.model.eq_data[self._grasp_eq, 0:3] = 0.0
                self.model.eq_data[self._grasp_eq, 3:6] = 0.0
                self.data.eq_active[self._grasp_eq] = 1
                self._grasped = self._ever_grasped = True
        elif not close and self._gripper_closed:
            self._gripper_closed = False
            if self._grasped:
                self.data.eq_active[self._grasp_eq] = 0
                self._grasped = False

    # gym API ---------------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """The layout is fixed (variety comes from the expert); ``seed`` only seeds ``np_random``."""
        super().reset(seed=seed)
        self._reset_state()
        self._check_contacts()
        obs = self._obs()
        self._states.append(obs["agent_pos"].copy())
        return obs, self._info(False)

    def step(self, action: np.ndarray):
        a = np.asarray(action, dtype=float).reshape(-1)
        if a.shape != (4,):
            raise ValueError(f"PickPlace action must have 4 values (3 velocities + gripper), got shape {a.shape}")
        a = np.clip(np.nan_to_num(a), -1.0, 1.0)
        self._set_gripper(bool(a[3] > 0.0))
        self._desired = np.clip(self._desired + a[:3] * MAX_SPEED * DT, WORKSPACE_LOW, WORKSPACE_HIGH)
        self.data.ctrl[:3] = self._desired - START
        mujoco.mj_step(self.model, self.data, nstep=N_SUBSTEPS)
        self._steps += 1
        self._check_contacts()
        if (not self._collided and self._ever_grasped and not self._grasped
                and np.linalg.norm(self.object_pos - TARGET) < SUCCESS_TOL):
            self._success = True
        obs = self._obs()
        self._states.append(obs["agent_pos"].copy())
        terminated = self._collided or self._success
        truncated = (not terminated) and self._steps >= self._max_episode_steps
        reward = 1.0 if self._success else 0.0
        return obs, reward, terminated, truncated, self._info(terminated or truncated)

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        if self._renderer is None:
            self._renderer = _renderer(self.model, 240, 320)
        cam = mujoco.MjvCamera()
        cam.lookat[:] = (0.0, 0.0, 0.4)
        cam.distance, cam.azimuth, cam.elevation = 1.6, 150.0, -25.0
        self._renderer.update_scene(self.data, camera=cam)
        return self._renderer.render()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


# ------------------------------------------------------------------------------------------ expert


def phase_via_points(phase_mode: int, centre: np.ndarray) -> list[np.ndarray]:
    """Two via-points flanking ``centre`` along y on the phase mode's side, at its tight/wide offset."""
    if not 0 <= int(phase_mode) < N_PHASE_MODES:
        raise ValueError(f"phase mode must be in 0..{N_PHASE_MODES - 1}, got {phase_mode}")
    side, dist = SIDES[int(phase_mode) // 2], DISTANCES[int(phase_mode) % 2]
    dx, dz = SIDE_DIRS[side]
    off = np.array([dx, 0.0, dz]) * OFFSETS[dist]
    return [centre + off + np.array([0.0, -VIA_DY, 0.0]), centre + off + np.array([0.0, VIA_DY, 0.0])]


class PickPlaceExpert:
    """Follows reach via-points to the object, grasps, follows carry via-points to the target, releases.

    Intra-mode variety: via-points are jittered (up to ``jitter`` m per axis), the cruise speed and each
    leg's speed vary, and the start delay and the pauses after grasp / before release are random.
    Control is a proportional law on the measured end-effector position, saturated at the cruise speed.
    """

    def __init__(self, reach: Sequence[Sequence[float]], carry: Sequence[Sequence[float]],
                 rng: np.random.Generator, jitter: float = 0.008) -> None:
        self.reach_via = [np.asarray(p, float) + rng.uniform(-jitter, jitter, 3) for p in reach]
        self.carry_via = [np.asarray(p, float) + rng.uniform(-jitter, jitter, 3) for p in carry]
        cruise = rng.uniform(0.7, 0.95)
        self.reach_speed = cruise * rng.uniform(0.92, 1.05, len(self.reach_via) + 1)
        self.carry_speed = cruise * rng.uniform(0.92, 1.05, len(self.carry_via) + 1)
        self.start_delay = int(rng.integers(0, 5))
        self.grasp_pause = int(rng.integers(1, 5))
        self.release_pause = int(rng.integers(0, 3))
        self.reset(None)

    def reset(self, obs: dict[str, np.ndarray] | None) -> None:
        self.stage, self.idx, self.count = "wait", 0, 0
        self.offset = np.zeros(3)
        self.prev: np.ndarray | None = None

    def _track(self, ee: np.ndarray, points: list[np.ndarray], speeds: np.ndarray) -> tuple[np.ndarray, float]:
        """Velocity fraction toward the current via-point (switching early), slowing at the last one."""
        while self.idx < len(points) - 1 and np.linalg.norm(points[self.idx] - ee) < 0.02:
            self.idx += 1
        err = points[self.idx] - ee
        dist = float(np.linalg.norm(err))
        speed = float(speeds[self.idx])
        if self.idx == len(points) - 1:
            speed = min(speed, BRAKE_GAIN * dist)  # proportional braking onto the grasp / release point
        v = err / max(dist, 1e-9) * speed
        return np.clip(v, -1.0, 1.0), dist

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        ee = np.asarray(obs["agent_pos"][:3], float)
        obj = np.asarray(obs["environment_state"][0:3], float)
        target = np.asarray(obs["environment_state"][3:6], float)
        moving = 0.0 if self.prev is None else float(np.linalg.norm(ee - self.prev))
        self.prev = ee
        act = np.zeros(4)
        if self.stage == "wait":
            # an explicit "open" (not 0.0, which sits on the open/closed threshold): learned policies
            # otherwise chatter the gripper at the start, which a phase-segmented policy reads as a grasp
            act[3] = -1.0
            self.count += 1
            if self.count > self.start_delay:
                self.stage, self.idx = "reach", 0
        if self.stage == "reach":
            v, _ = self._track(ee, [*self.reach_via, obj], self.reach_speed)
            act[:3] = v
            act[3] = -1.0
            if self.idx == len(self.reach_via) and np.linalg.norm(obj - ee) < 0.006 and moving < 0.002:
                self.stage, self.count = "grasp", 0
        if self.stage == "grasp":
            act[:3] = 0.0
            act[3] = 1.0
            self.offset = obj - ee  # measured while the closing fingers centre the object
            self.count += 1
            if self.count > self.grasp_pause:
                self.stage, self.idx = "carry", 0
        if self.stage == "carry":
            v, _ = self._track(ee, [*self.carry_via, target - self.offset], self.carry_speed)
            act[:3] = v
            act[3] = 1.0
            if (self.idx == len(self.carry_via) and np.linalg.norm(obj - target) < 0.008
                    and moving < 0.002):
                self.stage, self.count = "release", 0
        if self.stage == "release":
            act[:3] = 0.0
            act[3] = 1.0 if self.count < self.release_pause else -1.0
            self.count += 1
        return act.astype(np.float32)


def split_mode(mode: int) -> tuple[int, int]:
    """Env mode id -> (reach phase mode, carry phase mode)."""
    if isinstance(mode, bool) or not isinstance(mode, (int, np.integer)) or not 0 <= int(mode) < len(MODE_NAMES):
        raise ValueError(f"pick-place mode must be an int in 0..{len(MODE_NAMES) - 1}, got {mode!r}")
    return divmod(int(mode), N_PHASE_MODES)


def make_expert(mode: int, rng: np.random.Generator, scene: Any = 0) -> PickPlaceExpert:
    """Scripted expert for training mode ``mode`` = reach * 8 + carry (the layout is the same in every scene)."""
    reach, carry = split_mode(mode)
    return PickPlaceExpert(phase_via_points(reach, OBSTACLE_A), phase_via_points(carry, OBSTACLE_B), rng)


def expert_from_waypoints(waypoints: Any, rng: np.random.Generator, scene: Any = 0) -> PickPlaceExpert:
    """Expert along given way-points (dict ``{"reach", "carry"}`` or flat list; see module docstring)."""
    if isinstance(waypoints, dict):
        unknown = sorted(set(waypoints) - {"reach", "carry"})
        if unknown:
            raise ValueError(f"way-point dict has unknown key(s) {unknown}; expected 'reach' and 'carry'")
        reach = _points(waypoints.get("reach", []), "waypoints['reach']")
        carry = _points(waypoints.get("carry", []), "waypoints['carry']")
        return PickPlaceExpert(reach, carry, rng)
    pts = _points(waypoints, "waypoints")
    grasp = next((i for i, p in enumerate(pts) if np.linalg.norm(p - OBJECT) < GRASP_RADIUS), None)
    if grasp is None:
        raise ValueError(f"flat way-point list has no point within {GRASP_RADIUS} m of the object "
                         f"{OBJECT.tolist()} (the grasp point)")
    if len(pts) == grasp + 1 or np.linalg.norm(pts[-1] - TARGET) >= SUCCESS_TOL:
        raise ValueError(f"flat way-point list must end within {SUCCESS_TOL} m of the target "
                         f"{TARGET.tolist()} (the release point), after the grasp point")
    return PickPlaceExpert(pts[:grasp], pts[grasp + 1:-1], rng)


def _points(value: Any, where: str) -> list[np.ndarray]:
    if not isinstance(value, (list, tuple, np.ndarray)):
        raise ValueError(f"{where}: expected a list of [x, y, z] points, got {value!r}")
    out = []
    for i, p in enumerate(value):
        arr = np.asarray(p, dtype=float)
        if arr.shape != (3,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"{where}[{i}]: expected [x, y, z], got {p!r}")
        out.append(arr)
    return out


# -------------------------------------------------------------------------------------- classifier


def classify_phase(positions: np.ndarray, centre: np.ndarray) -> int | str:
    """Phase mode of an end-effector path by how it passes ``centre``'s obstacle, or :data:`NOVEL`.

    Uses the median (x, z) offset from the obstacle centre while the path is inside the obstacle's y-slab:
    the dominant axis and sign give the side, its size tight / wide; a large off-axis offset (rounding a
    corner diagonally) or no crossing at all is novel.
    """
    pos = np.asarray(positions, float)
    inside = np.abs(pos[:, 1] - centre[1]) <= OBSTACLE_HALF[1] + 0.01 if len(pos) else np.zeros(0, bool)
    if not inside.any():
        return NOVEL
    dx, dz = np.median(pos[inside][:, [0, 2]] - centre[[0, 2]], axis=0)
    r, s = max(abs(dx), abs(dz)), min(abs(dx), abs(dz))
    if s > MAX_OFF_AXIS or not MIN_OFFSET <= r < MAX_OFFSET:
        return NOVEL
    side = ("right" if dx > 0 else "left") if abs(dx) >= abs(dz) else ("over" if dz > 0 else "under")
    return SIDES.index(side) * 2 + int(r >= TIGHT_WIDE_SPLIT)


def classify_mode(states: np.ndarray, scene: Any = 0) -> int | str:
    """Training mode (reach * 8 + carry) of ``observation.state`` rows [x, y, z, gripper], or :data:`NOVEL`.

    The trajectory is split on the gripper state: the reach phase is everything before the gripper first
    closes, the carry phase runs from there until it opens again. Each phase is classified against its
    obstacle; if either is novel (or the gripper never closes) the trajectory is novel.
    """
    s = np.asarray(states, float)
    if s.ndim != 2 or s.shape[1] < 4:
        raise ValueError(f"classify_mode expects rows [x, y, z, gripper], got shape {s.shape}")
    closed = s[:, 3] > 0.5
    if not closed.any():
        return NOVEL
    g0 = int(np.argmax(closed))
    reopen = np.flatnonzero(~closed[g0:])
    g1 = g0 + int(reopen[0]) if len(reopen) else len(s)
    reach = classify_phase(s[:g0, :3], OBSTACLE_A)
    carry = classify_phase(s[g0:g1, :3], OBSTACLE_B)
    if reach == NOVEL or carry == NOVEL:
        return NOVEL
    return int(reach) * N_PHASE_MODES + int(carry)


# ------------------------------------------------------------------------------------- plotting hooks


def static_primitives(scene: Any = 0) -> tuple[Barrier, ...]:
    """Built-in obstacles that ``scene`` leaves in place (drawn by ``envs.plotting.draw_scene``)."""
    removed = set(load_scene(scene, ENV_NAME).remove)
    return tuple(Barrier("box", tuple(map(float, centre)), half_size=OBSTACLE_HALF, name=name)
                 for name, centre in zip(OBSTACLE_NAMES, (OBSTACLE_A, OBSTACLE_B), strict=True)
                 if name not in removed)


LANDMARKS = {"start": START, "object": OBJECT, "goal": TARGET}


# ------------------------------------------------------------------------------------- registration

SUITE_ENV = register_suite_env(SuiteEnv(
    name="pick-place",
    gym_id=GYM_ID,
    scene_key=ENV_NAME,
    lerobot_env_type="pdp_pick_place",
    module=__name__,
    mode_names=MODE_NAMES,
    trace_dims=(0, 1, 2),
    max_episode_steps=MAX_EPISODE_STEPS,
    fps=round(1 / DT),
    segment_on_gripper=3,
))

if GYM_ID not in gym.registry:
    gym.register(id=GYM_ID, entry_point=f"{__name__}:PickPlaceEnv", max_episode_steps=MAX_EPISODE_STEPS)


def _renderer(model: mujoco.MjModel, height: int, width: int) -> mujoco.Renderer:
    """MuJoCo's renderer, or an error saying how to get one on a machine without a display: MuJoCo picks its
    OpenGL backend from ``MUJOCO_GL`` when it is imported, so it cannot be chosen here (and a backend whose
    library is missing would break ``import mujoco`` for every env, not only this one's pictures)."""
    try:
        return mujoco.Renderer(model, height, width)
    except mujoco.FatalError as e:
        if "OpenGL" not in str(e):
            raise
        raise RuntimeError(
            f"pick-place renders its camera and videos with MuJoCo's OpenGL renderer, which has no context here "
            f"({e}): on a machine without a display set MUJOCO_GL=egl (or osmesa) in the environment before "
            "starting, e.g. `MUJOCO_GL=egl lerobot-eval ...`") from e
