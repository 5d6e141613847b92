"""What LeRobot's async robot client lacks for a simulated robot, added around two of its module globals.

``python -m lerobot.async_inference.robot_client`` (LeRobot 0.6.x) tells the policy server its features with
``map_robot_keys_to_lerobot_features``, which merges every float observation into one ``observation.state``,
and has no notion of an episode. For a ``pdp_sim`` robot it drives, and only then:

* ``map_robot_keys_to_lerobot_features`` is wrapped to split ``observation.state`` into ``observation.state``
  and ``observation.environment_state`` by name, the layout ``make-dataset`` writes and PDP was trained on
  (``python -m lerobot_pdp.policy_server`` passes the second on to the policy);
* ``RobotClient`` is wrapped so that the robot, when it resets its scene (a new episode), drops the actions
  still queued from the episode that ended, and a chunk planned from that episode's observations that arrives
  after the reset (it was in flight); the run ends after ``--robot.episodes`` (the client's shutdown
  event, as Ctrl-C would, set in place of the next observation) and ends cleanly (the receiving thread leaves
  its request before the channel closes); a failed start (no server listening, the policy refused) ends the
  process, and so does a server lost mid-run (observations undeliverable for :data:`SERVER_LOST_S`);
* a client serving PDP (any robot) whose server could not plan a chunk (``python -m lerobot_pdp.policy_server``
  fails that action request with the error and serves nothing more) ends its run, where LeRobot's logs the
  failed request and asks again, for good;
* ``async_client`` (the command's entry point) is wrapped so that a run that could not start, lost its server
  or was stopped by it exits with status 1 and says why (LeRobot's exits 0 and only logs it);
* LeRobot's control loop clears its "must go" flag after sending a must-go observation; when the chunk answering
  it arrives before that clear (a fast server), the receiver's set is undone and the next observations, sent
  without it, can all be filtered by the server as too similar (a robot standing still: a stalled run). For
  ``pdp_sim`` the flag is set again when a chunk arrived while the observation was in flight;
* a client serving PDP (any robot but ``pdp_sim``) at another ``--fps`` than the policy's training data was recorded
  at is warned (when the checkpoint's config.json is readable on the client's machine);
* a client serving PDP (any robot) that blends overlapping chunks (LeRobot's default ``weighted_average``) is
  warned, with the flag that executes each action from one chunk (``--aggregate_fn_name=latest_only``), and so is
  one that sends observations only from an empty queue (``--chunk_size_threshold=0``: frames a chunk apart);
* the robot marks each observation with its env episode (``paced_chunks.EPISODE_MARK``, not one of its features):
  ``python -m lerobot_pdp.policy_server`` passes it on, and PDP starts a new episode (a fresh observation history)
  when it changes.

Nothing of LeRobot is changed on disk; other robots are untouched but for those warnings.
"""

from __future__ import annotations

import functools
import logging
import sys
import threading
import time
from typing import Any

from .hooks import split_environment_state, wrap_all
from .live import LIVE

logger = logging.getLogger(__name__)

CLIENT_MODULE = "lerobot.async_inference.robot_client"
# longest wait for the receiving thread at the end of a run: LeRobot's server answers a request within its
# --obs_queue_timeout (2 s by default)
RECEIVER_WAIT_S = 5.0
# how long observations may fail to reach the server before a pdp_sim run counts it as lost and ends
SERVER_LOST_S = 5.0

# why a pdp_sim run ended in failure, for ``async_client``'s exit status (one run per process)
FAILURES: list[str] = []

# the client's aggregation that executes each action from one PDP chunk; LeRobot's default blends two (0.3 old +
# 0.7 new): two samples of a multimodal policy averaged (docs/deploy.md, "Asynchronous inference")
PDP_AGGREGATION = "latest_only"
BLENDED = ("this client blends the overlapping actions of two chunks (--aggregate_fn_name=%s); PDP's chunks are "
           "samples of a multimodal policy, and an average of two can fall between their routes (measured: "
           "lerobot_pdp's docs/deploy.md, Asynchronous inference): pass --aggregate_fn_name=latest_only")
# a client that sends an observation only when its queue is empty sends none of the frames before it: PDP's
# history, which is consecutive frames, would hold frames a chunk apart
EMPTY_ONLY = ("--chunk_size_threshold=%s: this client sends an observation only when its queue is empty, so the "
              "served PDP sees none of the frames before it and conditions on frames a chunk apart (measured: "
              "lerobot_pdp's docs/deploy.md, Asynchronous inference): keep LeRobot's default 0.5")


