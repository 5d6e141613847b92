"""``lerobot_pdp/KitchenMicrowave-v0``: open the Franka Kitchen microwave along one of several routes.

The paper's OpenMicrowave domain. It wraps gymnasium-robotics ``FrankaKitchen-v1``
(``tasks_to_complete=["microwave"]``) and adds the scene's barriers to the kitchen model at load time
with ``mujoco.MjSpec``, so the robot, the kitchen and its dynamics are exactly the original ones.

Frames. Scene files and way-points are in the kitchen's **world frame** (metres, z up): the robot base
is at (0, 0, 1.8), the counter top under the microwave at z = 1.60, the handle (door closed) at
:data:`HANDLE` = (-0.642, 0.493, 1.792) and the door hinge at :data:`HINGE` (axis +z; the door opens
towards the robot, hinge angle decreasing). Mode templates are written in a *handle frame* for
readability: origin at the closed-door handle, ``t`` along the door away from the hinge (world ~ +x),
``n`` the door's outward normal (towards the robot, world ~ -y), ``z`` up.

Observation (``Dict``)::

    agent_pos          (21,) = [ee xyz (3, site ``end_effector``, world frame),
                                joint qpos (9: 7 arm + 2 fingers), joint qvel (9)]
    environment_state  (5,)  = [microwave hinge angle (rad), handle xyz (3, site ``microhandle_site``),
                                hinge angular velocity (rad/s)]

Joint qpos/qvel are the kitchen's own (slightly noisy) robot observation: the kitchen integrates the
velocity action from exactly these values, so a policy (or the expert) that sees them can act exactly.
``agent_pos[:3]`` is the behavior trace, hence ``trace_dims=(0, 1, 2)``.

Actions: the kitchen's own 9 joint-velocity commands in [-1, 1] (x 2 rad/s, integrated over dt = 0.08 s
into position targets); the last two drive the fingers (+1 opens).

``info``: ``is_success`` (door opened past the kitchen's threshold, |q + 0.75| < 0.3, and no collision),
``collided`` (the simulator reports a contact between a robot geom and a *scene barrier*; touching the
kitchen itself - counter, kettle, microwave body, door - does not count, since the original task touches
the door and incidental furniture contact is not what scenes constrain; which barrier touched which robot
body: :meth:`~KitchenMicrowaveEnv.barrier_contacts`), ``clearance`` (current robot-to-barrier distance,
approximate, see :meth:`~KitchenMicrowaveEnv.clearance`), ``min_clearance`` (its minimum over the episode
so far; ``inf`` without barriers), ``door_angle`` and, on the last step, ``mode``
(:func:`classify_mode` of the episode's ``agent_pos`` rows). Episodes end on success or collision and are
truncated after :data:`MAX_EPISODE_STEPS` (training routes need 53-77 steps).

Scenes must keep clear of the start end effector (5 cm), the handle (4 cm), the robot's reset pose and
the kettle (a free body an overlapping barrier would launch); violations raise :class:`SceneError`.
Barriers are static world geoms; they do not stop the door (none of the shipped ones is in its swing).
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from .scene import Scene, SceneError, load_scene
from .suite import NOVEL, SuiteEnv, mode_info, register_suite_env

ENV_NAME = "kitchen-microwave"
SCENE_KEY = "kitchen_microwave"
GYM_ID = "lerobot_pdp/KitchenMicrowave-v0"
MODE_NAMES = ("front", "high", "low", "right", "high-right")
MAX_EPISODE_STEPS = 150
DT = 0.08  # kitchen control period (frame_skip 40 x 2 ms); LeRobot/gym metadata round 12.5 Hz to 12
FPS = 12

HANDLE = np.array([-0.641919, 0.492627, 1.792])  # microhandle_site, door closed
HINGE = np.array([-1.12758, 0.454906, 1.792])  # microwave hinge anchor; axis +z
DOOR_YAW = 0.30108  # rotation of the microwave about +z; the door's outward normal is (sin, -cos, 0)
EE_START = np.array([-0.431879, 0.118886, 2.024569])  # end_effector site at the (deterministic) reset

_T = np.array([math.cos(DOOR_YAW), math.sin(DOOR_YAW), 0.0])  # along the door, away from the hinge
_N = np.array([math.sin(DOOR_YAW), -math.cos(DOOR_YAW), 0.0])  # outward door normal (towards the robot)
_Z = np.array([0.0, 0.0, 1.0])

# Mode templates: via-points in the handle frame (t, n, z), passed before the common pre-grasp point.
MODE_VIAS: dict[str, tuple[tuple[float, float, float], ...]] = {
    "front": ((0.02, 0.38, 0.0),),
    "high": ((0.0, 0.20, 0.24),),
    "low": ((0.0, 0.24, -0.10),),
    "right": ((0.26, 0.36, 0.18), (0.06, 0.20, 0.14)),  # second via keeps the fingers off the kettle
    "high-right": ((0.22, 0.16, 0.30), (0.08, 0.14, 0.22)),
}
PREGRASP_N = 0.12  # pre-grasp point: this far out along the door normal, then straight in to the handle
CLASSIFY_TOL = 0.07  # a trace must pass within this of every via-point of a mode (jitter is +-0.02)

BARRIER_PREFIX = "pdp_barrier_"
_JOINT_LO = np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, 0.0, -2.8973])  # model range and
_JOINT_HI = np.array([2.8973, 1.7628, 2.8973, -0.4, 2.8973, 2.1127, 2.8973])  # franka_config bounds
# Null-space posture bias: the grasp configuration of the "front" route. Without it the redundant
# wrist drifts into a flipped branch on some routes and hits joint 6's limit just above the handle.
_Q_NOMINAL = np.array([-1.0, -1.74, 2.0, -1.6, -1.0, 1.13, 2.75])
_POSTURE_GAIN = 0.1
_ACT_SCALE = 2.0 * DT  # one action unit moves the position target by this many rad (m for fingers)


def handle_frame_to_world(p: Sequence[float]) -> np.ndarray:
    """A point given as (t, n, z) offsets from the closed-door handle, in world coordinates."""
    t, n, z = (float(v) for v in p)
    return HANDLE + t * _T + n * _N + z * _Z


def mode_waypoints(mode: int | str) -> list[np.ndarray]:
    """World-frame via-points of a training mode (without jitter)."""
    name = _mode_name(mode)
    return [handle_frame_to_world(v) for v in MODE_VIAS[name]]


def _mode_name(mode: int | str) -> str:
    if isinstance(mode, str) and mode in MODE_VIAS:
        return mode
    if isinstance(mode, (int, np.integer)) and not isinstance(mode, bool) and 0 <= int(mode) < len(MODE_NAMES):
        return MODE_NAMES[int(mode)]
    raise ValueError(f"unknown kitchen-microwave mode {mode!r}; expected 0-{len(MODE_NAMES) - 1} or one of "
                     f"{list(MODE_NAMES)}")


# ----------------------------------------------------------------------------------------------------
# Model loading: the kitchen's own XML plus barrier geoms, compiled with MjSpec.


def _kitchen_xml() -> Path:
    import gymnasium_robotics.envs.franka_kitchen.franka_env as franka_env

    return (Path(franka_env.__file__).parent / "../assets/kitchen_franka/kitchen_assets/kitchen_env_model.xml").resolve()


def _add_barriers(spec: Any, scene: Scene) -> None:
    """Add the scene's barriers as static world geoms that collide with the robot.

    The kitchen's robot geoms have contype 1 and its furniture contype 0 / conaffinity 1; barriers use the
    furniture's convention (contype 0, conaffinity 1), so they touch the robot (and the kettle) but never
    each other or the floor.
    """
    import mujoco

    for i, b in enumerate(scene.barriers):
        g = spec.worldbody.add_geom()
        g.name = f"{BARRIER_PREFIX}{i}"
        g.pos = list(b.center3(default_z=0.0))
        if b.shape == "box":
            g.type = mujoco.mjtGeom.mjGEOM_BOX
            g.size = list(b.half_size)
        else:
            g.type = mujoco.mjtGeom.mjGEOM_CYLINDER
            g.size = [b.radius, b.half_height, 0.0]
        g.contype = 0
        g.conaffinity = 1
        g.group = 1
        g.rgba = list(b.rgba) if b.rgba else [0.85, 0.25, 0.2, 0.7]


_PATCH_LOCK = threading.Lock()


def _make_kitchen(scene: Scene, **kwargs: Any) -> Any:
    """Build gymnasium-robotics' ``KitchenEnv`` whose robot model carries the scene's barriers.

    ``KitchenEnv.__init__`` constructs ``FrankaRobot`` by module-global name, and ``MujocoEnv.__init__``
    loads the model through ``_initialize_simulation``. We override that method in a subclass and swap the
    module global only for the duration of the constructor (under a lock), instead of copying their code.
    """
    import gymnasium_robotics.envs.franka_kitchen.franka_env as franka_env
    import gymnasium_robotics.envs.franka_kitchen.kitchen_env as kitchen_env
    import mujoco

    class _BarrierFrankaRobot(franka_env.FrankaRobot):
        def _initialize_simulation(self):  # noqa: ANN202 - MujocoEnv's signature
            spec = mujoco.MjSpec.from_file(self.fullpath)
            _add_barriers(spec, scene)
            model = spec.compile()
            model.vis.global_.offwidth = max(model.vis.global_.offwidth, self.width)
            model.vis.global_.offheight = max(model.vis.global_.offheight, self.height)
            return model, mujoco.MjData(model)

    with _PATCH_LOCK:
        original = kitchen_env.FrankaRobot
        kitchen_env.FrankaRobot = _BarrierFrankaRobot
        try:
            return kitchen_env.KitchenEnv(tasks_to_complete=["microwave"], terminate_on_tasks_completed=False,
                                          **kwargs)
        finally:
            kitchen_env.FrankaRobot = original


@functools.cache
def _kinematics_model() -> Any:
    """The plain kitchen model, for the expert's forward kinematics (shared, read-only)."""
    import mujoco

    return mujoco.MjModel.from_xml_path(str(_kitchen_xml()))


