"""The ``pdp_sim`` robot: a suite env behind LeRobot's ``Robot`` interface, so real CLIs run without hardware.

Observations are the env's ``agent_pos`` and ``environment_state`` entries as named float values (the
names ``make-dataset`` writes into its dataset features); actions are the env's action entries by name.
An env episode ends on success, collision or the env's time limit; the robot then resets its own scene
before the next observation, as a person would, and appends the episode's outcome to ``outcomes``.
Inside ``lerobot-rollout`` the names carry ``.pos`` / ``.vel`` suffixes and the robot resets the policy per
episode and ends the run after ``episodes`` (see :mod:`.rollout_hooks`); in LeRobot's async robot client it
drops the last episode's queued actions and ends the run likewise (:mod:`.client_hooks`).
"""

from __future__ import annotations

import json
import logging
import os
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from lerobot.robots import Robot

from . import client_hooks, record_hooks
from .config_pdp_sim import PDPSimConfig
from .live import LIVE

logger = logging.getLogger(__name__)

# Live pdp_sim robots by id (LeRobot's record loop gives a teleoperator no observation: it watches the robot).
_LIVE = LIVE


def find_robot(robot_id: str | None = None) -> PDPSim:
    """The live ``pdp_sim`` robot with ``robot_id`` (None: the only one); a clear error otherwise."""
    live = dict(_LIVE)
    if robot_id is not None:
        if robot_id not in live:
            raise LookupError(f"no pdp_sim robot with id {robot_id!r}; live: {sorted(live)}")
        return live[robot_id]
    if len(live) != 1:
        raise LookupError(
            f"pdp_waypoints drives a pdp_sim robot in the same process; found {len(live)} "
            f"({sorted(live)}). Use --robot.type=pdp_sim, and --teleop.robot_id when there are several"
        )
    return next(iter(live.values()))


