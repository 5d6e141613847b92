"""Real-time chunking: PDP under ``lerobot-rollout --inference.type=rtc``.

LeRobot's RTC engine (``lerobot.rollout.inference.rtc``) generates chunks in a background thread while the
control loop keeps its pace; each new chunk replaces the queue, less the actions executed while it was being
generated (``inference_delay``). To keep the new chunk continuous with what the robot is executing, the
engine passes the previous chunk's unexecuted actions (``prev_chunk_left_over``) and LeRobot's flow-matching
policies guide their sampler towards them (Black et al., "Real-Time Execution of Action Chunking Flow
Policies"). PDP samples with DDIM, so the same prefix is imposed on the *predicted clean chunk* of every DDIM
step: ``x0 <- x0 + w * (prefix - x0)`` with LeRobot's prefix weights ``w`` (1 over the delay, then decaying to 0
at ``execution_horizon``), and the step goes towards the edited chunk. The denoiser sees the prefix in every
noisy chunk after that, so the free actions are denoised to continue it. No backward pass: a guided chunk
costs what a plain one does.

What differs from ``select_action``:

- the engine passes one observation per chunk, not the control loop's history. With ``rtc_observation_history``
  (the default) PDP keeps the observations the loop publishes (:class:`PublishedObservations`, fed by the
  engine's ``notify_observation``) and conditions the chunk on the ``n_obs_steps`` up to the chunk's own, as
  ``select_action`` does; otherwise (or before the loop has published enough) the history is filled with the
  chunk's observation, as at an episode's first chunk;
- the whole predicted future is returned (``horizon - n_obs_steps + 1`` actions, not ``n_action_steps``), so
  the engine's queue has slack while the next chunk is generated;
- per-phase latents advance on the gripper commands the robot executes, and fitted chunk noises belong to the
  demonstration's frames (noise j to the frames from ``j * n_action_steps``): ``select_action`` counts the actions
  it hands out and its chunks; under RTC PDP's queue (:class:`ConsumedDelayQueue`, below) tells PDP each action the
  loop takes from it, so the next chunk the engine generates after a phase ends is conditioned on the next phase's
  latent (``select_action`` replans at once), and a chunk planned at the episode's step k starts from noise
  ``k // n_action_steps`` (``Steering.by_step``); while noises are replayed the queue lets the engine start chunks
  only from the observations of steps ``j * n_action_steps`` (:attr:`ConsumedDelayQueue.noise_cadence`), so each
  noise meets its own frames. With LeRobot's own queue
  (``rtc_consumed_delay=false``) nothing reports the executed actions: both are refused with a message
  (``--inference.type=sync`` runs them), at start-up and as live requests (the robot keeps its latent);
- a chunk whose generation overlapped a ``reset()`` (a new episode), or whose observation was published
  before it, is returned empty: its observation belongs to the episode that ended (the observations the loop
  published tell which episode a chunk's is from, with or without the history; LeRobot's engine keeps its last
  observation across ``reset()``).

A new chunk must continue from the step of the observation it was generated from. LeRobot's queue (0.6.1)
replaces its actions with the new chunk less ``ceil(latency * fps)`` actions, and takes the prefix from the
actions not yet executed when the engine starts the chunk. The loop publishes an observation and then executes
that step's action, so the engine usually reads an observation whose step's action is already executed: its
prefix starts one step late, and the number dropped is off by one either way. PDP's chunks are short and
replanned every few actions, so that misalignment recurs (avoiding, pick-place: docs/performance.md). With
``rtc_consumed_delay`` (the default) PDP has the engine use :class:`ConsumedDelayQueue`, which counts the
actions executed since the observation (the engine's ``notify_observation`` announces each one) and tells PDP
each executed action (its gripper phases and its step in the episode). It is set on
LeRobot's engine module when a PDP policy is prepared for RTC, so an engine started later in the same process, for
any policy, builds it too (``lerobot-rollout`` runs one policy per process).
On CUDA a guided chunk is replayed from the sampler's captured graph too, the prefix's target and weights its inputs.

When the engine gives up (LeRobot's engine retries a failed chunk, e.g. PDP's ``FloatingPointError`` for a
non-finite action, and after 10 in a row logs "Fatal error in RTC thread" and ends the run as finished),
``lerobot-rollout`` exits 1 naming the last error, after LeRobot's teardown has stopped the robot
(:func:`install_exit_status`); LeRobot's own run exits 0 there.
"""

