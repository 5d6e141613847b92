"""Steering requests, as written for a running PDP (``lerobot-pdp steer``, :func:`write_steering`): their form,
their checks against a checkpoint, and writing them whole.

Torch-free and LeRobot-free on purpose: ``lerobot-pdp steer`` is typed while a robot runs, beside the policy's
own process, and must answer in a blink rather than after importing LeRobot's policies. The policy's side (polling
the file, applying a request, fitting in the background) is :mod:`lerobot_pdp.steering`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .atomic import write_text_atomic
from .checkpoint_files import damaged_weights, read_config_json, require_checkpoint_files
from .episodes import check_recording, recording_info

REQUEST_KEYS = ("mode", "latent", "dataset")


def mode_key(mode: Any) -> Any:
    """A mode as a user types it: a string of digits (``"3"``, ``" -1 "``) is the mode id it reads as, anything else
    (a mode's name, an int) is returned as given. The one rule for every place a mode arrives as text: the steer
    file, ``lerobot-pdp`` flags, ``--policy.steer_mode``, ``fit_latent(init=...)``, the explorer's choices."""
    if isinstance(mode, str) and mode.strip().lstrip("-").isdigit():
        return int(mode)
    return mode


def write_steering(path: str | Path, request: dict[str, Any], expect: SteerTarget | None = None) -> None:
    """Validate ``request`` (its form; with ``expect``, also against the policy's latent size and modes; a
    recording to fit, its folder and episode, and with a checkpoint's ``expect`` its features and length) and write
    it atomically to ``path`` as strict JSON (no NaN /
    Infinity, which the policy would reject)."""
    check_request(request, expect)
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a folder: give the steering file's path (the one the running policy's "
                                "--policy.steer_file names)")
    if not path.parent.is_dir():
        raise FileNotFoundError(f"cannot write the steering file {path}: folder {path.parent} does not exist "
                                "(give the path the running policy's --policy.steer_file names)")
    if "dataset" in request:  # the recording as the policy will look for it (relative: to the file's folder)
        root, episode, _ = fit_request(request, base=path.parent)
        if expect is not None and expect.recording is not None:  # what the policy's fit would refuse
            check_recording(root, episode, expect.recording, min_frames=expect.horizon, fps=expect.fps,
                            names=expect.names)
    write_text_atomic(path, json.dumps(request, allow_nan=False) + "\n")


@dataclass
class SteerTarget:
    """What a request is checked against: the latent size and mode ids a policy accepts, and where they came
    from (named in the error). ``modes`` None: not known (unlabelled modes are discovered by the policy)."""

    latent_dim: int | None
    modes: dict[int, str] | None
    source: str  # "checkpoint DIR", named with an unknown mode
    latent_source: str  # why latent_dim is expected, named with a latent of another size
    recording: dict[str, tuple[int, ...]] | None = None  # features a recording to fit must have (key -> shape)
    horizon: int | None = None  # frames a recording's episode needs at least (one action chunk)
    fps: float | None = None  # the frame rate of the policy's training data (a recording's must be it)
    names: dict[str, list[str]] | None = None  # the training data's value names by key (a recording's order)


def checkpoint_target(checkpoint: str | Path) -> SteerTarget:
    """The latent size and mode labels of a checkpoint folder, read from its config.json and the behavior bank
    in model.safetensors (no policy is built)."""
    from safetensors import SafetensorError, safe_open

    folder = require_checkpoint_files(checkpoint)
    config, weights = folder / "config.json", folder / "model.safetensors"
    cfg = read_config_json(config)  # a damaged file: an error naming it
    try:
        with safe_open(str(weights), framework="numpy") as f:  # numpy: no torch import
            labels = f.get_tensor("behavior_mode").tolist() if "behavior_mode" in f.keys() else []
            n_taught = f.get_slice("taught_latents").get_shape()[0] if "taught_latents" in f.keys() else 0
    except SafetensorError as e:
        raise damaged_weights(str(weights), e) from e
    names = {int(k): v for k, v in (cfg.get("mode_names") or {}).items()}
    labelled = sorted({int(m) for m in labels if m >= 0})
    trained = labels[: len(labels) - n_taught]  # taught modes (the last rows) have ids without labelled data too
    modes = {m: names.get(m, str(m)) for m in labelled} if any(m >= 0 for m in trained) else None
    features = {**(cfg.get("input_features") or {}), **(cfg.get("output_features") or {})}
    recording = {k: tuple(ft["shape"]) for k, ft in features.items() if isinstance(ft, dict) and "shape" in ft}
    return SteerTarget(int(cfg.get("latent_dim", 2)), modes, f"checkpoint {folder}",
                       f"latent_dim of checkpoint {folder}", recording or None, cfg.get("horizon"),
                       cfg.get("dataset_fps"), cfg.get("dataset_feature_names"))