class PDPSim(Robot):
    """A simulated robot of config type ``pdp_sim`` (see :class:`PDPSimConfig`)."""

    config_class = PDPSimConfig
    name = "pdp_sim"

    def __init__(self, config: PDPSimConfig):
        import gymnasium as gym

        import lerobot_pdp.envs  # noqa: F401  (registers the suite)
        from lerobot_pdp.envs.recording import _dataset_features
        from lerobot_pdp.envs.scene import load_scene
        from lerobot_pdp.envs.suite import get_suite_env

        if config.id is None:
            config.id = "pdp_sim"
        super().__init__(config)
        self.config = config
        # the env renders the cameras itself; lerobot-record sizes its image writers from len(robot.cameras)
        self.cameras: dict[str, Any] = {name: None for name in config.camera_names}
        self.suite = get_suite_env(config.env)  # KeyError naming the known envs
        self.scene = load_scene(_scene_arg(config.scene), self.suite.scene_key)
        cams = ({"camera": ",".join(config.camera_names), "image_size": tuple(config.camera_size)}
                if config.camera_names else {})
        self.env = gym.make(self.suite.gym_id, scene=self.scene, disable_env_checker=True, **cams)  # bad name: ValueError
        features = _dataset_features(self.env)
        self.state_names: list[str] = list(features["observation.state"]["names"])
        self.env_state_names: list[str] = list(features["observation.environment_state"]["names"])
        self.action_names: list[str] = list(features["action"]["names"])
        clash = set(self.state_names) & set(self.env_state_names)
        if clash:
            raise ValueError(f"pdp_sim: {self.suite.name} has names in both state and environment state: {clash}")
        from . import rollout_hooks

        # lerobot-rollout routes only "*.pos" / "*.vel" scalars to the policy: there the names carry suffixes
        self.in_rollout = rollout_hooks.building_rollout_context()
        obs_sfx, act_sfx = (".pos", ".vel") if self.in_rollout else ("", "")
        self.state_keys = [n + obs_sfx for n in self.state_names]  # the names LeRobot sees
        self.env_state_keys = [n + obs_sfx for n in self.env_state_names]
        self.action_keys = [n + act_sfx for n in self.action_names]
        self._engine: Any = None  # lerobot-rollout's inference engine (reset per episode)
        self._stop_event: Any = None  # lerobot-rollout's shutdown event (set after `episodes`)
        self._rollout_events: dict | None = None  # the episodic strategy's keyboard flags
        self.finished = 0  # env episodes finished (success, collision, time limit or cut)
        self._connected = False
        self.run_id: str | None = None  # set at connect: marks this run's outcome lines
        self.obs: dict[str, np.ndarray] | None = None  # the env's last observation (what the operator sees)
        self.episode = -1  # increases at every scene reset; the teleoperator restarts its route on a change
        self.holding = False  # True during lerobot-record's reset phase: actions are not applied
        self._states: list[np.ndarray] = []
        self._steps = 0
        self._pending_reset = False
        self._events: dict | None = None
        self.recorded_labels: list[int | str] = []  # mode label of each recorded (saved) episode
        self.dataset_root: Path | None = None
        self.first_episode: int | None = None  # dataset index of the first recorded episode (> 0: --resume)
        _LIVE[config.id] = self
        record_hooks.install()  # no-op outside lerobot-record
        client_hooks.install()  # no-op outside LeRobot's async robot client
        if self.in_rollout:
            rollout_hooks.install()

    # ---- LeRobot Robot interface ----
    @property
    def observation_features(self) -> dict[str, type | tuple[int, int, int]]:
        h, w = self.config.camera_size
        return {**{n: float for n in self.state_keys + self.env_state_keys},
                **{name: (h, w, 3) for name in self.config.camera_names}}

    @property
    def action_features(self) -> dict[str, type]:
        return {n: float for n in self.action_keys}

    @property
    def is_connected(self) -> bool:
        return self._connected

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        """Nothing to calibrate in simulation."""

    def configure(self) -> None:
        """Nothing to configure in simulation."""

    def connect(self, calibrate: bool = True) -> None:
        self._connected = True
        # each run's lines are told apart by their `run` (a rerun, or two runs given one file, append to it)
        self.run_id = f"{datetime.now(UTC):%Y%m%dT%H%M%S.%fZ}-{os.getpid()}"
        earlier = Path(self.config.outcomes) if self.config.outcomes else None
        if earlier is not None and earlier.is_file() and earlier.stat().st_size > 0:
            logger.warning("pdp_sim: %s already holds %d outcome line(s) of earlier runs; this run appends its own, "
                           "marked run=%s", earlier, len(earlier.read_text().splitlines()), self.run_id)
        self.reset_scene()

    def disconnect(self) -> None:
        if self._connected and self._steps > 0 and not self._pending_reset:
            self._finish_episode({}, cut=True)
        self._connected = False
        self._write_mode_labels()
        self.env.close()

    def get_observation(self) -> dict[str, float | np.ndarray]:
        self._require_connected()
        if self._pending_reset and self._events is None and not self.done:  # in lerobot-record the next phase resets
            self.reset_scene()
            if self._engine is not None:
                self._engine.reset()  # a new episode: a fresh observation history and action queue
        assert self.obs is not None
        values = np.concatenate([self.obs["agent_pos"], self.obs["environment_state"]]).astype(float)
        out: dict[str, float | np.ndarray] = dict(zip(self.state_keys + self.env_state_keys, values.tolist(),
                                                      strict=True))
        out.update({name: self.obs["pixels"][name] for name in self.config.camera_names})  # uint8 (H, W, 3)
        mark = getattr(self._engine, "episode_mark", None)  # LeRobot's async client: the served policy resets on it
        if mark is not None:
            out[mark] = float(self.episode)
        return out

    def send_action(self, action: dict[str, Any]) -> dict[str, Any]:
        self._require_connected()
        missing = [n for n in self.action_keys if n not in action]
        if missing and action and set(action) <= set(self.state_keys + self.env_state_keys):
            # lerobot-rollout's "return to the initial position" (between episodic episodes, at teardown) sends
            # observed values as targets: a simulated robot resets its scene instead, as the operator would
            if self._steps > 0 and not self._pending_reset:
                self._finish_episode({}, cut=True)
            return action
        if missing:
            raise KeyError(f"pdp_sim: action lacks {missing}; expected {self.action_keys}")
        if self.holding or self._pending_reset:
            return action  # reset phase / episode over: the scene stays as it is
        vec = np.asarray([float(action[n]) for n in self.action_keys], dtype=np.float32)
        self.obs, _, terminated, truncated, info = self.env.step(vec)
        self._steps += 1
        self._action_times.append(time.perf_counter())
        self._actions.append(vec)
        self._states.append(np.asarray(self.obs["agent_pos"], dtype=float))
        if terminated or truncated:
            self._finish_episode(info, cut=False)
            if self._events is not None and self.config.end_episodes:
                self._events["exit_early"] = True  # the operator's "next episode" key
        return action

    # ---- episodes ----
    @property
    def done(self) -> bool:
        """All ``config.episodes`` env episodes are finished: the robot holds still."""
        return self.config.episodes is not None and self.finished >= self.config.episodes

    def attach_rollout(self, engine: Any, stop_event: Any) -> None:
        """lerobot-rollout's inference engine (reset on every scene reset) and shutdown event (set when done)."""
        self._engine, self._stop_event = engine, stop_event

    def attach_events(self, events: dict) -> None:
        """The episodic strategy's keyboard flags: an env episode's end ends the recorded episode."""
        self._rollout_events = events

    def reset_scene(self) -> None:
        """Start a new env episode in the configured scene (reset noise from ``(seed, episode)``)."""
        self.episode += 1
        seed = int(np.random.default_rng([self.config.seed, self.episode]).integers(2**31 - 1))
        self.obs, _ = self.env.reset(seed=seed)
        self._states = [np.asarray(self.obs["agent_pos"], dtype=float)]
        self._steps = 0
        self._action_times: list[float] = []  # when each action of this episode was applied (loop timing)
        self._actions: list[np.ndarray] = []  # the actions applied (how smoothly one chunk hands over to the next)
        self._pending_reset = False
        self.last_label: int | str | None = None

    def _finish_episode(self, info: dict, cut: bool) -> None:
        """Classify the episode, append its outcome line and schedule a scene reset."""
        label = self.suite.classify_mode(np.stack(self._states), scene=self.scene)
        self.last_label = label
        outcome = {
            "episode": self.episode,
            "env": self.suite.name,
            "scene": self.config.scene,
            "run": self.run_id,
            "success": bool(info.get("is_success", False)) and not cut,
            "collided": bool(info.get("collided", False)),
            "mode": label if isinstance(label, str) else int(label),
            "steps": self._steps,
            "ended_by": "stopped" if cut else ("success" if info.get("is_success") else
                                               "collision" if info.get("collided") else "time_limit"),
            **self._loop_timing(),
            **self._action_steps(),
        }
        if self.config.outcomes:
            path = Path(self.config.outcomes)
            path.parent.mkdir(parents=True, exist_ok=True)
            with path.open("a") as f:
                f.write(json.dumps(outcome) + "\n")
        logger.info("pdp_sim episode %d: %s", self.episode, outcome)
        self._pending_reset = True
        self.finished += 1
        if self._rollout_events is not None and self.config.end_episodes:
            self._rollout_events["exit_early"] = True  # the operator's "next episode" key
        if self.done and self._stop_event is not None:
            logger.info("pdp_sim: %d episodes done, ending the rollout", self.finished)
            self._stop_event.set()  # as the operator's Ctrl-C would

    def _loop_timing(self) -> dict[str, float]:
        """How the control loop kept its pace in this episode: actions per second between the first and the
        last action, the median pause between two actions and the longest one (a stalled loop shows there)."""
        t = self._action_times
        if len(t) < 2:
            return {}
        gaps = np.diff(t)
        return {"actions_per_s": round((len(t) - 1) / (t[-1] - t[0]), 2),
                "median_gap_s": round(float(np.median(gaps)), 4), "max_gap_s": round(float(gaps.max()), 4)}

    def _action_steps(self) -> dict[str, float]:
        """How far the commanded action moved between two steps (Euclidean, the gripper command left out: it
        switches by design): the median step, the 90th percentile and the largest; how smoothly one chunk hands
        over to the next shows in the upper ones."""
        if len(self._actions) < 2:
            return {}
        a = np.stack(self._actions)
        if self.suite.segment_on_gripper is not None:
            a = np.delete(a, self.suite.segment_on_gripper, axis=1)
        steps = np.linalg.norm(np.diff(a, axis=0), axis=1)
        median, p90 = np.percentile(steps, [50, 90])
        return {"action_step_median": round(float(median), 5), "action_step_p90": round(float(p90), 5),
                "action_step_max": round(float(steps.max()), 5)}

    # ---- lerobot-record phases (called by record_hooks) ----
    def begin_phase(self, events: dict, recording: bool, dataset: Any = None) -> None:
        """A record or reset phase starts: from a fresh scene either way; hold still while resetting."""
        self._events = events
        if dataset is not None and getattr(dataset, "root", None) is not None:
            self.dataset_root = Path(dataset.root)
        if recording and self.first_episode is None:
            # lerobot-record --resume=true: this session's episodes follow the dataset's. Their env episodes are
            # numbered alike, so the logs match LeRobot's and the reset noise does not repeat the first session's
            self.first_episode = int(getattr(dataset, "num_episodes", 0) or 0)
            if self.first_episode and self._connected and self.finished == 0 and self._steps == 0:
                self.episode = self.first_episode - 1
                self.reset_scene()
        if self._connected and (self._steps > 0 or self._pending_reset):
            if not self._pending_reset:
                self._finish_episode({}, cut=True)
            self.reset_scene()
        self.holding = not recording
        if not recording and self.config.end_episodes:
            events["exit_early"] = True  # the scene is reset already: no need to wait out reset_time_s

    def end_phase(self, events: dict, recording: bool, dataset: Any = None, single_task: str | None = None) -> None:
        """A phase ended: label the recorded episode (and its task string when none was given)."""
        if recording:
            if self._steps > 0 and not self._pending_reset:
                self._finish_episode({}, cut=True)  # the record timer ran out first
            label = self.last_label if self.last_label is not None else "novel"
            self.recorded_labels.append(label)
            if not single_task and dataset is not None:
                _set_episode_task(dataset, self.suite.task_string(label))
        elif events.get("rerecord_episode") and self.recorded_labels:
            self.recorded_labels.pop()  # lerobot-record drops that episode
        self.holding = False

    def abort_phase(self) -> None:
        """The record loop was interrupted: the env episode is logged as cut; the episode being recorded is
        never saved (``lerobot-record`` finalizes only the saved ones), so it gets no mode label and
        ``meta/mode_labels.json`` still matches the saved episodes."""
        if self._steps > 0 and not self._pending_reset:
            self._finish_episode({}, cut=True)
        self.holding = False

    def _write_mode_labels(self) -> None:
        """``meta/mode_labels.json`` for the recorded dataset, when every episode has a training mode.

        After ``--resume=true`` the file covers the dataset's earlier episodes too: their labels come from the
        file they had (kept as they are), else from their task strings. When some episode has no training
        mode the file cannot be written, and an old one is removed: it would label only some episodes, which
        training and ``label-modes`` refuse.
        """
        if self.dataset_root is None or not self.recorded_labels:
            return
        from lerobot_pdp.episodes import MODE_LABELS_FILE, write_mode_labels

        info = self.dataset_root / "meta" / "info.json"
        if not info.is_file():
            return
        total = json.loads(info.read_text()).get("total_episodes")
        if not isinstance(total, int):
            logger.warning("pdp_sim: %s has no total_episodes; no %s written", info, MODE_LABELS_FILE)
            return
        first = self.first_episode or 0
        # saved episodes are a prefix of the recorded ones: only the last can be unsaved (interrupted before
        # lerobot-record's save_episode)
        labels: dict[int, int | str | None] = dict(enumerate(self.recorded_labels[:max(total - first, 0)], first))
        if not labels:
            return  # nothing saved (an empty recording)
        names = {int(m): self.suite.mode_names[int(m)] for m in labels.values() if isinstance(m, (int, np.integer))}
        if first:
            earlier, earlier_names = self._earlier_labels(first)
            labels, names = {**earlier, **labels}, {**names, **earlier_names}  # the dataset's names kept
        modes = {e: int(m) for e, m in labels.items() if isinstance(m, (int, np.integer))}
        path = self.dataset_root / "meta" / MODE_LABELS_FILE
        if sorted(modes) == list(range(total)):
            write_mode_labels(self.dataset_root, modes, names)
            return
        missing = {e: labels.get(e) for e in range(total) if e not in modes}
        removed = path.is_file()
        if removed:
            path.unlink()
        if not modes and not removed:  # e.g. one demonstration of a new route: nothing to label, nothing wrong
            logger.info("pdp_sim: no meta/%s: no episode has a training mode (%d episodes, labels %s)",
                        MODE_LABELS_FILE, total, list(missing.values()))
            return
        logger.warning("pdp_sim: no meta/%s: episodes %s have no training mode (labels %s), episodes %s have one; "
                       "PDP reads the modes from the task strings%s", MODE_LABELS_FILE, sorted(missing),
                       list(missing.values()), sorted(modes),
                       f" (removed {path}, which labelled only some episodes)" if removed else "")

    def _earlier_labels(self, first: int) -> tuple[dict[int, int | str | None], dict[int, str]]:
        """Mode labels and names of the episodes a resumed dataset had before this session (``0..first-1``): from
        its ``meta/mode_labels.json``, else (an episode the file lacks, or no file) from its task string."""
        from lerobot_pdp.episodes import parse_task_mode, parse_task_name, read_episodes, read_mode_labels

        labels: dict[int, int | str | None] = {}
        names: dict[int, str] = {}
        try:
            found = read_mode_labels(self.dataset_root)
        except ValueError as e:  # a damaged file: the task strings still carry the labels
            logger.warning("pdp_sim: ignoring the dataset's mode labels: %s", e)
            found = None
        if found is not None:
            labels = {e: m for e, m in found[0].items() if e < first}
            names = dict(found[1])
        rest = [e for e in range(first) if e not in labels]
        if rest:
            for e, item in read_episodes(self.dataset_root, [], rest, mode_labels=False).items():
                labels[e] = parse_task_mode(item["task"])
                if isinstance(labels[e], int) and parse_task_name(item["task"]):
                    names.setdefault(labels[e], parse_task_name(item["task"]))
        return labels, names

    def _require_connected(self) -> None:
        if not self._connected:
            raise ConnectionError(f"{self} is not connected; call connect() first")


def _scene_arg(scene: str) -> int | str:
    return int(scene) if str(scene).strip().isdigit() else scene


def _set_episode_task(dataset: Any, task: str) -> None:
    """Give every buffered frame of the current episode ``task`` (the mode label, as make-dataset writes it)."""
    buf = getattr(getattr(dataset, "writer", None), "episode_buffer", None)
    if isinstance(buf, dict) and isinstance(buf.get("task"), list):
        buf["task"] = [task] * len(buf["task"])
    else:  # pragma: no cover - another LeRobot layout
        logger.warning("pdp_sim: cannot set the episode task string on this LeRobot version")