from __future__ import annotations

import functools
import logging
import sys
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

import torch
from lerobot.policies.rtc.action_queue import ActionQueue
from lerobot.policies.rtc.configuration_rtc import RTCConfig
from lerobot.policies.rtc.modeling_rtc import RTCProcessor
from torch import Tensor

from .diffusion import PrefixGuide
from .pdp_model import check_finite_actions

logger = logging.getLogger(__name__)
ENGINE_MODULE = "lerobot.rollout.inference.rtc"
SCRIPT_MODULE = "lerobot.scripts.lerobot_rollout"
# what ended each PDP run whose RTC engine gave up, in this process (lerobot-rollout then exits 1 naming it)
ENGINE_FAILURES: list[str] = []
# How many actions a new chunk is held to the last one, chosen on validation checkpoints at 50 fps on a CPU
# (docs/performance.md, "How long a new chunk is held to the last one")
RECOMMENDED_EXECUTION_HORIZON = 3


class ConsumedDelayQueue(ActionQueue):
    """LeRobot's RTC action queue, aligned with the observation each chunk comes from: a new chunk replaces the
    queue less the actions executed since that observation, and the prefix it continues starts at that
    observation's step (see the module docstring).

    The loop publishes an observation, then executes that step's action; the engine's thread reads the latest
    observation at any time in between, usually after that action. So the queue counts the actions executed
    (``executed``, never reset: ``last_index`` restarts with every chunk) and notes the count at each observation
    (:meth:`observed`, from the engine's ``notify_observation``); the thread asks for the action index right
    after reading the observation, which pins the chunk to it (an observation published in the microseconds
    between the two would shift it by one step). Without ``observed`` calls the count starts at that read."""

    def __init__(self, cfg: RTCConfig) -> None:
        super().__init__(cfg)
        # reentrant: merge checks, under the lock, that no clear() (a new episode) came while its chunk was generated
        self.lock = threading.RLock()
        self.cleared = 0  # clear() calls: a chunk started before the last one belongs to the episode that ended
        self._chunk_cleared = 0  # ``cleared`` when the pending chunk was started (get_action_index)
        self.executed = 0
        self.executed_at_observation: int | None = None  # None: no observation announced
        self._chunk_from: int | None = None  # ``executed`` at the observation the pending chunk comes from
        self._last_original: Tensor | None = None  # the last executed action, normalised
        # told each executed action [A], normalised, outside the lock (PDP's steps and phases; set by _announcing)
        self.on_executed: Callable[[Tensor], None] | None = None
        # (PDP's episode step at the latest observation, the chunk cadence fitted noises need or None); set by
        # _announcing. Fitted chunk noise j belongs to the demonstration's frames from j * n_action_steps, so
        # while noises are replayed a chunk starts only from the observation of such a step, as sync replans:
        # the queue threshold alone replanned every 7 actions at threshold 7 in a rollout (a chunk's generation
        # spanning about two steps), and a noise used off its frames takes the chunk away from the fitted one
        self.noise_cadence: Callable[[], tuple[int, int | None]] | None = None
        self._step_at_observation: int | None = None

    def observed(self) -> None:
        """The loop published an observation (before executing that step's action)."""
        step = self.noise_cadence()[0] if self.noise_cadence is not None else None
        with self.lock:
            self.executed_at_observation = self.executed
            self._step_at_observation = step

    def qsize(self) -> int:
        """LeRobot's count of the actions left; the engine starts a chunk when it falls to its threshold. While
        fitted noises are replayed (:attr:`noise_cadence`), 0 exactly at the observations of their steps (once
        each) and a count above any threshold otherwise, unless the queue ran dry."""
        size = super().qsize()
        every = self.noise_cadence()[1] if self.noise_cadence is not None else None
        if every is None or size == 0:
            return size
        with self.lock:
            step, seen = self._step_at_observation, self.executed_at_observation
            fresh = step is not None and step % every == 0 and self._chunk_from != seen
        return 0 if fresh else size + (1 << 30)

    def get(self) -> Tensor | None:
        with self.lock:  # LeRobot's get, counting what it hands out
            if self.queue is None or self.last_index >= len(self.queue):
                return None
            self._last_original = executed = self.original_queue[self.last_index]
            self.last_index += 1
            self.executed += 1
            action = self.queue[self.last_index - 1].clone()
        if self.on_executed is not None:
            self.on_executed(executed)
        return action

    def clear(self) -> None:
        with self.lock:  # a new episode: nothing executed belongs to its chunks, nor does a chunk in flight
            super().clear()
            self._last_original = None
            self.cleared += 1

    def merge(self, original_actions: Tensor, processed_actions: Tensor, real_delay: int,
              action_index_before_inference: int | None = None) -> None:
        """LeRobot's merge, but a chunk started before the last :meth:`clear` (the engine's ``reset()`` at a new
        episode, which does not wait for its thread) is dropped: PDP's own check (:func:`rtc_chunk`) ends when the
        chunk is returned, and the engine merges it after postprocessing it."""
        with self.lock:
            if action_index_before_inference is not None and self._chunk_cleared != self.cleared:
                logger.debug("PDP under RTC: a chunk started before the episode's reset is dropped")
                return
            super().merge(original_actions, processed_actions, real_delay, action_index_before_inference)

    def get_action_index(self) -> int:
        with self.lock:  # the engine's thread, as it starts a chunk from the observation it just read
            self._chunk_cleared = self.cleared
            seen = self.executed_at_observation
            self._chunk_from = self.executed if seen is None else seen
            return self.last_index

    def get_left_over(self) -> Tensor | None:
        """The previous chunk's actions from the chunk's observation on (at most one step back: the loop
        executes one action per observation)."""
        with self.lock:
            if self.original_queue is None:
                return None
            behind = 0 if self._chunk_from is None else self.executed - self._chunk_from
            start = self.last_index - behind
            if start < 0 and self._last_original is not None:  # that action came from the chunk before
                return torch.cat([self._last_original[None], self.original_queue])
            return self.original_queue[max(start, 0):].clone()

    def _check_and_resolve_delays(self, real_delay: int, action_index_before_inference: int | None = None) -> int:
        if action_index_before_inference is None or self._chunk_from is None:
            return max(0, real_delay)
        return max(0, self.executed - self._chunk_from)  # merge holds the lock


