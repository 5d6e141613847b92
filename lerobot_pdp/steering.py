"""Live steering of a running PDP through a small JSON file (``--policy.steer_file=PATH``).

LeRobot's deployment loops (``lerobot-rollout``, ``lerobot-eval``) offer no channel into a running policy,
and reloading the policy would stop the robot. So the policy polls one file at each new action chunk: when
its content changed, the request in it sets the active latent before the chunk is generated. Requests:

* ``{"mode": 3}`` (a mode id, or a mode name): the mean latent of that training mode;
* ``{"latent": [0.1, -0.4]}``: that latent (``[[..], [..]]``: one per phase); ``{"latent": null}``: back to
  the policy's default (``inference_latent``);
* ``{"dataset": DIR, "episode": 0}``: fit z to that episode of a local LeRobotDataset (e.g. a new
  ``lerobot-record`` demonstration); ``"steps"`` overrides ``fit_steps``. A relative ``DIR`` is taken
  relative to the steering file's folder. The fit runs in a background thread, off the control path: the
  policy keeps acting on its current latent until the fit is done, and the first chunk after that uses the
  fitted one (a request written meanwhile supersedes it).

Write the file whole (:func:`write_steering`, or ``lerobot-pdp steer``): a reader must never see half a
request. Requests are checked before they are written (finite values, mode ids; with the checkpoint, its
latent size and modes) and written as strict JSON. A bad request that reaches the policy anyway (a
hand-written file) is logged and the current latent kept, with the fit of the last good request if one is
still running: a typo must not stop a running robot.

A checkpoint is also steered once, as it loads, by its config's ``steer_*`` fields (:func:`apply_config_steering`).
"""

from __future__ import annotations

import atexit
import contextlib
import contextvars
import json
import logging
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import torch

from .configuration_pdp import STEERING_FIELDS
from .console import latent_text
from .latent_fitting import FitCancelled, cancellable
from .lerobot_command import rollout_with_rtc
from .realtime_chunking import RTC_ENGINE, RTC_WAY_OUT
from .rollout_checks import check_rollout_cameras
from .steer_requests import (  # noqa: F401  (re-exported: the requests' checks and writer live there)
    REQUEST_KEYS,
    SteerTarget,
    check_request,
    checkpoint_target,
    file_target,
    fit_request,
    mode_key,
    write_steering,
)

logger = logging.getLogger(__name__)

_RUNNING: set[BackgroundFit] = set()  # live-steering fits still running, cancelled when the process exits


@atexit.register
def _cancel_running_fits() -> None:
    for fit in list(_RUNNING):
        fit.cancel()
        fit.wait(10)
        logger.warning("steering: the fit to %s episode %d was still running after %.1f s when the process ended: "
                       "abandoned, its latent never acted on (a fit at start-up, --policy.steer_dataset_root, runs "
                       "before the first action)", fit.root, fit.episode, fit.seconds or 0.0)


def apply_steering(policy: Any, request: dict[str, Any], base: str | Path | None = None) -> Any:
    """Set ``policy``'s active latent from one request (see the module docstring); returns the new latent.

    Raises ValueError / KeyError / FileNotFoundError naming what is wrong (unknown mode, latent of the wrong
    size, recording that does not match the checkpoint, ...).
    """
    check_request(request)
    if "dataset" in request:
        root, episode, steps = fit_request(request, base)
        return policy.fit_latent((root, episode), steps=steps).z
    if "latent" in request:
        policy.set_latent(request["latent"])
        return request["latent"]
    if "mode" in request:
        mode = _mode_id(policy, request["mode"])
        means = policy.mode_latents()
        if mode not in means:
            raise KeyError(f"steering: mode {request['mode']!r} is not a mode of this checkpoint; its modes are "
                           f"{_known_modes(means)}")
        policy.set_latent(means[mode])
        return means[mode]
    raise AssertionError("unreachable: check_request admits one of REQUEST_KEYS")


