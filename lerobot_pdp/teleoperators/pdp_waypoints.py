"""The ``pdp_waypoints`` teleoperator: the env's scripted expert, acting like a person on a leader arm.

LeRobot's record loop calls ``get_action()`` without an observation, but the experts are closed-loop (they
steer towards the next way-point from the current position), as a person watches the follower arm. So the
teleoperator watches its ``pdp_sim`` robot in the same process (:func:`find_robot`), restarts its route when
the robot has reset its scene, and sends neutral actions while the robot is held for a reset.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from lerobot.teleoperators import Teleoperator

from ..robots.pdp_sim import PDPSim, find_robot
from .config_pdp_waypoints import PDPWaypointsConfig


class PDPWaypoints(Teleoperator):
    """A scripted teleoperator of config type ``pdp_waypoints`` (see :class:`PDPWaypointsConfig`)."""

    config_class = PDPWaypointsConfig
    name = "pdp_waypoints"

    def __init__(self, config: PDPWaypointsConfig):
        if config.id is None:
            config.id = "pdp_waypoints"
        super().__init__(config)
        self.config = config
        self.robot: PDPSim | None = None
        self._mode: int | None = None
        self._waypoints: np.ndarray | None = None
        self._expert = None
        self._episode = None
        self._connected = False
        self._checked_for: PDPSim | None = None  # the robot the route was resolved against
        try:
            robot = find_robot(config.robot_id)
        except LookupError:
            return  # no robot yet: connect() checks the route
        # lerobot-record makes the robot, then the teleoperator, then the dataset folder: a mode or way-point
        # file the robot's env cannot take is refused here, before anything is written
        self._resolve_route(robot)

    def _resolve_route(self, robot: PDPSim) -> None:
        """The mode id or way-points of the route in ``robot``'s env and scene (a clear error if they do not fit)."""
        from lerobot_pdp.envs.recording import _resolve_modes, check_waypoints, resolve_waypoints

        if self.config.mode is not None:
            self._mode = _resolve_modes(robot.suite, [self.config.mode])[0]
        else:
            self._waypoints = resolve_waypoints(self.config.waypoints, robot.scene, robot.suite)
            # a point the arm can never reach would record an idle or colliding episode as a demonstration
            check_waypoints(robot.suite, self._waypoints, f"--teleop.waypoints={self.config.waypoints}")
        self._checked_for = robot

    @property
    def action_features(self) -> dict[str, type]:
        robot = self.robot
        if robot is None:
            try:
                robot = find_robot(self.config.robot_id)
            except LookupError:
                return {}
        return robot.action_features

    @property
    def feedback_features(self) -> dict:
        return {}

    @property
    def is_connected(self) -> bool:
        return self._connected

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        """Nothing to calibrate."""

    def configure(self) -> None:
        """Nothing to configure."""

    def connect(self, calibrate: bool = True) -> None:
        """Find the robot and check the route against its env and scene (bad mode or file -> clear error)."""
        robot = find_robot(self.config.robot_id)
        if robot is not self._checked_for:
            self._resolve_route(robot)
        self.robot = robot
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False
        self.robot = None

    def send_feedback(self, feedback: dict[str, Any]) -> None:
        """The robot is watched directly; no feedback channel is needed."""

    def get_action(self) -> dict[str, float]:
        if not self._connected or self.robot is None:
            raise ConnectionError(f"{self} is not connected; call connect() first")
        robot = self.robot
        names = robot.action_keys  # suffixed inside lerobot-rollout
        if robot.obs is None or robot.holding:
            return dict.fromkeys(names, 0.0)
        if self._episode != robot.episode:  # the scene was reset: start the route again
            from lerobot_pdp.envs.recording import WAYPOINT_JOB

            stream = WAYPOINT_JOB if self._mode is None else self._mode
            rng = np.random.default_rng([self.config.seed, stream, robot.episode])
            if self._mode is None:
                self._expert = robot.suite.expert_from_waypoints(self._waypoints, rng, scene=robot.scene)
            else:
                self._expert = robot.suite.make_expert(self._mode, rng, scene=robot.scene)
            self._expert.reset(robot.obs)
            self._episode = robot.episode
        action = np.asarray(self._expert(robot.obs), dtype=float)
        return dict(zip(names, action.tolist(), strict=True))