class PublishedObservations:
    """The raw observations the control loop published to LeRobot's RTC engine, newest last, so a chunk can be
    conditioned on the history ``select_action`` keeps: the engine passes a chunk only the one it read.

    The engine's thread reads the latest observation, preprocesses it and asks for a chunk; the loop may publish
    another meanwhile, so the chunk's own observation is found among the last few by comparing it, preprocessed
    as the engine does, with the chunk's. The frames before it are preprocessed the same way (the engine's
    pipeline; PDP's is stateless). Frames from before an episode's start (the policy's ``reset()``) are not
    its history, and a chunk whose own frame is from an episode that ended is stale. ``keep_history=False``:
    only that check (the chunk is conditioned on its observation repeated)."""

    def __init__(self, n_obs_steps: int, keep_history: bool = True) -> None:
        self.n_obs_steps = n_obs_steps
        self.keep_history = keep_history
        self._frames: deque[tuple[int, dict]] = deque(maxlen=n_obs_steps + 8)  # (policy resets, raw observation)
        self._engine: Any = None
        self._lock = threading.Lock()
        self.matched = 0  # chunks whose observation was found among the frames kept
        self.unmatched = 0  # chunks whose observation was not (conditioned on it repeated, its episode unchecked)

    def published(self, engine: Any, obs: dict) -> None:
        """The loop published ``obs`` (the control loop's thread)."""
        resets = engine._policy.steering.resets
        with self._lock:
            self._engine = engine
            self._frames.append((resets, obs))

    def history(self, policy: Any, batch: dict[str, Tensor]) -> tuple[dict[str, Tensor] | None, bool]:
        """(``batch``'s condition features as [1, n_obs_steps, *frame], the earlier frames from the observations
        published before the chunk's in its episode, the earliest repeated when fewer exist, or None: not found
        or no history kept; whether the chunk's observation belongs to an episode that has ended)."""
        with self._lock:
            engine, frames = self._engine, list(self._frames)
        features = policy.config.condition_features
        keys = list(features)
        if engine is None or not frames or any(k not in batch or batch[k].shape != (1, *features[k].shape)
                                                 for k in keys):
            return None, False  # nothing published, or not one frame of the engine's (a history passed: kept)
        i = self._find(engine, [obs for _, obs in frames], batch, keys)
        if i is None:
            self.unmatched += 1
            if self.unmatched == 1:
                logger.warning("PDP under RTC: a chunk's observation was not among the last %d the loop published; "
                               "its episode is not checked%s (and any other chunk like it)", len(frames),
                               ", and it is conditioned on that observation repeated" if self.keep_history else "")
            return None, False
        episode = frames[i][0]
        if episode != policy.steering.resets:
            return None, True
        self.matched += 1
        if not self.keep_history:
            return None, False
        earlier = [_preprocess(engine, obs) for resets, obs in frames[max(0, i - self.n_obs_steps + 1) : i]
                   if resets == episode]
        earlier = [earlier[0] if earlier else batch] * (self.n_obs_steps - 1 - len(earlier)) + earlier
        return {k: torch.stack([f[k] for f in [*earlier, batch]], dim=1) for k in keys}, False

    @staticmethod
    def _find(engine: Any, frames: list[dict], batch: dict[str, Tensor], keys: list[str]) -> int | None:
        """The index of the chunk's observation in ``frames``, searched newest first (usually the chunk's own).
        The robot's vectors are compared first, as they cost little to preprocess, up to the end of the newest
        run of frames they match: one match is the chunk's own. Images tell apart the frames of a run (a robot
        at rest), and are compared throughout when the policy has no vector input."""
        newest_first = list(range(len(frames) - 1, -1, -1))
        vectors = {k: ft for k, ft in engine._hw_features.items() if ft["dtype"] not in ("image", "video")}
        run: list[int] = []
        compared: list[str] = []
        for i in newest_first if vectors else []:
            pre = _preprocess(engine, frames[i], vectors)
            compared = compared or [k for k in keys if k in pre]
            if not compared:
                break
            if _same_frame(pre, batch, compared):
                run.append(i)
            elif run:
                break
        if compared and len(run) <= 1:
            return run[0] if run else None  # a frame whose vectors differ cannot be the chunk's
        return next((i for i in (run if compared else newest_first)
                     if _same_frame(_preprocess(engine, frames[i]), batch, keys)), None)


