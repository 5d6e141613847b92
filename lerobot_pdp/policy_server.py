"""LeRobot's asynchronous-inference policy server, serving PDP: ``python -m lerobot_pdp.policy_server``.

LeRobot 0.6.1's ``python -m lerobot.async_inference.policy_server`` serves only the policy types of its
hard-coded ``SUPPORTED_POLICIES`` and loads no plugins, so it refuses ``pdp``. This command is that server,
with its options (``--host --port --fps --inference_latency --obs_queue_timeout``), changed in this process
only (nothing of LeRobot is changed on disk):

* plugins are loaded and ``pdp`` is admitted;
* the observation vectors the robot client sends besides ``observation.state`` (``observation.environment_state``)
  reach the policy: LeRobot's server passes on the state and the cameras only; so does ``pdp_sim``'s episode mark,
  on which PDP starts a new episode (:mod:`lerobot_pdp.paced_chunks`);
* a chunk is planned once per chunk, just in time: from the observation sent when the client holds no more
  actions than a chunk takes to plan, whatever LeRobot's similarity filter says (it planned back to back on
  states that pass it, and only from an empty queue on states in metres: :class:`lerobot_pdp.paced_chunks.JustInTime`;
  ``--policy.async_just_in_time=false``: only from an empty queue, whole chunks);
* each chunk continues the last one: it is held to the actions of the last chunk the client runs while it is
  planned, fading to free at ``--policy.async_execution_horizon`` (5; 0: a fresh sample each chunk), so the route
  is kept where chunks are spliced (:class:`lerobot_pdp.paced_chunks.LastChunk`; ``--policy.async_carry_noise=true``
  carries the last chunk's sampler noise, shifted, too);
* every observation the client sends is kept, and each chunk is planned on consecutive frames: the ones
  received just before the planned one join PDP's history first; one whose predecessor was not sent waits for
  the next, a control step later (:class:`lerobot_pdp.paced_chunks.ReceivedFrames`);
* a PDP chunk's first action is timed at the step after the observation's (LeRobot's times it at the
  observation's, the last action the client executed, so its client skips it and runs each action a step early);
* the actions the client executed (the timestep of its last action comes with each observation) reach the
  policy, so a latent per gripper phase follows the robot (:class:`lerobot_pdp.paced_chunks.ExecutedActions`),
  and so does each chunk's step in the episode, so fitted chunk noises are replayed aligned to the frames they
  were fitted to (:meth:`lerobot_pdp.paced_chunks.LastChunk.fitted_noise`);
* a robot client whose features are not the checkpoint's (another env, a missing camera) is refused as it connects
  (gRPC ``FAILED_PRECONDITION``, :data:`CLIENT_REFUSED`, each difference named), before LeRobot loads anything, so
  a client already being served keeps its policy;
* a chunk the served PDP cannot plan (an error: a non-finite action, an observation it cannot read) ends the
  client's run: its action request fails with the error (gRPC ``ABORTED``, :data:`PLANNING_FAILED`) and the
  server serves nothing more until a client connects again; LeRobot's logs the error and answers nothing, for
  good, so the robot would wait for actions that never come (``pdp_sim``'s hooks end the client with status 1);
* ``--policy.<field>=<value>`` sets a field of the PDP checkpoint's config when the server loads it, as on
  ``lerobot-eval`` / ``lerobot-rollout``'s command lines: steering (``--policy.steer_file``,
  ``--policy.steer_mode``, ``--policy.steer_latent``, ``--policy.steer_dataset_root`` ...) and sampling fields.

The robot side is LeRobot's own client (``python -m lerobot.async_inference.robot_client --policy_type=pdp
--pretrained_name_or_path=CKPT ...``); the checkpoint is loaded by the server, from its file system. How PDP
acts on one observation at a time: :mod:`lerobot_pdp.paced_chunks`.
"""

from __future__ import annotations

import contextlib
import functools
import io
import logging
import sys
import time
from collections.abc import Callable, Sequence
from types import SimpleNamespace
from typing import Any

logger = logging.getLogger(__name__)