def file_target(path: str | Path) -> SteerTarget | None:
    """The latent size of the request already in a steering file (what the running policy accepted, or will
    reject, already), or None when it holds no latent."""
    try:
        latent = json.loads(Path(path).read_text()).get("latent")
    except (OSError, ValueError, AttributeError):
        return None
    if not isinstance(latent, list) or not latent:
        return None
    row = latent[0] if isinstance(latent[0], list) else latent
    return SteerTarget(len(row), None, str(path), f"the size of the latent already in {path}; --policy-path "
                       "checks against the policy's checkpoint instead")


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def check_request(request: Any, expect: SteerTarget | None = None) -> dict[str, Any]:
    """The request's form: a JSON object with exactly one of ``mode``, ``latent``, ``dataset``, finite latent
    values, a mode id >= 0 or a name, an episode and steps >= 0; with ``expect``, the latent's size and the mode
    against the policy's."""
    if not isinstance(request, dict):
        raise ValueError(f"a steering request must be a JSON object, got {type(request).__name__}: {request!r}")
    given = [k for k in REQUEST_KEYS if k in request]
    if len(given) != 1:
        raise ValueError(f"a steering request needs exactly one of {list(REQUEST_KEYS)}, got {sorted(request)}")
    allowed = {"dataset": {"dataset", "episode", "steps"}}.get(given[0], {given[0]})
    extra = sorted(set(request) - allowed)
    if extra:
        raise ValueError(f"unknown keys {extra} in a {given[0]!r} steering request (allowed: {sorted(allowed)})")
    if "latent" in request and request["latent"] is not None:
        _check_latent(request["latent"], expect)
    if "mode" in request:
        _check_mode(request["mode"], expect)
    if "dataset" in request:
        if not isinstance(request["dataset"], str) or not request["dataset"]:
            raise ValueError(f"steering: dataset must be a folder path, got {request['dataset']!r}")
        for key, what in (("episode", "an episode index (an integer >= 0)"), ("steps", "an integer >= 0")):
            v = request.get(key)
            if v is not None and (not isinstance(v, int) or isinstance(v, bool) or v < 0):
                raise ValueError(f"steering: {key} must be {what}, got {v!r}")
    return request


def _check_latent(latent: Any, expect: SteerTarget | None) -> None:
    rows = latent if isinstance(latent, list) and latent and all(isinstance(r, list) for r in latent) else [latent]
    if not all(isinstance(r, list) and r and all(_is_number(x) for x in r) for r in rows):
        raise ValueError(f"steering: latent must be a list of numbers (or one list per phase), got {latent!r}")
    bad = [x for r in rows for x in r if not math.isfinite(x)]
    if bad:
        raise ValueError(f"steering: latent {latent} has non-finite values {bad}; every value must be a finite number")
    if len({len(r) for r in rows}) != 1:
        raise ValueError(f"steering: the phase latents of {latent} have different sizes")
    if expect is not None and expect.latent_dim is not None and len(rows[0]) != expect.latent_dim:
        raise ValueError(f"steering: latent {latent} has {len(rows[0])} values; expected {expect.latent_dim} "
                         f"({expect.latent_source})")


def _check_mode(mode: Any, expect: SteerTarget | None) -> None:
    mode = mode_key(mode)
    if isinstance(mode, bool) or not isinstance(mode, (int, str)) or mode == "" or (isinstance(mode, int) and mode < 0):
        raise ValueError(f"steering: mode must be a mode id >= 0 or a mode name, got {mode!r}")
    if expect is None or expect.modes is None:
        return
    known = ", ".join(f"{m} ({n})" for m, n in sorted(expect.modes.items()))
    if mode not in expect.modes and mode not in expect.modes.values():
        raise ValueError(f"steering: no mode {mode!r} in {expect.source}; its modes are {known}")
    named = [m for m, n in expect.modes.items() if n == mode] if isinstance(mode, str) else []
    if len(named) > 1:
        raise ValueError(f"steering: mode name {mode!r} names modes {sorted(named)} in {expect.source}; steer by "
                         f"mode id (its modes are {known})")


def fit_request(request: dict[str, Any], base: str | Path | None = None) -> tuple[Path, int, int | None]:
    """The (dataset root, episode, steps) of a ``dataset`` request, checked before any fit starts: a dataset
    folder whose ``meta/info.json`` counts the episode."""
    root = Path(request["dataset"])
    if base is not None and not root.is_absolute():
        root = Path(base) / root
    total = int(recording_info(root).get("total_episodes") or 0)  # the data files: the fit's own check
    episode = request.get("episode", 0)
    if total == 0:
        check_recording(root, episode, {})  # an empty recording: said as adapt and lerobot-rollout say it
    if not 0 <= episode < total:
        raise ValueError(f"steering: {root} holds {total} episode(s) (0-{total - 1}); no episode {episode}")
    return root, episode, request.get("steps")
