"""``--teleop.type=pdp_waypoints``: a scripted operator for the ``pdp_sim`` robot."""

from __future__ import annotations

from dataclasses import dataclass

from lerobot.teleoperators import TeleoperatorConfig

from ..config_errors import config_error


@TeleoperatorConfig.register_subclass("pdp_waypoints")
@dataclass(kw_only=True)
class PDPWaypointsConfig(TeleoperatorConfig):
    """Drive a ``pdp_sim`` robot along a route, like a person with a leader arm.

    Attributes:
        waypoints: ``"scene"`` (the robot's scene file's own way-points) or a JSON/YAML file of points (or a
            scene file with ``waypoints``). Exclusive with ``mode``.
        mode: a training mode of the env, by id (``"3"``) or name: the env's scripted expert for that mode.
        seed: the route's jitter in episode k comes from ``(seed, stream, k)``.
        robot_id: ``--robot.id`` of the robot to drive; None = the only ``pdp_sim`` robot in the process.
    """

    waypoints: str | None = None
    mode: str | None = None
    seed: int = 0
    robot_id: str | None = None

    def __post_init__(self) -> None:
        if (self.waypoints is None) == (self.mode is None):
            raise config_error("pdp_waypoints needs exactly one of --teleop.waypoints=<file or \"scene\"> "
                               "and --teleop.mode=<id or name>")
        if self.mode is not None:
            self.mode = str(self.mode).strip()
            # the id's range depends on the robot's env: PDPWaypoints checks it when it is made, which
            # lerobot-record does before it writes the dataset folder
            try:
                negative = int(self.mode) < 0
            except ValueError:
                negative = False  # a mode name
            if not self.mode or negative:
                raise config_error(f"pdp_waypoints: --teleop.mode={self.mode!r} is not a mode; expected a mode id "
                                   ">= 0 or a mode name of the robot's env")