def _preprocess(engine: Any, obs: dict, features: dict | None = None) -> dict[str, Tensor]:
    """``obs`` as the engine's thread turns a raw observation into the policy's input (lerobot.rollout.inference.rtc,
    ``_rtc_loop``; its helpers are LeRobot's own); ``features``: only these of the robot's."""
    from lerobot.policies.utils import prepare_observation_for_inference
    from lerobot.utils.feature_utils import build_dataset_frame

    frame = build_dataset_frame(engine._hw_features if features is None else features, obs, prefix="observation")
    frame = prepare_observation_for_inference(frame, torch.device(engine._device), engine._task,
                                              engine._robot.robot_type)
    frame["task"] = [engine._task]
    return engine._preprocessor(frame)


def _same_frame(a: dict[str, Tensor], b: dict[str, Tensor], keys: list[str]) -> bool:
    return all(torch.equal(a[k], b[k].to(a[k].device)) for k in keys)


def prepare_rtc(policy: Any) -> None:
    """What ``lerobot-rollout`` calls once ``config.rtc_config`` is set (``init_rtc_processor``), before the
    engine starts: name the run's prefix length against the recommended one; keep the observations the loop
    publishes (the chunks' episodes, and with ``rtc_observation_history`` their history); with
    ``rtc_consumed_delay`` have the engine build its queue as :class:`ConsumedDelayQueue` (which also reports the
    executed actions: PDP's gripper phases and chunk noises follow them); refuse steering RTC cannot honour (now,
    and in live requests of ``steer_file``)."""
    if getattr(policy.config.rtc_config, "enabled", True):
        logger.info("PDP under RTC: this run holds each new chunk to the last one over its first %d actions "
                    "(--inference.rtc.execution_horizon); %d is recommended: LeRobot's default 10 cost pick-place "
                    "about 20 points against sync (docs/deploy.md)", policy.config.rtc_config.execution_horizon,
                    RECOMMENDED_EXECUTION_HORIZON)
    else:  # LeRobot's engine then appends each chunk as it comes (--inference.rtc.enabled=false)
        logger.info("PDP under RTC's engine with --inference.rtc.enabled=false: new chunks are planned in the "
                    "background and appended, nothing held to the last one")
    cfg = policy.config
    keep_history = cfg.rtc_observation_history and cfg.n_obs_steps > 1
    policy._rtc_observations = PublishedObservations(cfg.n_obs_steps, keep_history)
    policy._rtc_reports_executed = _install_queue(policy, sys.modules.get(ENGINE_MODULE), keep_history)
    policy.steering.by_step = policy._rtc_reports_executed  # chunk noises by the episode's step, not in order
    _report_failures(sys.modules.get(ENGINE_MODULE))
    check_rtc_steering(policy)
    if policy._steer_file is not None:  # a live request the engine cannot follow is refused, the latent kept
        policy._steer_file.check = check_rtc_steering


