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
request. A bad request is logged and the current latent kept: a typo must not stop a running robot.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any

from .adaptation import fit_provenance
from .atomic import write_text_atomic

logger = logging.getLogger(__name__)

REQUEST_KEYS = ("mode", "latent", "dataset")


def write_steering(path: str | Path, request: dict[str, Any]) -> None:
    """Validate ``request`` (its form, not against a policy) and write it atomically to ``path``."""
    check_request(request)
    write_text_atomic(path, json.dumps(request) + "\n")


def check_request(request: Any) -> dict[str, Any]:
    """The request's form: a JSON object with exactly one of ``mode``, ``latent``, ``dataset``."""
    if not isinstance(request, dict):
        raise ValueError(f"a steering request must be a JSON object, got {type(request).__name__}: {request!r}")
    given = [k for k in REQUEST_KEYS if k in request]
    if len(given) != 1:
        raise ValueError(f"a steering request needs exactly one of {list(REQUEST_KEYS)}, got {sorted(request)}")
    allowed = {"dataset": {"dataset", "episode", "steps"}}.get(given[0], {given[0]})
    extra = sorted(set(request) - allowed)
    if extra:
        raise ValueError(f"unknown keys {extra} in a {given[0]!r} steering request (allowed: {sorted(allowed)})")
    return request


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
            raise KeyError(f"steering: mode {request['mode']!r} is not a training mode; modes are {sorted(means)}")
        policy.set_latent(means[mode])
        return means[mode]
    raise AssertionError("unreachable: check_request admits one of REQUEST_KEYS")


def fit_request(request: dict[str, Any], base: str | Path | None = None) -> tuple[Path, int, int | None]:
    """The (dataset root, episode, steps) of a ``dataset`` request, checked before any fit starts."""
    root = Path(request["dataset"])
    if base is not None and not root.is_absolute():
        root = Path(base) / root
    if not (root / "meta" / "info.json").is_file():
        raise FileNotFoundError(f"steering: {root} is not a LeRobotDataset (no meta/info.json)")
    episode = request.get("episode", 0)
    if not isinstance(episode, int) or isinstance(episode, bool) or episode < 0:
        raise ValueError(f"steering: episode must be an episode index >= 0, got {episode!r}")
    steps = request.get("steps")
    if steps is not None and (not isinstance(steps, int) or steps < 0):
        raise ValueError(f"steering: steps must be an integer >= 0, got {steps!r}")
    return root, episode, steps


def _mode_id(policy: Any, mode: Any) -> int:
    """A mode id from an int, a digit string or a mode name of the checkpoint (``config.mode_names``)."""
    if isinstance(mode, int) and not isinstance(mode, bool):
        return mode
    if isinstance(mode, str):
        if mode.strip().lstrip("-").isdigit():
            return int(mode)
        names = policy.config.mode_names or {}
        for k, name in names.items():
            if name == mode:
                return int(k)
        raise KeyError(f"steering: unknown mode name {mode!r}; the checkpoint's modes are {names or 'unnamed'}")
    raise ValueError(f"steering: mode must be a mode id or name, got {mode!r}")


class BackgroundFit:
    """One ``fit_latent`` of a ``dataset`` request in a daemon thread (a robot loop must not wait for it; a
    process that ends meanwhile does not wait either). The result is activated by the control thread."""

    def __init__(self, policy: Any, root: Path, episode: int, steps: int | None):
        self.root, self.episode, self.steps = root, episode, steps
        self.result: Any = None
        self.error: BaseException | None = None
        self.started = time.perf_counter()
        self.seconds: float | None = None
        self._thread = threading.Thread(target=self._run, args=(policy,), name="pdp-steering-fit", daemon=True)
        self._thread.start()

    def _run(self, policy: Any) -> None:
        try:
            self.result = policy.fit_latent((self.root, self.episode), steps=self.steps, activate=False)
        except BaseException as e:  # noqa: BLE001 - reported by the control thread, which keeps its latent
            self.error = e
        self.seconds = time.perf_counter() - self.started

    def done(self) -> bool:
        return not self._thread.is_alive()

    def wait(self, timeout: float | None = None) -> bool:
        self._thread.join(timeout)
        return self.done()


class SteerFile:
    """Polls one steering file; :meth:`poll` applies its request once per change of the file (a ``dataset``
    request once its background fit is done)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._seen: tuple[int, int, int] | None = None
        self.fit: BackgroundFit | None = None  # the fit of the newest request, while it is not applied

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the running fit (if any) is done; True when none is left running."""
        return self.fit is None or self.fit.wait(timeout)

    def poll(self, policy: Any) -> bool:
        """Apply the file's request if the file changed since the last poll, and a background fit that has
        finished; True when the latent changed."""
        changed = self._finish_fit(policy)
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            return changed
        signature = (st.st_mtime_ns, st.st_size, st.st_ino)
        if signature == self._seen:
            return changed
        self._seen = signature
        self.fit = None  # a newer request supersedes a fit still running (its result is dropped)
        try:
            request = check_request(json.loads(self.path.read_text()))
            if "dataset" in request:
                root, episode, steps = fit_request(request, base=self.path.parent)
                self.fit = BackgroundFit(policy, root, episode, steps)
                logger.info("steering file %s: fitting z to %s episode %d in the background; acting on the "
                            "current latent until it is ready", self.path, root, episode)
                return changed
            z = apply_steering(policy, request, base=self.path.parent)
        except Exception as e:  # noqa: BLE001 - a running robot keeps its latent on any bad request
            logger.error("steering file %s: %s; keeping the current latent", self.path, e)
            return changed
        logger.info("steering file %s: %s -> latent %s", self.path, request,
                    z.tolist() if hasattr(z, "tolist") else z)
        return True

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
        policy.steering.activate(result.z, result.noise, fit_provenance((fit.root, fit.episode), result,
                                                                        policy.config, steps=fit.steps))
        logger.info("steering file %s: latent %s fitted to %s episode %d in %.1f s, active from this chunk",
                    self.path, result.z.tolist(), fit.root, fit.episode, fit.seconds)
        return True