def config_steer_file(cfg: Any, training: bool) -> SteerFile | None:
    """The steering file of ``--policy.steer_file`` (None without one). A policy built to train (``lerobot-train``
    passes its dataset) is not steered as it loads: its ``steer_*`` fields are said once, as they go into every
    checkpoint's config.json and steer each later load of it (a fit to a recording again at every load)."""
    given = {f: getattr(cfg, f) for f in STEERING_FIELDS if getattr(cfg, f) is not None}
    if training and given:
        logger.warning("steering given to a training run (%s): PDP does not steer the policy it trains; the "
                       "checkpoints' config.json keeps it and every load of them is steered so. To steer a trained "
                       "checkpoint, give --policy.steer_* when loading it (lerobot-eval, lerobot-rollout)",
                       ", ".join(f"{k}={v!r}" for k, v in given.items()))
    return SteerFile(cfg.steer_file) if cfg.steer_file else None


def apply_config_steering(policy: Any, training: bool = False) -> None:
    """Apply ``policy``'s config steering fields, the steering of a checkpoint loaded by ``lerobot-eval`` /
    ``lerobot-rollout``: ``steer_latent``, else ``steer_mode`` (that mode's mean latent), else
    ``steer_dataset_root`` + ``steer_episode_index`` (a fit to that episode, run now, not in the control loop); then
    a request already in ``steer_file`` (:meth:`SteerFile.start`). Nothing when loaded to train
    (:func:`config_steer_file` said so)."""
    if training:
        return
    cfg = policy.config
    # what the policy acts under once loaded, named when a steering file's `--default` request drops it
    loaded = "the adapted checkpoint's latent" if len(policy.steering.latent) else None
    given = [f"{name}={value}" for name, value in (("steer_latent", cfg.steer_latent), ("steer_mode", cfg.steer_mode),
                                                  ("steer_dataset_root", cfg.steer_dataset_root)) if value is not None]
    if len(given) > 1:  # one wins by this order; a flag left over from an earlier command must not pass unseen
        logger.warning("steering: %s given together; %s wins (steer_latent, then steer_mode, then a fit to "
                       "steer_dataset_root), %s ignored", ", ".join(given), given[0].partition("=")[0],
                       ", ".join(g.partition("=")[0] for g in given[1:]))
    if cfg.steer_latent is not None:
        policy.set_latent(torch.tensor(cfg.steer_latent, dtype=torch.float32))
        logger.info("steered by steer_latent: latent %s", cfg.steer_latent)
        loaded = "--policy.steer_latent"
    elif cfg.steer_mode is not None:
        means = policy.mode_latents()
        try:
            mode = _mode_id(policy, cfg.steer_mode)  # an id, or a name of the checkpoint's mode_names
        except KeyError:
            mode = None
        if mode not in means:
            raise KeyError(f"steer_mode {cfg.steer_mode!r} is not a mode of this checkpoint (an id or a name); its "
                           f"modes are {_known_modes(means)}")
        policy.steering.activate(means[mode], provenance={"source": "mode", "mode": mode})
        name = means.names.get(mode)
        logger.info("steered to mode %s%s: latent %s", mode, f" ({name})" if name else "", latent_text(means[mode]))
        loaded = f"mode {mode} (--policy.steer_mode)"
    elif cfg.steer_dataset_root is not None:
        start_up_fit(policy, (cfg.steer_dataset_root, int(cfg.steer_episode_index or 0)))
        loaded = "the latent fitted at start-up (--policy.steer_dataset_root)"
    if getattr(policy, "_steer_file", None) is not None:  # a request already in the file wins over the above
        policy._steer_file.start(policy, loaded)