def _install_queue(policy: Any, engine: Any, keep_history: bool) -> bool:
    """Give LeRobot's RTC ``engine`` module (loaded by lerobot-rollout before it loads the policy) PDP's
    announcements and queue; True when the queue will report each executed action."""
    if engine is None:
        return False
    cfg = policy.config
    announce = getattr(engine.RTCInferenceEngine, "notify_observation", None)
    if announce is None:
        logger.warning("PDP: this LeRobot's RTC engine has no notify_observation; each chunk is conditioned on its "
                       "observation repeated, aligned with the moment the engine reads it (it may be one step late), "
                       "and a chunk from the last episode's observation is not told apart")
        return False
    if not getattr(announce, "announces_to_pdp", False):
        engine.RTCInferenceEngine.notify_observation = _announcing(announce)
    if keep_history:
        logger.info("PDP under RTC: each chunk is conditioned on the last %d observations the loop published, "
                    "as select_action is (--policy.rtc_observation_history=false: on its own, repeated)",
                    cfg.n_obs_steps)
    if not cfg.rtc_consumed_delay:
        return False
    if engine.ActionQueue is ConsumedDelayQueue:
        return True
    if engine.ActionQueue is not ActionQueue or not hasattr(ActionQueue, "_check_and_resolve_delays"):
        logger.warning("PDP: this LeRobot's RTC engine has another action queue (%s); its delay rule is kept",
                       engine.ActionQueue)
        return False
    engine.ActionQueue = ConsumedDelayQueue
    future = cfg.horizon - cfg.n_obs_steps + 1  # what rtc_chunk returns
    logger.info("PDP under RTC: a new chunk replaces the queue less the actions executed since its observation "
                "(--policy.rtc_consumed_delay=false: LeRobot's ceil(latency * fps)). PDP plans %d actions ahead, so "
                "LeRobot's default --inference.queue_threshold=30 generates chunks back to back, one core busy; "
                "--inference.queue_threshold=%d replans every ~%d actions as sync does (docs/deploy.md)",
                future, future - cfg.n_action_steps, cfg.n_action_steps)
    return True


def _report_failures(engine: Any) -> None:
    """Have LeRobot's RTC engine thread, when it ends failed while running a PDP policy, add what failed last to
    :data:`ENGINE_FAILURES` (the engine only logs it)."""
    if engine is None or getattr(engine.RTCInferenceEngine._rtc_loop, "reports_to_pdp", False):
        return
    loop = engine.RTCInferenceEngine._rtc_loop

    @functools.wraps(loop)
    def _rtc_loop(self: Any) -> None:
        loop(self)
        policy = getattr(self, "_policy", None)
        if getattr(self, "failed", False) and hasattr(policy, "_rtc_observations"):
            error = getattr(policy, "_rtc_error", None)
            ENGINE_FAILURES.append(f"{type(error).__name__}: {error}" if error is not None else
                                   "an error outside PDP's chunk (the log's 'Fatal error in RTC thread' names it)")

    _rtc_loop.reports_to_pdp = True
    engine.RTCInferenceEngine._rtc_loop = _rtc_loop


def install_exit_status() -> None:
    """Make ``lerobot-rollout`` exit 1 when a PDP run's RTC engine gave up (LeRobot's script ends it as finished, exit
    0, so a supervising script sees success): its ``rollout`` is wrapped to raise ``SystemExit`` with the last
    error after it returns, i.e. after LeRobot's teardown stopped the robot. Only ``lerobot-rollout`` (the plugin
    module is imported before its ``main`` calls ``rollout``); other policies' runs are not changed."""
    main = sys.modules.get("__main__")
    script = main if getattr(getattr(main, "__spec__", None), "name", None) == SCRIPT_MODULE else \
        sys.modules.get(SCRIPT_MODULE)
    run = getattr(script, "rollout", None)
    if run is None or getattr(run, "exits_on_pdp_failure", False):
        return

    @functools.wraps(run)
    def rollout(*args: Any, **kwargs: Any) -> Any:
        done = len(ENGINE_FAILURES)
        result = run(*args, **kwargs)
        if len(ENGINE_FAILURES) > done:
            raise SystemExit(f"lerobot-rollout: error: LeRobot's RTC engine stopped generating PDP's chunks, so the run "
                             f"was ended and the robot stopped; the last chunk failed with {ENGINE_FAILURES[-1]}")
        return result

    rollout.exits_on_pdp_failure = True
    script.rollout = rollout


