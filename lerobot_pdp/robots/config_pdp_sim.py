"""``--robot.type=pdp_sim``: a suite env driven through LeRobot's ``Robot`` interface (no hardware)."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.robots import RobotConfig

from lerobot_pdp.config_errors import config_error


@RobotConfig.register_subclass("pdp_sim")
@dataclass(kw_only=True)
class PDPSimConfig(RobotConfig):
    """A simulated robot: one benchmark env in one scene, with the env's own physics.

    Attributes:
        env: suite env name (``reach-around``, ``avoiding``, ``pick-place``, ``kitchen-microwave``), scene
            key, gym id or ``pdp_*`` env type.
        scene: scene index (``"0"``) or a scene file path.
        outcomes: JSON-lines file; one line per finished episode (``success``, ``collided``, ``mode``, ...)
            is appended to it, marked with the run (``run``: start time and process id; a file that already
            holds lines is warned of). None: no file.
        seed: reset noise of episode k comes from ``(seed, k)``, so a recording is reproducible.
        end_episodes: inside ``lerobot-record``, end the recorded episode when the env episode ends
            (success, collision, time limit), as the operator would press the "next episode" key, and end the
            reset phase at once (the robot has reset its scene itself). False: recorded episodes last
            ``--dataset.episode_time_s``; after the env episode ends the robot holds still until the next
            phase. Outside ``lerobot-record`` the robot resets its scene right after an episode ends.
        camera_names: env cameras recorded as ``observation.images.<name>`` (e.g. ``[oblique]`` on
            reach-around; the env names its valid cameras when one is unknown).
        camera_size: (height, width) of the camera images.
        episodes: stop after this many env episodes: the robot then holds still and, inside
            ``lerobot-rollout`` (which has no episode count of its own, only ``--duration``), ends the run as
            the operator's Ctrl-C would. None: run on. Ignored by ``lerobot-record`` (``--dataset.num_episodes``).
    """

    env: str = "reach-around"
    scene: str = "0"
    outcomes: str | None = None
    seed: int = 0
    end_episodes: bool = True
    camera_names: list[str] = field(default_factory=list)
    camera_size: tuple[int, int] = (96, 96)
    episodes: int | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.episodes is not None and self.episodes < 1:
            raise config_error(f"pdp_sim: episodes must be >= 1 or None, got {self.episodes}")