def start_up_fit(policy: Any, episode: tuple[Any, int], steps: int | None = None) -> None:
    """Fit and activate z (and chunk noises with ``fit_noise=chunks``) to ``episode`` now, before the control loop
    starts, with a progress bar: ``--policy.steer_dataset_root`` and a ``dataset`` request already in the steering file
    when the policy loads."""
    refuse_paced_fit(policy, episode)  # refused after the fit otherwise (seconds to minutes)
    check_rollout_cameras(policy.config)  # so is a robot without the policy's cameras (lerobot-rollout)
    cfg = policy.config
    noises = " and one sampler noise per chunk" if cfg.fit_noise == "chunks" else ""
    logger.info("fitting the latent%s to %s episode %d before the control loop starts", noises, *episode)
    t0 = time.perf_counter()
    stop = threading.Event()
    with stopped_by_signals(stop) as caught, cancellable(stop):
        try:
            res = policy.fit_latent(episode, steps=steps, progress=True)  # a bar: with chunk noises, a minute on a CPU
        except FitCancelled:
            why = caught[0] if caught else "the process ending"  # off the main thread: no handler of ours
            stopped = KeyboardInterrupt(f"{why} during the start-up fit to {episode[0]} episode {episode[1]}, "
                                        f"{time.perf_counter() - t0:.1f} s in: stopped before any control loop started "
                                        "(no robot connected)")
            stopped.said_by_pdp = True  # one line in LeRobot's commands (cli_errors)
            raise stopped from None
    noises = f" and {len(res.noise)} chunk noise(s)" if res.noise is not None else ""
    logger.info("fitted latent%s to %s episode %d in %.1f s: %s (error ratio %s: its error on the demonstration "
                "over the training demonstrations' at their own latents; steering is at risk from %g)", noises,
                *episode, time.perf_counter() - t0, latent_text(res.z),
                "n/a" if res.error_ratio is None else f"{res.error_ratio:.2f}", cfg.fit_warn_ratio)


@contextlib.contextmanager
def stopped_by_signals(stop: threading.Event) -> Iterator[list[str]]:
    """In the block, SIGINT and SIGTERM set ``stop`` (the names of those caught are yielded) and reach the handlers
    they had before too. A minute-long fit runs inside ``from_pretrained``, where LeRobot's own handlers (which
    only set its shutdown event) would go unseen: the fit would run out and the robot be connected after a Ctrl-C.
    Only on the main thread, where Python runs signal handlers."""
    caught: list[str] = []
    if threading.current_thread() is not threading.main_thread():
        yield caught
        return
    # a handler installed from C reads as None and could not be put back: that signal is left alone (ours would stay
    # after the block and swallow every later Ctrl-C)
    before = {s: h for s in (signal.SIGINT, signal.SIGTERM) if (h := signal.getsignal(s)) is not None}

    def handler(signum: int, frame: Any) -> None:
        caught.append(signal.Signals(signum).name)
        stop.set()
        previous = before[signal.Signals(signum)]
        if callable(previous) and previous is not signal.default_int_handler:  # LeRobot's: its shutdown event set
            previous(signum, frame)

    for s in before:
        signal.signal(s, handler)
    try:
        yield caught
    finally:
        for s, h in before.items():
            signal.signal(s, h)

# (engine, way out, whether it reports the executed actions and each chunk's step) of a caller that replans at its
# own pace, set while it loads the policy: LeRobot's async policy server (policy_server.py) sets it; lerobot-rollout's
# RTC engine is told from the command line
_PACED: contextvars.ContextVar[tuple[str, str, bool] | None] = contextvars.ContextVar("pdp_paced_caller", default=None)


@contextlib.contextmanager
def paced_caller(engine: str, way_out: str, reports_executed: bool = False) -> Iterator[None]:
    """Policies loaded in this block will be called by ``engine``, which replans at its own pace (and, when
    ``reports_executed``, tells the policy the actions the robot executed, so per-phase latents follow, and each
    chunk's step, so fitted chunk noises are replayed by step): a start-up fit whose result it cannot follow is
    refused before it runs (:func:`refuse_paced_fit`), as ``realtime_chunking.check_rtc_steering`` refuses it at a
    chunk."""
    token = _PACED.set((engine, way_out, reports_executed))
    try:
        yield
    finally:
        _PACED.reset(token)