def _executed(policy: Any, action: Tensor) -> None:
    """An action the RTC loop executed ([A], normalised): one more step of the episode, and counted in the
    policy's gripper phases; a phase that ends takes effect at the engine's next chunk (no replan forced: the
    robot keeps executing the queue)."""
    policy.steering.executed_steps += 1
    policy._advance_phase(action[None], replan=False)


def _noise_cadence(policy: Any) -> tuple[int, int | None]:
    """(The episode's step, ``n_action_steps`` while fitted chunk noises are replayed by step, else None)."""
    st = policy.steering
    return st.executed_steps, policy.config.n_action_steps if st.by_step and len(st.noises) else None


def _announcing(notify: Callable[..., None]) -> Callable[..., None]:
    """The engine's ``notify_observation``, first telling PDP's queue and observation history that an observation
    was published."""

    def notify_observation(engine: Any, obs: dict) -> None:
        queue, policy = getattr(engine, "_action_queue", None), getattr(engine, "_policy", None)
        if isinstance(queue, ConsumedDelayQueue):
            if queue.on_executed is None and getattr(policy, "_rtc_reports_executed", False):
                queue.on_executed = functools.partial(_executed, policy)
                queue.noise_cadence = functools.partial(_noise_cadence, policy)
            queue.observed()
        published = getattr(policy, "_rtc_observations", None)
        if published is not None:
            published.published(engine, obs)
        notify(engine, obs)

    notify_observation.announces_to_pdp = True
    return notify_observation


RTC_ENGINE, RTC_WAY_OUT = "lerobot-rollout's RTC engine", "Use --inference.type=sync, or"


def check_rtc_steering(policy: Any, engine: str = RTC_ENGINE, way_out: str = RTC_WAY_OUT,
                       reports_executed: bool | None = None, replays_noises: bool | None = None,
                       noises_why: str | None = None) -> None:
    """Refuse steering that ``engine``, which replans at its own pace, cannot honour (see the module
    docstring), naming the way out. ``reports_executed``: whether the actions the robot executes reach the policy
    (None: what :func:`prepare_rtc` found for lerobot-rollout's RTC engine), which per-phase latents need;
    ``replays_noises``: whether fitted chunk noises are replayed by step (None: the same); ``noises_why``: why
    they are not, when not for want of the executed actions."""
    steering = policy.steering
    if reports_executed is None:
        reports_executed = getattr(policy, "_rtc_reports_executed", False)
    if replays_noises is None:
        replays_noises = reports_executed
    how = "the actions the robot executes do not reach PDP"
    if engine == RTC_ENGINE and not policy.config.rtc_consumed_delay:
        how += " (with --policy.rtc_consumed_delay=true, the default, PDP's queue reports them)"
    if steering.per_phase and not reports_executed:
        raise ValueError(
            f"PDP is steered with one latent per phase ({len(steering.latent)} phases), which advance on the gripper "
            f"commands the robot executes; {engine} replans at its own pace and {how}, so phases cannot "
            f"follow. {way_out} steer with one latent (a mode or a latent of one phase)")
    if len(steering.noises.noise) and not replays_noises:
        why = noises_why or how
        raise ValueError(
            f"the active adaptation carries {len(steering.noises.noise)} fitted chunk noises, one per "
            f"{policy.config.n_action_steps} executed actions of the demonstration; {engine} replans at its own "
            f"pace and {why}, so they cannot be replayed in step. {way_out} use an adaptation fitted "
            "without noises (fit_noise=none)")