def client_module() -> Any:
    """LeRobot's robot-client module when this process loaded it: imported, or run as ``python -m`` (then it is
    ``__main__``, where the client looks its globals up); None otherwise."""
    main = sys.modules.get("__main__")
    if getattr(getattr(main, "__spec__", None), "name", None) == CLIENT_MODULE:
        return main
    return sys.modules.get(CLIENT_MODULE)


def install() -> bool:
    """Wrap the client's functions once; False when LeRobot's robot client is not loaded."""
    return wrap_all(client_module(), {"map_robot_keys_to_lerobot_features": _wrap_features, "RobotClient": _wrap_client,
                                      "async_client": _wrap_main},
                    "LeRobot robot client", "environment_state stays in the state and episodes do not end the run")


def _ours(robot: Any) -> bool:
    return any(r is robot for r in list(LIVE.values()))


def _wrap_main(original):
    @functools.wraps(original)
    def async_client(*args: Any, **kwargs: Any):
        from ..cli_errors import ending_on_signals

        FAILURES.clear()
        with ending_on_signals("robot client"):  # Ctrl-C / SIGTERM: LeRobot's finally stops it, the robot disconnected
            result = original(*args, **kwargs)
        if FAILURES:
            raise SystemExit(f"robot client: {FAILURES[0]}")  # exit status 1, the reason on stderr
        return result

    return async_client


def _wrap_features(original):
    @functools.wraps(original)
    def map_robot_keys_to_lerobot_features(robot: Any) -> dict[str, dict]:
        features = original(robot)
        if _ours(robot):
            features = split_environment_state(features, robot.state_keys, robot.env_state_keys)
        return features

    return map_robot_keys_to_lerobot_features


class QueuedActions:
    """What the robot resets at a scene reset, in place of lerobot-rollout's inference engine: the client's
    queued actions, which belong to the episode that ended."""

    def __init__(self, client: Any):
        # torch: imported when a client drives the robot, not with the plugin
        from ..paced_chunks import EPISODE_MARK

        self.client = client
        self.episode_mark = EPISODE_MARK  # the key under which the robot's observations carry their env episode

    def reset(self) -> None:
        # after a chunk being checked and queued (_aggregate_action_queues), never between the two
        with self.client._pdp_reset_lock, self.client.action_queue_lock:
            self.client._pdp_reset_at = time.time()  # the clock of the observations' timestamps
            dropped = self.client.action_queue.qsize()
            self.client.action_queue.queue.clear()
        self.client.must_go.set()  # the next observation is answered whatever it looks like
        logger.info("pdp_sim: new episode, %d queued action(s) of the last one dropped", dropped)


def _check_fps(config: Any) -> None:
    """The client's ``--fps`` against the rate the policy's training data was recorded at (a warning naming both),
    when the checkpoint's config.json can be read on this machine; the server may load a path or repo this machine
    lacks, and then there is nothing to compare with here."""
    from lerobot.configs.policies import PreTrainedConfig

    from ..episodes import simulated_robot
    from ..rollout_checks import warn_other_fps

    robot = str(getattr(config.robot, "type", ""))
    if simulated_robot(robot):  # one env step per action whatever the pace: nothing to compare, nothing to read
        return
    try:
        policy_config = PreTrainedConfig.from_pretrained(config.pretrained_name_or_path)
    except (OSError, ValueError) as e:
        logger.debug("frame rate not checked: %s not readable here (%s)", config.pretrained_name_or_path, e)
        return
    warn_other_fps(policy_config, config.fps, robot, "the robot client")