def refuse_paced_fit(policy: Any, episode: tuple[Any, int]) -> None:
    """Under a caller that replans at its own pace, refuse a start-up fit whose result it could not follow, before
    the fit runs: sampler noises per chunk or one latent per gripper phase, unless it reports the executed actions
    and so each chunk's step (lerobot-rollout's RTC engine with ``rtc_consumed_delay``, PDP's policy server); the chunk-time checks, ``realtime_chunking.check_rtc_steering``, would refuse them only
    after it."""
    rtc = (RTC_ENGINE, RTC_WAY_OUT, bool(policy.config.rtc_consumed_delay))  # PDP's RTC queue reports them
    engine, way_out, reports_executed = _PACED.get() or (rtc if rollout_with_rtc() else (None, None, False))
    if engine is None:
        return
    if policy.config.fit_noise == "chunks" and not reports_executed:  # noises are replayed by the reported step
        cause = (" and, with --policy.rtc_consumed_delay=false, the actions the robot executes do not reach PDP (the "
                 "default, true, has PDP's queue report them)" if engine == RTC_ENGINE else "")
        raise ValueError(f"--policy.fit_noise=chunks fits one sampler noise per {policy.config.n_action_steps} "
                         f"executed actions, which {engine} cannot replay in step (it replans at its own pace{cause}). "
                         f"{way_out} --policy.fit_noise=none")
    if policy.config.segment_gripper_dim is None or reports_executed:  # one latent, or phases that follow the robot
        return
    phases = len(policy._demonstration(episode, "auto", need_action=True).segments)
    if phases > 1:
        raise ValueError(f"{episode[0]} episode {episode[1]} splits into {phases} gripper phases, fitted one latent "
                         f"each, which advance on the gripper commands the robot executes; {engine} replans at its "
                         f"own pace and they do not reach PDP, so phases cannot follow. {way_out} steer with one "
                         "latent (--policy.steer_mode, --policy.steer_latent)")


def _known_modes(means: Any) -> str:
    """'0 (left), 1 (right), 2': a checkpoint's modes (``mode_latents()``) by id and name, for an error."""
    return ", ".join(f"{m} ({means.names[m]})" if means.names.get(m) else str(m) for m in sorted(means))


def _mode_id(policy: Any, mode: Any) -> int:
    """A mode id from an int, a digit string or a mode name of the checkpoint (``config.mode_names``)."""
    if isinstance(mode, int) and not isinstance(mode, bool):
        return mode
    if isinstance(mode, str):
        if isinstance(mode_key(mode), int):  # "3"
            return int(mode)
        names = policy.config.mode_names or {}
        ids = [int(k) for k, name in names.items() if name == mode]
        if len(ids) > 1:  # a checkpoint taught before names were checked: no silent pick
            raise KeyError(f"steering: mode name {mode!r} names modes {ids}; steer by mode id")
        if ids:
            return ids[0]
        known = ", ".join(f"{k} ({v})" for k, v in sorted(names.items(), key=lambda kv: int(kv[0]))) or "unnamed"
        raise KeyError(f"steering: unknown mode name {mode!r}; the checkpoint's modes are {known}")
    raise ValueError(f"steering: mode must be a mode id or name, got {mode!r}")


class BackgroundFit:
    """One ``fit_latent`` of a ``dataset`` request in a daemon thread (a robot loop must not wait for it). The
    result is activated by the control thread. :meth:`cancel` stops it at its next step: a newer request
    supersedes it, and a process that ends meanwhile cancels it and waits the step out (a thread left inside
    torch's kernels aborts the interpreter's exit)."""

    def __init__(self, policy: Any, root: Path, episode: int, steps: int | None):
        self.root, self.episode, self.steps = root, episode, steps
        self.result: Any = None
        self.error: BaseException | None = None
        self.started = time.perf_counter()
        self.seconds: float | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(policy,), name="pdp-steering-fit", daemon=True)
        _RUNNING.add(self)
        self._thread.start()

    def _run(self, policy: Any) -> None:
        try:
            with cancellable(self._stop):
                self.result = policy.fit_latent((self.root, self.episode), steps=self.steps, activate=False)
        except BaseException as e:  # noqa: BLE001 - reported by the control thread, which keeps its latent
            self.error = e
        finally:
            self.seconds = time.perf_counter() - self.started
            _RUNNING.discard(self)

    def cancel(self) -> None:
        """Stop the fit at its next step (its result, if it finishes first, is dropped by the caller)."""
        self._stop.set()

    def done(self) -> bool:
        return not self._thread.is_alive()

    def wait(self, timeout: float | None = None) -> bool:
        self._thread.join(timeout)
        return self.done()