def _geom_sample_points(model: Any, geoms: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample points (geom frame) of collision geoms: (geom id per point, local xyz, radius per point)."""
    import mujoco

    ids, pts, rad = [], [], []
    for g in geoms:
        gtype, size = model.geom_type[g], model.geom_size[g]
        if gtype == mujoco.mjtGeom.mjGEOM_MESH:
            mid = model.geom_dataid[g]
            adr, num = model.mesh_vertadr[mid], model.mesh_vertnum[mid]
            local, r = model.mesh_vert[adr:adr + num].astype(np.float64), 0.0
        elif gtype == mujoco.mjtGeom.mjGEOM_CAPSULE:
            local, r = np.stack([np.zeros(9), np.zeros(9), np.linspace(-size[1], size[1], 9)], axis=1), size[0]
        elif gtype == mujoco.mjtGeom.mjGEOM_SPHERE:
            local, r = np.zeros((1, 3)), size[0]
        elif gtype == mujoco.mjtGeom.mjGEOM_BOX:
            grid = np.array(np.meshgrid(*[[-v, 0.0, v] for v in size[:3]], indexing="ij")).reshape(3, -1).T
            local, r = grid, 0.0
        else:
            raise NotImplementedError(f"clearance for robot geom type {gtype} is not implemented")
        ids.append(np.full(len(local), g))
        pts.append(local)
        rad.append(np.full(len(local), r))
    return np.concatenate(ids), np.concatenate(pts), np.concatenate(rad)


def _signed_distance(b: Any, pts: np.ndarray) -> np.ndarray:
    """Vectorized signed distance from points (N, 3) to a barrier primitive (negative inside)."""
    c = np.asarray(b.center3(0.0))
    d = pts - c
    if b.shape == "box":
        q = np.abs(d) - np.asarray(b.half_size)
        return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)
    radial = np.hypot(d[:, 0], d[:, 1]) - b.radius
    axial = np.abs(d[:, 2]) - b.half_height
    outside = np.hypot(np.maximum(radial, 0.0), np.maximum(axial, 0.0))
    return outside + np.minimum(np.maximum(radial, axial), 0.0)


# ----------------------------------------------------------------------------------------------------
# The environment.


class KitchenMicrowaveEnv(gym.Env):
    """FrankaKitchen microwave opening with scene barriers; see the module docstring for the spaces."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": FPS}

    def __init__(
        self,
        scene: int | str | Path | Scene | dict | None = 0,
        max_episode_steps: int = MAX_EPISODE_STEPS,
        render_mode: str | None = None,
        robot_noise_ratio: float = 0.01,
        object_noise_ratio: float = 0.0005,
    ) -> None:
        self.scene = load_scene(scene, SCENE_KEY)
        if self.scene.remove:
            raise SceneError(f"{self.scene.source}: 'remove' is not supported by {ENV_NAME} (the kitchen's "
                             f"furniture carries joints the task observation depends on); got "
                             f"{list(self.scene.remove)}")
        self.scene.check_clear({"start end effector": EE_START}, margin=0.05)
        self.scene.check_clear({"microwave handle": HANDLE}, margin=0.04)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if int(max_episode_steps) < 1:
            raise ValueError(f"max_episode_steps must be >= 1, got {max_episode_steps}")
        self.render_mode = render_mode
        self._max_episode_steps = int(max_episode_steps)
        self.task_description = "open the microwave door"
        self.task = "kitchen_microwave"

        self._kitchen = _make_kitchen(self.scene, render_mode=render_mode, robot_noise_ratio=robot_noise_ratio,
                                      object_noise_ratio=object_noise_ratio)
        self.model = self._kitchen.model
        self.data = self._kitchen.data
        m = self.model
        self._ee_site = m.site("end_effector").id
        self._handle_site = m.site("microhandle_site").id
        robot_root = m.body("panda0_link0").id
        # Moving robot bodies only: the base is welded to the world, and MuJoCo never generates contacts
        # between static geoms, so a barrier touching the base is neither a collision nor reachable.
        robot_bodies = {b for b in range(m.nbody) if self._is_descendant(b, robot_root) and m.body_weldid[b] != 0}
        self._robot_geoms = np.array([g for g in range(m.ngeom) if m.geom_bodyid[g] in robot_bodies
                                      and (m.geom_contype[g] or m.geom_conaffinity[g])], dtype=int)
        self._barrier_geoms = np.array([m.geom(f"{BARRIER_PREFIX}{i}").id for i in range(len(self.scene.barriers))],
                                       dtype=int)
        self._pt_geom, self._pt_local, self._pt_radius = _geom_sample_points(m, self._robot_geoms)
        self._hinge_qadr = m.jnt_qposadr[m.joint("microwave").id]
        self._hinge_vadr = m.jnt_dofadr[m.joint("microwave").id]
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(9,), dtype=np.float32)
        self.observation_space = gym.spaces.Dict({
            "agent_pos": gym.spaces.Box(-np.inf, np.inf, shape=(21,), dtype=np.float64),
            "environment_state": gym.spaces.Box(-np.inf, np.inf, shape=(5,), dtype=np.float64),
        })
        self._steps = 0
        self._states: list[np.ndarray] = []
        self._min_clearance = math.inf

        # The reset pose is deterministic: check once that no barrier intersects the robot there, and
        # that none intersects the kettle (a free body: an overlap would launch it and change the dynamics).
        self._kitchen.reset(seed=0)
        d0 = self.clearance()
        if d0 < 0.01:
            raise SceneError(f"{self.scene.source}: a barrier touches the robot at its reset pose "
                             f"(clearance {d0:.3f} m, need >= 0.010 m)")
        kettle = m.body("kettle").id
        for c in self.data.contact[: self.data.ncon]:
            pair = (int(c.geom1), int(c.geom2))
            if any(g in self._barrier_geoms for g in pair) and any(
                    m.body_rootid[m.geom_bodyid[g]] == kettle for g in pair):
                b = next(g for g in pair if g in self._barrier_geoms)
                raise SceneError(f"{self.scene.source}: barriers[{m.geom(b).name[len(BARRIER_PREFIX):]}] "
                                 f"intersects the kettle (a free body); move it clear of the kettle")

    def _is_descendant(self, body: int, root: int) -> bool:
        while body > 0:
            if body == root:
                return True
            body = int(self.model.body_parentid[body])
        return False

    # -- physics queries ------------------------------------------------------------------------------

    def clearance(self) -> float:
        """Minimum robot-to-barrier distance (``inf`` without barriers), from the robot's collision geoms.

        Evaluated analytically on sample points of every moving robot collision geom (mesh vertices,
        capsule axes minus their radius, box corners/edge and face centres) against each barrier
        primitive, so it is a slight over-estimate (by at most a mesh facet's sag). ``mj_geomDistance`` is
        not used: in MuJoCo 3.11 it returns spurious 0.0 (native CCD) or spurious negative (libccd)
        distances for mesh-box pairs 3-40 cm apart. Collisions themselves come from the simulator's
        contacts, see :meth:`barrier_contacts`.
        """
        if not self.scene.barriers:
            return math.inf
        rot = self.data.geom_xmat[self._pt_geom].reshape(-1, 3, 3)
        pts = np.einsum("nij,nj->ni", rot, self._pt_local) + self.data.geom_xpos[self._pt_geom]
        best = math.inf
        for b in self.scene.barriers:
            best = min(best, float(np.min(_signed_distance(b, pts) - self._pt_radius)))
        return best

    def _barrier_contact_mask(self) -> np.ndarray:
        """Per contact of the current state: a penetrating barrier-robot contact (what ``collided`` means)."""
        c = self.data.contact[: self.data.ncon]
        g1, g2 = np.asarray(c.geom1), np.asarray(c.geom2)
        hit = np.isin(g1, self._barrier_geoms) | np.isin(g2, self._barrier_geoms)
        robot = np.isin(g1, self._robot_geoms) | np.isin(g2, self._robot_geoms)
        return hit & robot & (np.asarray(c.dist) < 0)

    def _barrier_contact(self) -> bool:
        return bool(len(self._barrier_geoms) and np.any(self._barrier_contact_mask()))

    def barrier_contacts(self) -> list[str]:
        """What touches what right now: ``"<barrier name> / <robot body>"`` for every penetrating contact
        of a scene barrier with the robot (barriers without a name are ``barriers[i]``), sorted. Empty when
        ``collided`` would be False; called by diagnostics after a collision, not on every step."""
        if not len(self._barrier_geoms):
            return []
        m, hits = self.model, set()
        for k in np.flatnonzero(self._barrier_contact_mask()):
            c = self.data.contact[int(k)]
            g1, g2 = int(c.geom1), int(c.geom2)
            barrier, robot = (g1, g2) if g1 in self._barrier_geoms else (g2, g1)
            i = int(m.geom(barrier).name[len(BARRIER_PREFIX):])
            hits.add(f"{self.scene.barriers[i].name or f'barriers[{i}]'} / {m.body(m.geom_bodyid[robot]).name}")
        return sorted(hits)

    def _obs(self, kitchen_obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        robot = np.asarray(kitchen_obs["observation"][:18], dtype=np.float64)
        ee = self.data.site_xpos[self._ee_site]
        handle = self.data.site_xpos[self._handle_site]
        env_state = np.array([self.data.qpos[self._hinge_qadr], *handle, self.data.qvel[self._hinge_vadr]])
        return {"agent_pos": np.concatenate([ee, robot]).astype(np.float64),
                "environment_state": env_state.astype(np.float64)}

    # -- gym API --------------------------------------------------------------------------------------

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        kobs, _ = self._kitchen.reset(seed=seed)
        self._steps = 0
        obs = self._obs(kobs)
        self._states = [obs["agent_pos"].copy()]
        clearance = self.clearance()
        self._min_clearance = clearance
        info = {"is_success": False, "collided": False, "clearance": clearance, "min_clearance": clearance,
                "door_angle": float(obs["environment_state"][0])}
        return obs, info

    def step(self, action):
        action = np.asarray(action, dtype=np.float64).reshape(-1)
        if action.shape != (9,):
            raise ValueError(f"{GYM_ID} expects 9 joint-velocity actions, got shape {action.shape}")
        if not np.all(np.isfinite(action)):
            raise ValueError(f"{GYM_ID} got a non-finite action {action.tolist()}")
        kobs, _, _, _, kinfo = self._kitchen.step(np.clip(action, -1.0, 1.0))
        self._steps += 1
        obs = self._obs(kobs)
        self._states.append(obs["agent_pos"].copy())
        clearance = self.clearance()
        self._min_clearance = min(self._min_clearance, clearance)
        collided = self._barrier_contact()
        opened = "microwave" in kinfo["episode_task_completions"]
        success = opened and not collided
        terminated = bool(collided or success)
        truncated = (not terminated) and self._steps >= self._max_episode_steps
        info = {"is_success": bool(success), "collided": bool(collided), "clearance": clearance,
                "min_clearance": self._min_clearance, "door_angle": float(obs["environment_state"][0])}
        if terminated or truncated:
            info.update(mode_info(classify_mode(np.stack(self._states)), MODE_NAMES))
        return obs, float(success), terminated, truncated, info

    def render(self):
        return self._kitchen.render()

    def close(self) -> None:
        self._kitchen.close()


# ----------------------------------------------------------------------------------------------------
# Scripted expert.


class MicrowaveExpert:
    """Damped-least-squares IK expert: via-points -> pre-grasp -> grasp the handle -> pull along the arc.

    It owns a private copy of the kitchen model for kinematics (site ``end_effector`` Jacobian) and turns
    each IK step into the kitchen's velocity action, adding gravity feed-forward (``qfrc_bias / kp``: the
    position servos otherwise sag ~4 cm) and clamping to joint limits (joint 2 starts at its lower limit;
    clamped joints are removed from the Jacobian and the step re-solved, so the others compensate).
    The gripper is kept horizontal (fingers side by side) with a weak yaw target along the door normal, so
    the fingers straddle the vertical handle bar. The expert is open loop with respect to barriers.
    """

    def __init__(
        self,
        waypoints: Sequence[Sequence[float]],
        speed: float = 0.25,
        start_delay: int = 0,
        speed_jitter: Sequence[float] | None = None,
        grasp_offset: float = 0.01,
        pull_lead: float = 0.12,
        yaw_follow: float = 0.5,
        close_steps: int = 3,
    ) -> None:
        self.waypoints = [np.asarray(w, dtype=np.float64) for w in waypoints]
        self.speed = float(speed)
        self.start_delay = int(start_delay)
        self.speed_jitter = None if speed_jitter is None else [float(s) for s in speed_jitter]
        self.grasp_offset = float(grasp_offset)
        self.pull_lead = float(pull_lead)
        self.yaw_follow = float(yaw_follow)
        self.close_steps = int(close_steps)
        import mujoco

        self._mj = mujoco
        self._m = _kinematics_model()
        self._d = mujoco.MjData(self._m)
        self._site = self._m.site("end_effector").id
        self._hinge_qadr = self._m.jnt_qposadr[self._m.joint("microwave").id]
        self._kp = self._m.actuator_gainprm[:7, 0].copy()
        self._jp = np.zeros((3, self._m.nv))
        self._jr = np.zeros((3, self._m.nv))
        self.reset(None)

    def reset(self, obs: dict[str, np.ndarray] | None) -> None:
        self._phase = "delay"
        self._t = 0
        self._s = 0.0
        self._k = 0
        self._path: np.ndarray | None = None
        if obs is not None:
            self._build_path(np.asarray(obs["agent_pos"][:3]), np.asarray(obs["environment_state"][1:4]))

    def _build_path(self, ee: np.ndarray, handle: np.ndarray) -> None:
        approach = -_N
        self._grasp = handle - self.grasp_offset * approach  # ee site sits behind the finger pads
        pregrasp = handle - PREGRASP_N * approach
        pts = [ee, *self.waypoints, pregrasp]
        self._path = np.stack(pts)
        seg = np.linalg.norm(np.diff(self._path, axis=0), axis=1)
        if self.speed_jitter is not None and len(self.speed_jitter) >= len(seg):
            seg = seg / np.asarray(self.speed_jitter[: len(seg)])  # slower segments are "longer" in time
        self._seg_time = seg
        self._cum = np.concatenate([[0.0], np.cumsum(seg)])
        self._seg_len = np.linalg.norm(np.diff(self._path, axis=0), axis=1)
        self._hold = ee.copy()

    def _carrot(self) -> np.ndarray:
        s = min(self._s, self._cum[-1])
        i = int(min(np.searchsorted(self._cum, s, side="right") - 1, len(self._path) - 2))
        f = (s - self._cum[i]) / max(self._cum[i + 1] - self._cum[i], 1e-9)
        return self._path[i] + f * (self._path[i + 1] - self._path[i])

    def _ik(self, q: np.ndarray, door: float, target: np.ndarray, yaw: float, fingers: float) -> tuple[np.ndarray, np.ndarray]:
        mj, m, d = self._mj, self._m, self._d
        d.qpos[:9] = q
        d.qpos[self._hinge_qadr] = door
        d.qvel[:] = 0.0
        mj.mj_forward(m, d)
        ee = d.site_xpos[self._site].copy()
        rot = d.site_xmat[self._site].reshape(3, 3)
        err = target - ee
        norm = np.linalg.norm(err)
        if norm > 0.04:
            err *= 0.04 / norm
        w_up = np.cross(rot[:, 0], _Z)  # site x axis -> world up: fingers side by side, gripper level
        z_des = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
        z_cur = rot[:, 2].copy()
        z_cur[2] = 0.0
        z_cur /= max(np.linalg.norm(z_cur), 1e-9)
        w_yaw = float(np.clip(np.cross(z_cur, z_des)[2], -0.2, 0.2))
        mj.mj_jacSite(m, d, self._jp, self._jr, self._site)
        wrot, wyaw = 0.3, 0.1
        jac = np.vstack([self._jp[:, :7], wrot * self._jr[:2, :7], wyaw * self._jr[2:3, :7]])
        e = np.concatenate([err, wrot * w_up[:2], [wyaw * w_yaw]])
        free = np.ones(7, dtype=bool)
        posture = _POSTURE_GAIN * (_Q_NOMINAL - q[:7])
        for _ in range(4):
            jf = jac * free
            inv = np.linalg.solve(jf @ jf.T + 0.05**2 * np.eye(6), np.eye(6))
            dq = jf.T @ (inv @ e) + (posture - jf.T @ (inv @ (jf @ posture))) * free
            qn = q[:7] + dq
            bad = ((qn < _JOINT_LO + 0.02) | (qn > _JOINT_HI - 0.02)) & free
            if not bad.any():
                break
            free &= ~bad
        q_des = np.clip(q[:7] + dq, _JOINT_LO + 0.02, _JOINT_HI - 0.02)
        ctrl = q_des + d.qfrc_bias[:7] / self._kp
        action = np.empty(9)
        action[:7] = (ctrl - q[:7]) / _ACT_SCALE
        action[7:] = fingers
        return np.clip(action, -1.0, 1.0), ee

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        agent = np.asarray(obs["agent_pos"], dtype=np.float64)
        env_state = np.asarray(obs["environment_state"], dtype=np.float64)
        q, door = agent[3:12], float(env_state[0])
        if self._path is None:
            self._build_path(agent[:3], env_state[1:4])
        self._t += 1
        if self._phase == "delay":
            if self._t > self.start_delay:
                self._phase = "move"
            else:
                return self._ik(q, door, self._hold, DOOR_YAW, 1.0)[0].astype(np.float32)
        if self._phase == "move":
            self._s += self.speed * DT
            action, ee = self._ik(q, door, self._carrot(), DOOR_YAW, 1.0)
            if self._s >= self._cum[-1] and np.linalg.norm(ee - self._path[-1]) < 0.02:
                self._phase = "insert"
        elif self._phase == "insert":
            action, ee = self._ik(q, door, self._grasp, DOOR_YAW, 1.0)
            if np.linalg.norm(ee - self._grasp) < 0.008:
                self._phase = "grasp"
        elif self._phase == "grasp":
            action, _ = self._ik(q, door, self._grasp, DOOR_YAW, -1.0)
            self._k += 1
            if self._k >= self.close_steps:
                self._phase = "pull"
        else:  # pull: lead the door along its arc about the hinge, fingers closed on the handle
            angle = max(door - self.pull_lead, -0.9)
            c, s = math.cos(angle), math.sin(angle)
            rel = self._grasp - HINGE
            target = HINGE + np.array([c * rel[0] - s * rel[1], s * rel[0] + c * rel[1], rel[2]])
            action, _ = self._ik(q, door, target, DOOR_YAW + self.yaw_follow * angle, -1.0)
        return action.astype(np.float32)


def _check_waypoints(waypoints: Any) -> list[np.ndarray]:
    try:
        arr = np.asarray(waypoints, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"way-points must be a list of [x, y, z] points, got {waypoints!r}") from e
    if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) == 0:
        raise ValueError(f"way-points must be a non-empty list of [x, y, z] world points, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"way-points must be finite, got {arr.tolist()}")
    reach = np.linalg.norm(arr - np.array([0.0, 0.0, 1.8]), axis=1)
    if np.any(reach > 0.9):
        i = int(np.argmax(reach))
        raise ValueError(f"way-point {i} {arr[i].round(3).tolist()} is {reach[i]:.2f} m from the robot base "
                         f"(0, 0, 1.8); the Franka reaches ~0.85 m")
    return list(arr)


def _jittered_expert(waypoints: list[np.ndarray], rng: np.random.Generator, jitter: float) -> MicrowaveExpert:
    vias = [w + rng.uniform(-jitter, jitter, size=3) for w in waypoints]
    return MicrowaveExpert(
        vias,
        speed=float(rng.uniform(0.2, 0.3)),
        start_delay=int(rng.integers(0, 4)),
        speed_jitter=list(rng.uniform(0.85, 1.15, size=len(vias) + 1)),
        grasp_offset=float(rng.uniform(0.0, 0.02)),
        pull_lead=float(rng.uniform(0.1, 0.15)),
        yaw_follow=float(rng.uniform(0.3, 0.6)),
    )


def make_expert(mode: int | str, rng: np.random.Generator, scene: Any = 0) -> MicrowaveExpert:
    """Expert for a training mode: the mode's via-points with +-2 cm jitter, random speed and timing.

    ``scene`` is accepted for the suite's API; the training routes do not depend on it.
    """
    return _jittered_expert(mode_waypoints(mode), rng, jitter=0.02)


def expert_from_waypoints(waypoints: Any, rng: np.random.Generator, scene: Any = 0) -> MicrowaveExpert:
    """Expert through arbitrary world-frame via-points (``None``: the scene file's ``waypoints``).

    The via-points are passed before the common pre-grasp point; jitter is 1 cm so a route given for a
    narrow opening stays inside it.
    """
    if waypoints is None:
        sc = load_scene(scene, SCENE_KEY)
        if sc.waypoints is None:
            raise ValueError(f"{sc.source} ships no 'waypoints'; pass way-points explicitly")
        waypoints = sc.waypoints
    return _jittered_expert(_check_waypoints(waypoints), rng, jitter=0.01)


def classify_mode(states: np.ndarray, scene: Any = 0) -> int | str:
    """Training mode whose via-points the end-effector trace passed closest to, or ``"novel"``.

    A mode matches when the trace (``states[:, :3]``) comes within :data:`CLASSIFY_TOL` of each of its
    via-points; the best-matching mode (smallest worst-case distance) wins.
    """
    x = np.asarray(states, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] < 3 or len(x) == 0:
        raise ValueError(f"states must be (T, >=3) agent_pos rows with the ee xyz first, got shape {x.shape}")
    trace = x[:, :3]
    best, best_score = None, math.inf
    for i, name in enumerate(MODE_NAMES):
        score = max(float(np.min(np.linalg.norm(trace - v, axis=1))) for v in mode_waypoints(name))
        if score < best_score:
            best, best_score = i, score
    return best if best_score <= CLASSIFY_TOL else NOVEL


# ----------------------------------------------------------------------------------------------------
# Registration (cheap: no gymnasium-robotics import here).

SUITE_ENV = register_suite_env(SuiteEnv(
    name=ENV_NAME,
    gym_id=GYM_ID,
    scene_key=SCENE_KEY,
    lerobot_env_type="pdp_kitchen_microwave",
    module=__name__,
    mode_names=MODE_NAMES,
    trace_dims=(0, 1, 2),
    max_episode_steps=MAX_EPISODE_STEPS,
    fps=FPS,
))

if GYM_ID not in gym.registry:
    gym.register(id=GYM_ID, entry_point=f"{__name__}:KitchenMicrowaveEnv", max_episode_steps=MAX_EPISODE_STEPS)