def prefix_guide(policy: Any, left_over: Tensor, inference_delay: int, batch_size: int,
                 rtc: RTCConfig | None = None) -> PrefixGuide | None:
    """The x0 edit imposing the previous chunk's unexecuted actions on a new chunk (None: nothing to impose).

    ``left_over`` [T, A] or [B, T, A], normalised, first row = the action for the chunk's observation step (with
    LeRobot's own queue: the next action to execute); the engine pads it with
    zero rows up to ``execution_horizon``, so trailing all-zero rows are dropped (an exact 0.0 in every action
    dimension is the engine's padding, not a policy output). ``rtc``: the prefix's length and weights (None: the
    rollout's, ``config.rtc_config``)."""
    cfg = policy.config
    rtc = rtc if rtc is not None else cfg.rtc_config
    prefix = left_over if left_over.dim() == 3 else left_over[None]
    nonzero = (prefix != 0).any(dim=-1).any(dim=0).nonzero()
    length = int(nonzero[-1]) + 1 if len(nonzero) else 0
    start = cfg.n_obs_steps - 1  # the chunk's action at the current observation
    length = min(length, cfg.horizon - start)
    if length == 0 or rtc.execution_horizon <= 0:
        return None
    weights = RTCProcessor(rtc).get_prefix_weights(max(0, inference_delay), min(rtc.execution_horizon, length),
                                                   cfg.horizon - start)
    device = policy.model.device
    w = torch.zeros(1, cfg.horizon, 1, device=device)
    w[0, start:, 0] = weights.to(device)
    target = torch.zeros(batch_size, cfg.horizon, policy.action_dim, device=device)
    target[:, start : start + length] = prefix[:, :length].to(device=device, dtype=target.dtype)
    return PrefixGuide(target, w)


def _remembering_errors(chunk: Callable[..., Tensor]) -> Callable[..., Tensor]:
    """``chunk``, keeping on the policy the error of its last call, if it failed (``_rtc_error``): LeRobot's engine
    only logs it."""

    @functools.wraps(chunk)
    def remembering(policy: Any, *args: Any, **kwargs: Any) -> Tensor:
        policy._rtc_error = None
        try:
            return chunk(policy, *args, **kwargs)
        except Exception as error:
            policy._rtc_error = error
            raise

    return remembering


@_remembering_errors
@torch.no_grad()
def rtc_chunk(policy: Any, batch: dict[str, Tensor], inference_delay: int | None = None,
              prev_chunk_left_over: Tensor | None = None, noise: Tensor | None = None, **_: object) -> Tensor:
    """The predicted future [B, horizon - n_obs_steps + 1, A] (normalised) from one observation, its first
    actions guided towards ``prev_chunk_left_over`` when the rollout's RTC config is enabled."""
    cfg = policy.config
    resets = policy.steering.resets
    if policy._steer_file is not None:  # live steering: a changed file sets z before this chunk
        policy._steer_file.poll(policy)
    check_rtc_steering(policy)
    published = getattr(policy, "_rtc_observations", None)
    history, ended = published.history(policy, batch) if published is not None else (None, False)
    if ended:  # the engine read this observation before an episode ended: no action of it reaches the next one
        return torch.zeros(1, 0, policy.action_dim, device=policy.model.device)
    if history is None:
        history = {k: _history(batch, k, len(ft.shape), cfg.n_obs_steps) for k, ft in cfg.condition_features.items()}
    obs_cond = policy.model.acting_cond(history)
    b = obs_cond.shape[0]
    z = policy.current_latent(b, obs_cond.device)
    rtc = cfg.rtc_config
    guide = None
    if rtc is not None and rtc.enabled and prev_chunk_left_over is not None:
        guide = prefix_guide(policy, prev_chunk_left_over, inference_delay or 0, b)
    if noise is None:  # fitted noises: the one of the episode's step (Steering.by_step); None: drawn
        noise = policy.steering.next_noise(b, obs_cond.device)
    chunk = policy.model.generate(obs_cond, z, noise, guide=guide)
    check_finite_actions(chunk, z)
    future = chunk[:, cfg.n_obs_steps - 1 :]
    if policy.steering.resets != resets:  # an episode ended while this chunk was generated
        return future[:, :0]
    return future


def _history(batch: dict[str, Tensor], key: str, frame_dims: int, n_obs_steps: int) -> Tensor:
    """``batch[key]`` as [B, n_obs_steps, *frame]: one frame [B, *frame] (what the engine passes) repeated, a
    history [B, n_obs_steps, *frame] kept."""
    if key not in batch:
        raise KeyError(f"PDP conditions on {key!r}, which the observation lacks; it has {sorted(batch)}")
    x = batch[key]
    if x.dim() == frame_dims + 2:
        return x
    return x.unsqueeze(1).expand(-1, n_obs_steps, *x.shape[1:])