class SteerFile:
    """Polls one steering file; :meth:`poll` applies its request once per change of the file (a ``dataset``
    request once its background fit is done).

    A change is a new (mtime, size, inode) or new contents: a file rewritten in place at the same size within
    one clock tick keeps its stat, so the contents (a few bytes) are compared at every poll as well.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if self.path.is_dir():  # read at every chunk: refused now, not as a crash of the control loop's first chunk
            raise ValueError(f"steer_file {self.path} is a folder: give the file `lerobot-pdp steer` writes, e.g. "
                             f"{self.path / 'steer.json'}")
        if not self.path.parent.is_dir():
            logger.warning("steer_file %s: folder %s does not exist, so no request can reach the policy (`lerobot-pdp "
                           "steer` refuses that path too); create it, or fix the path", self.path, self.path.parent)
        else:
            logger.info("steering file %s: read at each new chunk (`lerobot-pdp steer %s ...` writes it)", self.path,
                        self.path)
        self._seen: tuple[tuple[int, int, int], bytes] | None = None
        self._polled = False  # a bad request the file holds at the first poll is an error, as a bad steer_mode is
        self._read_error: str | None = None  # said once, not at every chunk
        self._loaded: str | None = None  # the steering the policy loaded with, until a request replaces it
        self.fit: BackgroundFit | None = None  # the fit of the newest request, while it is not applied
        # raises ValueError for a steering state the running engine cannot act under (realtime_chunking.py): the
        # request is then refused like a bad one, and the previous state kept
        self.check: Callable[[Any], None] | None = None

    def start(self, policy: Any, loaded: str | None = None) -> None:
        """The first poll, when the policy loads (:func:`apply_config_steering`): a request already in the file is
        applied before the first action, a recording fitted now (:func:`start_up_fit`, not in the background); a
        bad one is an error, as a bad ``--policy.steer_mode`` is. ``loaded``: the steering the policy loaded with
        (an adaptation, a ``steer_*`` flag), named with a warning when a ``--default`` request drops it."""
        self._loaded = loaded
        if not self._polled:
            self.poll(policy, at_start=True)

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the running fit (if any) is done; True when none is left running."""
        return self.fit is None or self.fit.wait(timeout)

    def poll(self, policy: Any, at_start: bool = False) -> bool:
        """Apply the file's request if the file changed since the last poll, and a background fit that has
        finished; True when the latent changed. ``at_start``: before any control loop (:meth:`start`), so a
        recording is fitted now rather than in the background."""
        changed = self._finish_fit(policy)
        first, self._polled = not self._polled, True
        try:
            st = os.stat(self.path)
            content = self.path.read_bytes()
        except FileNotFoundError:
            return changed
        except OSError as e:  # a folder or an unreadable file where the file was: the robot keeps its latent
            if str(e) != self._read_error:
                logger.error("steering file %s cannot be read (%s); keeping the current latent", self.path, e)
                self._read_error = str(e)
            return changed
        self._read_error = None
        seen = ((st.st_mtime_ns, st.st_size, st.st_ino), content)
        if seen == self._seen:
            return changed
        self._seen = seen
        pending, self.fit = self.fit, None  # a newer request supersedes a fit still running (cancelled below)
        try:
            try:
                request = json.loads(content, parse_constant=_no_constant)
            except json.JSONDecodeError as e:
                raise ValueError(f"not valid JSON ({e})") from e
            request = check_request(request)
            if "dataset" in request:
                root, episode, steps = fit_request(request, base=self.path.parent)
                if at_start:  # nothing acts yet: fitted now, with a bar, as --policy.steer_dataset_root is
                    start_up_fit(policy, (root, episode), steps)
                    logger.info("steering file %s: %s -> latent %s%s", self.path, request,
                                latent_text(policy.active_latent), self._overriding(at_start))
                    self._loaded = None
                    return True
                self._supersede(pending, request)
                self.fit = BackgroundFit(policy, root, episode, steps)
                logger.info("steering file %s: fitting z to %s episode %d in the background; acting on the "
                            "current latent until it is ready", self.path, root, episode)
                return changed
            z = self._checked(policy, lambda: apply_steering(policy, request, base=self.path.parent))
            self._supersede(pending, request)
        except Exception as e:  # noqa: BLE001 - a running robot keeps its latent on any bad request
            said = e.args[0] if isinstance(e, KeyError) and e.args else e  # a KeyError's str() is its repr
            if first:  # there before the first action: nothing to keep, refused as a bad --policy.steer_mode is
                raise ValueError(f"steering file {self.path} (there when the policy started): {said}") from e
            self.fit = pending  # a refused request supersedes nothing: the last good one's fit goes on
            logger.error("steering file %s: %s; keeping the current latent%s", self.path, said,
                         " (the fit still running stays)" if pending is not None else "")
            return changed
        if request.get("latent", 0) is None and self._loaded is not None:  # an adaptation dropped on the robot's next chunk
            logger.warning("steering file %s: back to the default latent (inference_latent=%r, as the base policy "
                           "acts); %s, which the policy loaded with, is dropped: write its request again, or restart "
                           "with a fresh steering file, to act under it", self.path, policy.config.inference_latent,
                           self._loaded)
        else:
            to = (f"latent {latent_text(z)}" if z is not None else  # --default: the policy's own choice per chunk
                  f"the default latent (inference_latent={policy.config.inference_latent!r})")
            logger.info("steering file %s: %s -> %s%s", self.path, request, to, self._overriding(at_start))
        self._loaded = None
        return True

    def _overriding(self, at_start: bool) -> str:
        """At load, what the file's request replaces (a ``steer_*`` flag, an adaptation), for its log line."""
        return f" (the file's request, in place of {self._loaded})" if at_start and self._loaded else ""

    def _supersede(self, pending: BackgroundFit | None, request: dict[str, Any]) -> None:
        """Stop the fit a newer request replaces (at its next step), and say so: its latent will never act."""
        if pending is not None:
            pending.cancel()
            logger.info("steering file %s: the fit to %s episode %d still running is cancelled (%s supersedes it)",
                        self.path, pending.root, pending.episode, request)

    def _checked(self, policy: Any, apply: Callable[[], Any]) -> Any:
        """``apply()``, undone when :attr:`check` refuses the steering state it leaves."""
        if self.check is None:
            return apply()
        st = policy.steering
        saved = (st.latent.clone(), st.noises.noise.clone(), st.provenance)
        out = apply()
        try:
            self.check(policy)
        except ValueError:
            st.activate(saved[0] if len(saved[0]) else None, saved[1] if len(saved[1]) else None, saved[2])
            raise
        return out

    def _finish_fit(self, policy: Any) -> bool:
        """Activate the background fit's latent (and noises) if it is done; True when it was."""
        fit = self.fit
        if fit is None or not fit.done():
            return False
        self.fit = None
        if fit.error is not None:
            logger.error("steering file %s: the fit to %s episode %d failed: %s; keeping the current latent",
                         self.path, fit.root, fit.episode, fit.error)
            return False
        result = fit.result
        try:
            self._checked(policy, lambda: policy.steering.activate(result.z, result.noise, result.provenance))
        except ValueError as e:
            logger.error("steering file %s: %s; keeping the current latent", self.path, e)
            return False
        self._loaded = None
        logger.info("steering file %s: latent %s fitted to %s episode %d in %.1f s, active from this chunk",
                    self.path, latent_text(result.z), fit.root, fit.episode, fit.seconds)
        return True


def _no_constant(name: str) -> Any:
    """json.loads reads NaN / Infinity by default; a steering request is strict JSON."""
    raise ValueError(f"{name} is not valid JSON (every latent value must be a finite number)")