SERVED = "pdp"
STATE = "observation.state"
_ORIGINAL = "_lerobot_original"
# how the failed action request of a client whose chunk PDP could not plan begins (its gRPC details)
PLANNING_FAILED = "the PDP policy server could not plan a chunk"
CLIENT_REFUSED = "the PDP policy server refused this robot client"


def split_policy_options(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """(the server's own options, the ``--policy.<field>=<value>`` options as config overrides ``--<field>=<value>``)."""
    server, policy = [], []
    for arg in argv:
        if arg.startswith("--policy."):
            policy.append("--" + arg.removeprefix("--policy."))
        else:
            server.append(arg)
    return server, policy


def check_policy_options(overrides: list[str]) -> None:
    """Refuse an unknown PDP field or a bad value now, not when the first robot client connects."""
    if not overrides:
        return
    import draccus

    from .configuration_pdp import PDPConfig

    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            draccus.parse(PDPConfig, args=["--device=cpu", *overrides])  # no device probe
    except (SystemExit, Exception) as e:  # draccus exits after printing its usage (unknown option) or raises
        said = (err.getvalue().strip().splitlines() or [""])[-1].split("error: ", 1)[-1] \
            if isinstance(e, SystemExit) else " ".join(str(e).split())
        raise SystemExit(f"lerobot_pdp.policy_server: bad --policy.* option ({said}) in "
                         f"{' '.join('--policy.' + o[2:] for o in overrides)}") from e


def with_vector_features(original: Callable) -> Callable:
    """Wrap LeRobot's ``raw_observation_to_observation``: it keeps ``observation.state`` and the cameras; float
    vectors of other names (``observation.environment_state``) are added as [1, D] tensors, read by name. A
    value the client's features name but its observation lacks is named (LeRobot's says only the name)."""

    def vectors(lerobot_features: dict[str, dict]) -> dict[str, list[str]]:
        return {k: list(ft["names"]) for k, ft in lerobot_features.items() if k.startswith("observation.")
                and ft.get("dtype") not in ("image", "video") and len(ft.get("shape", ())) == 1 and ft.get("names")}

    @functools.wraps(original)
    def raw_observation_to_observation(raw: dict[str, Any], lerobot_features: dict[str, dict], *args: Any, **kw: Any):
        import torch

        from .paced_chunks import EPISODE_KEY, EPISODE_MARK

        named = vectors(lerobot_features)
        for key, names in named.items():
            missing = [n for n in names if n not in raw]
            if missing:
                raise KeyError(f"the robot client's observation lacks {missing} of {key!r} (it has {sorted(raw)})")
        out = original(raw, lerobot_features, *args, **kw)
        for key, names in named.items():
            if key != STATE:
                out[key] = torch.tensor([float(raw[n]) for n in names], dtype=torch.float32).unsqueeze(0)
        if EPISODE_MARK in raw:  # pdp_sim's env episode (client_hooks.py): PDP starts a new one when it changes
            out[EPISODE_KEY] = torch.tensor([float(raw[EPISODE_MARK])])
        return out

    return raw_observation_to_observation


def with_input_check(original: Callable) -> Callable:
    """Wrap LeRobot's ``PolicyServer.SendPolicyInstructions``: the features a robot client of PDP sends must be the
    ones the checkpoint was trained on (its config.json, read first), else the request fails (gRPC
    ``FAILED_PRECONDITION``, details beginning with :data:`CLIENT_REFUSED`, naming each difference) and the client
    ends at connect (so it does, naming the error, when loading the policy fails). Checked before LeRobot loads
    anything: the policy, its start-up fit and the features a client already running is served with stay as they
    were (a robot of another env would otherwise get no action, the server failing at every chunk, and wait for
    good)."""

    @functools.wraps(original)
    def SendPolicyInstructions(self: Any, request: Any, context: Any):  # noqa: N802 - LeRobot's gRPC method
        import pickle

        import grpc

        specs = pickle.loads(request.data)  # nosec - LeRobot's own message, which its server unpickles too
        if getattr(specs, "policy_type", None) == SERVED:
            from lerobot.configs.policies import PreTrainedConfig

            rename = getattr(specs, "rename_map", None) or {}
            features = getattr(specs, "lerobot_features", None) or {}
            try:
                config = PreTrainedConfig.from_pretrained(specs.pretrained_name_or_path)
                check_client_features(config, {rename.get(k, k): v for k, v in features.items()})
            except ValueError as e:
                logger.error("refused the robot client %s: %s", context.peer(), e)
                context.abort(grpc.StatusCode.FAILED_PRECONDITION, f"{CLIENT_REFUSED}: {e}")
            try:
                return original(self, request, context)
            except Exception as e:  # noqa: BLE001 - a failed load (bad --policy.* option, no recording): named
                said = e.args[0] if isinstance(e, KeyError) and e.args else e
                logger.exception("could not load %s for the robot client %s", specs.pretrained_name_or_path,
                                 context.peer())
                context.abort(grpc.StatusCode.FAILED_PRECONDITION, f"{CLIENT_REFUSED}: loading "
                              f"{specs.pretrained_name_or_path} failed ({type(e).__name__}: {said})")
        return original(self, request, context)

    return SendPolicyInstructions


def check_client_features(config: Any, features: dict[str, dict]) -> None:
    """Every input the policy was trained on, with its shape, among the robot client's features (dataset format:
    cameras (H, W, C)); else a ValueError naming each difference."""
    from .episodes import feature_problems

    problems = feature_problems({k: tuple(ft.shape) for k, ft in config.input_features.items()}, features,
                                getattr(config, "dataset_feature_names", None))
    if problems:
        raise ValueError("the robot client does not give what the PDP policy needs: " + "; ".join(problems)
                         + f". The client gives {sorted(k for k in features if k.startswith('observation.'))}: is "
                         "its robot (--robot.type, --robot.env, its cameras) the one the policy was trained on?")


def with_policy_options(original: Callable, overrides: list[str]) -> Callable:
    """Wrap LeRobot's ``get_policy_class``: PDP is loaded with ``overrides`` applied to its saved config, told
    what the server will tell it (the executed actions, each chunk's step: per-phase latents and fitted chunk
    noises follow), and its steering checked as the client connects, not at its first chunk."""

    @functools.wraps(original)
    def get_policy_class(name: str):
        cls = original(name)
        if name != SERVED:
            if overrides:
                logger.warning("--policy.* options are PDP's; the client asks for %r: ignored", name)
            return cls

        def from_pretrained(path: str, **kwargs: Any):
            from lerobot.configs.policies import PreTrainedConfig

            from .paced_chunks import (
                PACED_ENGINE,
                PACED_WAY_OUT,
                ExecutedActions,
                LastChunk,
                ReceivedFrames,
                check_paced_steering,
            )
            from .steering import paced_caller

            if overrides:
                kwargs["config"] = PreTrainedConfig.from_pretrained(path, cli_overrides=list(overrides))
                logger.info("PDP config of %s with %s", path,  # as the user typed them
                            " ".join("--policy." + o[2:] for o in overrides))
            with paced_caller(PACED_ENGINE, PACED_WAY_OUT, reports_executed=True):  # phases follow; noises by step
                policy = cls.from_pretrained(path, **kwargs)
            if policy.config.segment_gripper_dim is not None:
                policy._paced_executed = ExecutedActions(policy)
            if policy.config.n_obs_steps > 1:
                policy._paced_frames = ReceivedFrames(policy.config.n_obs_steps)
            policy._paced_last = LastChunk(policy.config.async_carry_noise, policy.config.async_execution_horizon)
            check_paced_steering(policy)
            return policy

        return SimpleNamespace(from_pretrained=from_pretrained)

    return get_policy_class


def paced_timing(server: Any) -> Any:
    """The served PDP's :class:`lerobot_pdp.paced_chunks.JustInTime` (made with the policy: a new policy, a new
    one); None when the server does not serve PDP."""
    policy = getattr(server, "policy", None)
    if getattr(server, "policy_type", None) != SERVED or policy is None:
        return None
    if getattr(policy, "_paced_timing", None) is None:
        from .paced_chunks import JustInTime

        policy._paced_timing = JustInTime(server.config.environment_dt)
    return policy._paced_timing


def with_paced_observations(original: Callable) -> Callable:
    """Wrap LeRobot's ``PolicyServer._enqueue_observation``: a served PDP keeps every observation the client sends
    (one whose predecessors were not sent is not planned from: :class:`lerobot_pdp.paced_chunks.ReceivedFrames`)
    and plans its next chunk just in time, whatever LeRobot's similarity filter says
    (:class:`lerobot_pdp.paced_chunks.JustInTime`; ``--policy.async_just_in_time=false``: only from an empty queue);
    a must-go observation goes as in LeRobot's, unless it repeats the last one planned from."""

    @functools.wraps(original)
    def _enqueue_observation(self: Any, obs: Any) -> bool:
        timing = paced_timing(self)
        if timing is None:
            return original(self, obs)
        frames = getattr(self.policy, "_paced_frames", None)
        if frames is not None and not frames.received(obs):
            logger.debug("observation #%d waits for the next one: its predecessor was not sent", obs.get_timestep())
            return False
        if timing.repeats(obs):
            logger.debug("observation #%d: planned from already (sent again)", obs.get_timestep())
            return False
        if obs.must_go:
            queued = original(self, obs)
        elif self.policy.config.async_just_in_time and timing.due(obs):
            queued = _enqueue(self, obs)
        else:  # not yet due (or whole chunks: only from an empty queue)
            logger.debug("observation #%d: the client holds actions beyond the next chunk's lead", obs.get_timestep())
            return False
        if queued:
            timing.planning(obs, min(self.actions_per_chunk or self.policy.config.n_action_steps,
                                     self.policy.config.n_action_steps))
        return queued

    return _enqueue_observation


def _enqueue(server: Any, obs: Any) -> bool:
    """LeRobot's ``_enqueue_observation`` past its similarity filter (the newest observation replaces a queued one);
    a timestep already planned from is not planned from again."""
    with server._predicted_timesteps_lock:
        if obs.get_timestep() in server._predicted_timesteps:
            return False
    if server.observation_queue.full():
        server.observation_queue.get_nowait()
    server.observation_queue.put(obs)
    return True


def with_paced_policy(original: Callable, server: Any) -> Callable:
    """Wrap LeRobot's ``PolicyServer._predict_action_chunk`` (``server`` is its module): before a PDP chunk, the
    observations received just before the one planned from join the policy's history, and the actions the client
    executed up to its timestep are counted; the chunk's first action is then timed at the step after the
    observation's, and its actions are noted as planned (:class:`lerobot_pdp.paced_chunks.ReceivedFrames`,
    :func:`lerobot_pdp.paced_chunks.from_the_next_step`, :class:`lerobot_pdp.paced_chunks.ExecutedActions`)."""

    @functools.wraps(original)
    def _predict_action_chunk(self: Any, observation_t: Any):
        if self.policy_type != SERVED:
            return original(self, observation_t)
        try:
            return paced_chunk(self, observation_t)
        except Exception as e:  # the client is told by with_failed_planning, and served nothing more
            self._pdp_failure = (f"{PLANNING_FAILED} from observation #{observation_t.get_timestep()} "
                                 f"({type(e).__name__}: {e}); it serves this client nothing more: mend the cause "
                                 "(the server's log) and start the client again")
            self.shutdown_event.set()
            raise

    def paced_chunk(self: Any, observation_t: Any):
        from .paced_chunks import from_the_next_step, precede_history

        started = time.perf_counter()
        policy = getattr(self, "policy", None)
        frames = getattr(policy, "_paced_frames", None)
        if frames is not None:
            precede_history(policy, [self.preprocessor(server.raw_observation_to_observation(
                o.get_observation(), self.lerobot_features, self.policy_image_features))
                for o in frames.preceding(observation_t)])
        executed = getattr(policy, "_paced_executed", None)
        if executed is not None:
            executed.executed_up_to(observation_t.get_timestep())
        timing = paced_timing(self)
        last = getattr(policy, "_paced_last", None)
        if last is not None and timing is not None:
            last.plan(observation_t.get_timestep(), timing.delay())
        chunk = from_the_next_step(original(self, observation_t), self.config.environment_dt)
        if last is not None:
            last.sent(len(chunk))
        if executed is not None:
            executed.planned(chunk)
        if timing is not None:
            timing.planned(chunk, time.perf_counter() - started)
        return chunk

    return _predict_action_chunk


def with_failed_planning(original: Callable) -> Callable:
    """Wrap LeRobot's ``PolicyServer.GetActions``: the request during which PDP could not plan a chunk fails with
    the error (gRPC ``ABORTED``, details beginning with :data:`PLANNING_FAILED`); LeRobot's answers it with
    nothing, as when no observation came, and the client waits on."""

    @functools.wraps(original)
    def GetActions(self: Any, request: Any, context: Any):  # noqa: N802 - LeRobot's gRPC method
        self._pdp_failure = None
        out = original(self, request, context)
        if self._pdp_failure is not None:
            import grpc

            context.abort(grpc.StatusCode.ABORTED, self._pdp_failure)
        return out

    return GetActions


def admit_pdp(server: Any, overrides: list[str]) -> None:
    """Make LeRobot's policy-server module (``server``) serve PDP, in this process (the module docstring)."""
    if SERVED not in server.SUPPORTED_POLICIES:
        server.SUPPORTED_POLICIES = [*server.SUPPORTED_POLICIES, SERVED]
    for name, wrap in (("_predict_action_chunk", functools.partial(with_paced_policy, server=server)),
                       ("_enqueue_observation", with_paced_observations),
                       ("SendPolicyInstructions", with_input_check), ("GetActions", with_failed_planning)):
        method = getattr(server.PolicyServer, name)
        if not hasattr(method, _ORIGINAL):
            wrapper = wrap(method)
            setattr(wrapper, _ORIGINAL, method)
            setattr(server.PolicyServer, name, wrapper)
    for name, wrap in (("raw_observation_to_observation", with_vector_features),
                       ("get_policy_class", functools.partial(with_policy_options, overrides=overrides))):
        original = getattr(server, name)
        original = getattr(original, _ORIGINAL, original)  # admitted again: these options replace the last ones
        wrapper = wrap(original)
        setattr(wrapper, _ORIGINAL, original)
        setattr(server, name, wrapper)


def main(argv: Sequence[str] | None = None) -> None:
    args, overrides = split_policy_options(sys.argv[1:] if argv is None else argv)
    try:
        import draccus
        from lerobot.async_inference import policy_server as server
        from lerobot.async_inference.configs import PolicyServerConfig
    except ImportError as e:  # grpcio: LeRobot's "async" extra
        raise SystemExit(f"LeRobot's policy server needs its async extra ({e}): pip install 'lerobot[async]' "
                         "(or lerobot_policy_pdp[async])") from e
    from lerobot.utils.import_utils import register_third_party_plugins

    register_third_party_plugins()
    check_policy_options(overrides)
    admit_pdp(server, overrides)
    from .cli_errors import ending_on_signals
    from .latent_fitting import ENDING

    if any(a in ("-h", "--help") for a in args):  # draccus lists the server's options; PDP's come from here
        print("PDP's policy server: LeRobot's options below, and any --policy.<field>=<value> of PDPConfig (e.g. "
              "--policy.steer_mode=1, --policy.steer_dataset_root=DEMO --policy.steer_episode_index=0, "
              "--policy.steer_file=steer.json), applied to the checkpoint a client asks for (docs/deploy.md, "
              "'Asynchronous inference').\n")
    config = draccus.parse(PolicyServerConfig, args=args)
    with ending_on_signals("lerobot_pdp.policy_server"):  # Ctrl-C / SIGTERM: one line, not grpc's traceback
        try:
            server.serve(config)
        finally:  # a start-up fit running on a gRPC thread (a client connecting) stops: the exit waits for that thread
            ENDING.set()


if __name__ == "__main__":
    main()