def _wrap_client(original):
    class RobotClient(original):  # noqa: D101 - LeRobot's, with the robot told its client
        def __init__(self, *args: Any, **kwargs: Any):
            super().__init__(*args, **kwargs)
            self._pdp_sim = _ours(self.robot)
            self._pdp_chunks = 0  # chunks received, counted before LeRobot's receiver sets must_go
            self._pdp_reset_at: float | None = None  # when the robot last reset its scene (QueuedActions)
            self._pdp_reset_lock = threading.Lock()  # a scene reset and a chunk's check-and-queue exclude each other
            self._pdp_unsent_since: float | None = None
            if self.config.policy_type == "pdp":  # any robot serving PDP
                aggregation = getattr(self.config, "aggregate_fn_name", PDP_AGGREGATION)
                if aggregation != PDP_AGGREGATION:
                    logger.warning(BLENDED, aggregation)
                if self.config.chunk_size_threshold <= 0:
                    logger.warning(EMPTY_ONLY, self.config.chunk_size_threshold)
                _check_fps(self.config)
                from ..policy_server import CLIENT_REFUSED, PLANNING_FAILED

                # a chunk PDP could not plan ends the run; a refusal at connect (another robot) names its reason
                self.stub.GetActions = _failing_on(self.stub.GetActions, "ABORTED", PLANNING_FAILED, self)
                self.stub.SendPolicyInstructions = _failing_on(self.stub.SendPolicyInstructions, "FAILED_PRECONDITION",
                                                               CLIENT_REFUSED)
            if self._pdp_sim:  # the run ends below, before an observation would be sent to a stopped client
                self.robot.attach_rollout(QueuedActions(self), None)

        def start(self) -> bool:
            """LeRobot's; when it fails (no server listening, the policy refused) the robot is disconnected and
            the channel closed, so that the process ends instead of waiting on them."""
            started = super().start()
            if not started and self._pdp_sim:
                FAILURES.append(f"could not start with the policy server at {self.config.server_address} (no server "
                                "listening, or it refused the policy: see the log above)")
                super().stop()
            return started

        def send_observation(self, obs: Any) -> bool:
            sent = super().send_observation(obs)
            if self._pdp_sim:
                now = time.monotonic()
                if sent:
                    self._pdp_unsent_since = None
                elif self._pdp_unsent_since is None:
                    self._pdp_unsent_since = now
                elif now - self._pdp_unsent_since > SERVER_LOST_S and self.running:
                    FAILURES.append(f"lost the policy server at {self.config.server_address}: no observation "
                                    f"reached it for {SERVER_LOST_S:.0f} s")
                    logger.error("pdp_sim: %s; ending the run", FAILURES[-1])
                    self.shutdown_event.set()
            return sent

        def _aggregate_action_queues(self, incoming_actions: list, *args: Any, **kwargs: Any):
            with self._pdp_reset_lock:  # a scene reset between the check and LeRobot's queueing would get the chunk
                if self._pdp_sim and incoming_actions and self._planned_before_reset(incoming_actions[0]):
                    logger.info("pdp_sim: a chunk planned in the episode that ended arrived after it: dropped")
                else:
                    super()._aggregate_action_queues(incoming_actions, *args, **kwargs)
            self._pdp_chunks += 1  # LeRobot's receiver sets must_go right after this

        def _planned_before_reset(self, first: Any) -> bool:
            """Whether the chunk starting with ``first`` answers an observation taken before the last scene reset
            (in flight when the episode ended, it would run at the next one's start). Its observation's time:
            the first action's, one control step earlier for PDP's server (it times that action at the next step)."""
            step = self.config.environment_dt if self.config.policy_type == "pdp" else 0.0
            return self._pdp_reset_at is not None and first.get_timestamp() - step < self._pdp_reset_at

        def receive_actions(self, verbose: bool = False):
            self._pdp_receiver = threading.current_thread()
            return super().receive_actions(verbose)

        def stop(self):
            """The receiving thread leaves its pending request (the server answers within its observation timeout)
            before the channel closes: LeRobot's stop closes it under the request, which logs an error at every
            end of a run."""
            receiver = getattr(self, "_pdp_receiver", None)
            if self._pdp_sim and receiver is not None and receiver is not threading.current_thread():
                self.shutdown_event.set()
                receiver.join(timeout=RECEIVER_WAIT_S)
            super().stop()

        def control_loop_observation(self, task: str, verbose: bool = False):
            if self._pdp_sim and self.robot.done:
                if self.running:
                    logger.info("pdp_sim: %d episodes done, ending the run", self.robot.finished)
                    self.shutdown_event.set()  # as the operator's Ctrl-C would
                return None
            if not self._pdp_sim:
                return super().control_loop_observation(task, verbose)
            chunks = self._pdp_chunks
            observation = super().control_loop_observation(task, verbose)
            if self._pdp_chunks != chunks:  # a chunk arrived in flight: its must_go.set() may have been cleared since
                self.must_go.set()
            return observation

    RobotClient.__doc__ = original.__doc__
    return RobotClient


def _failing_on(call: Any, code: str, prefix: str, client: Any = None) -> Any:
    """The client stub's method ``call``: an error the PDP server sent on purpose (gRPC status ``code``, details
    beginning with ``prefix``) becomes the run's failure, its message whole; with ``client``, the run also ends, as
    Ctrl-C would. LeRobot's client only logs the gRPC error object: at connect (``start`` returns False) or per
    action request (its receiver asks again, for good)."""
    import grpc

    @functools.wraps(call)
    def failing_on(*args: Any, **kwargs: Any):
        try:
            return call(*args, **kwargs)
        except grpc.RpcError as e:
            details = e.details() if callable(getattr(e, "details", None)) else ""
            if e.code() == getattr(grpc.StatusCode, code) and (details or "").startswith(prefix):
                FAILURES.append(details)
                if client is not None:
                    logger.error("%s; ending the run", details)
                    client.shutdown_event.set()
            raise

    return failing_on
