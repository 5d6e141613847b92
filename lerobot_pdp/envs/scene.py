"""Scenes as data: the extra barriers (and removed built-in obstacles) that define a constraint shift.

A scene file is JSON or YAML in the env's world coordinates (metres)::

    {"name": "scene 1: only over-tight",
     "description": "optional free text",
     "barriers": [{"shape": "box", "pos": [x, y, z], "half_size": [hx, hy, hz]},
                  {"shape": "cylinder", "pos": [x, y] | [x, y, z], "radius": r, "half_height": h}],
     "remove": ["<name of a built-in obstacle>"],
     "waypoints": [[x, y, z], ...]}          # optional: a feasible route for a scripted demo

Scenes 0-3 of every env ship as ``scenes/<env>_scene<k>.json`` (the test scenes); validation scenes ship as
``scenes/<env>_val<k>.json`` and load by name (``scene="val1"``), so settings can be chosen on scenes that are
never reported. Any other file can be passed to ``gym.make(id, scene=PATH)`` without code changes. Validation errors name the file, the key and what
was expected, so a typo never silently yields the original scene.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

SCENE_KEYS = {"name", "description", "barriers", "remove", "waypoints"}
BOX_KEYS = {"shape", "pos", "half_size", "name", "rgba"}
CYLINDER_KEYS = {"shape", "pos", "radius", "half_height", "name", "rgba"}


class SceneError(ValueError):
    """A scene file or object is malformed, or conflicts with the env (e.g. a barrier covers the goal)."""


@dataclass(frozen=True)
class Barrier:
    """One static obstacle primitive. ``pos`` is the centre; cylinders stand upright (axis +z)."""

    shape: str
    pos: tuple[float, ...]
    half_size: tuple[float, float, float] | None = None
    radius: float | None = None
    half_height: float | None = None
    name: str | None = None
    rgba: tuple[float, float, float, float] | None = None

    def signed_distance(self, point: np.ndarray, default_z: float = 0.0) -> float:
        """Signed distance from ``point`` (2-D or 3-D) to the barrier surface; negative inside."""
        p = np.asarray(point, dtype=float)
        c = np.asarray(self.center3(default_z), dtype=float)
        if p.shape[-1] == 2:
            p = np.array([p[0], p[1], c[2]])
        if self.shape == "box":
            q = np.abs(p - c) - np.asarray(self.half_size)
            outside = np.linalg.norm(np.maximum(q, 0.0))
            return float(outside + min(q.max(), 0.0))
        radial = math.hypot(p[0] - c[0], p[1] - c[1]) - float(self.radius)
        axial = abs(p[2] - c[2]) - float(self.half_height)
        outside = math.hypot(max(radial, 0.0), max(axial, 0.0))
        return float(outside + min(max(radial, axial), 0.0))

    def center3(self, default_z: float = 0.0) -> tuple[float, float, float]:
        """Centre in 3-D; a 2-D cylinder position stands on ``default_z``."""
        if len(self.pos) == 2:
            return (self.pos[0], self.pos[1], default_z)
        return (self.pos[0], self.pos[1], self.pos[2])

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"shape": self.shape, "pos": list(self.pos)}
        if self.shape == "box":
            d["half_size"] = list(self.half_size)
        else:
            d["radius"] = self.radius
            d["half_height"] = self.half_height
        if self.name:
            d["name"] = self.name
        if self.rgba:
            d["rgba"] = list(self.rgba)
        return d


@dataclass(frozen=True)
class Scene:
    """A constraint shift: extra barriers plus names of built-in obstacles to remove."""

    name: str = "scene 0: original"
    barriers: tuple[Barrier, ...] = ()
    remove: tuple[str, ...] = ()
    waypoints: tuple[tuple[float, ...], ...] | None = None
    description: str = ""
    source: str = field(default="<object>", compare=False)

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"name": self.name, "barriers": [b.to_dict() for b in self.barriers]}
        if self.description:
            d["description"] = self.description
        if self.remove:
            d["remove"] = list(self.remove)
        if self.waypoints is not None:
            d["waypoints"] = [list(w) for w in self.waypoints]
        return d

    def check_clear(self, points: dict[str, np.ndarray], margin: float, default_z: float = 0.0) -> None:
        """Raise :class:`SceneError` if a barrier comes within ``margin`` of a named point (start, goal)."""
        for i, b in enumerate(self.barriers):
            for label, p in points.items():
                d = b.signed_distance(p, default_z)
                if d < margin:
                    raise SceneError(
                        f"{self.source}: barriers[{i}] ({b.shape} at {list(b.pos)}) covers the {label} "
                        f"{np.round(np.asarray(p), 3).tolist()} (clearance {d:.3f} m, need >= {margin:.3f} m)"
                    )


def _floats(value: Any, n: int | tuple[int, ...], where: str) -> tuple[float, ...]:
    ns = (n,) if isinstance(n, int) else n
    if not isinstance(value, (list, tuple)) or len(value) not in ns:
        raise SceneError(f"{where}: expected a list of {' or '.join(map(str, ns))} numbers, got {value!r}")
    out = []
    for v in value:
        out.append(_float(v, where))
    return tuple(out)


def _float(v: Any, where: str, positive: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SceneError(f"{where}: expected a number, got {v!r}")
    f = float(v)
    if not math.isfinite(f):
        raise SceneError(f"{where}: expected a finite number, got {v!r}")
    if positive and f <= 0:
        raise SceneError(f"{where}: expected a positive number, got {v!r}")
    return f


def _barrier(d: Any, where: str) -> Barrier:
    if not isinstance(d, dict):
        raise SceneError(f"{where}: expected a mapping with 'shape', got {d!r}")
    shape = d.get("shape")
    if shape not in ("box", "cylinder"):
        raise SceneError(f"{where}.shape: expected 'box' or 'cylinder', got {shape!r}")
    allowed = BOX_KEYS if shape == "box" else CYLINDER_KEYS
    unknown = sorted(set(d) - allowed)
    if unknown:
        raise SceneError(f"{where}: unknown key(s) {unknown} for a {shape}; allowed: {sorted(allowed)}")
    rgba = _floats(d["rgba"], 4, f"{where}.rgba") if "rgba" in d else None
    name = d.get("name")
    if name is not None and not isinstance(name, str):
        raise SceneError(f"{where}.name: expected a string, got {name!r}")
    if shape == "box":
        for k in ("pos", "half_size"):
            if k not in d:
                raise SceneError(f"{where}: a box needs '{k}'")
        hs = _floats(d["half_size"], 3, f"{where}.half_size")
        if min(hs) <= 0:
            raise SceneError(f"{where}.half_size: expected positive half sizes, got {list(hs)}")
        return Barrier("box", _floats(d["pos"], 3, f"{where}.pos"), half_size=hs, name=name, rgba=rgba)
    for k in ("pos", "radius", "half_height"):
        if k not in d:
            raise SceneError(f"{where}: a cylinder needs '{k}'")
    return Barrier(
        "cylinder",
        _floats(d["pos"], (2, 3), f"{where}.pos"),
        radius=_float(d["radius"], f"{where}.radius", positive=True),
        half_height=_float(d["half_height"], f"{where}.half_height", positive=True),
        name=name,
        rgba=rgba,
    )


def scene_from_dict(d: Any, source: str = "<dict>") -> Scene:
    """Validate a parsed scene mapping; errors name ``source`` and the offending key."""
    if not isinstance(d, dict):
        raise SceneError(f"{source}: a scene must be a mapping, got {type(d).__name__}")
    unknown = sorted(set(d) - SCENE_KEYS)
    if unknown:
        raise SceneError(f"{source}: unknown key(s) {unknown}; allowed: {sorted(SCENE_KEYS)}")
    name = d.get("name", Path(source).stem)
    if not isinstance(name, str):
        raise SceneError(f"{source}: 'name' must be a string, got {name!r}")
    barriers = d.get("barriers", [])
    if not isinstance(barriers, list):
        raise SceneError(f"{source}: 'barriers' must be a list, got {barriers!r}")
    remove = d.get("remove", [])
    if not isinstance(remove, list) or not all(isinstance(r, str) for r in remove):
        raise SceneError(f"{source}: 'remove' must be a list of obstacle names, got {remove!r}")
    waypoints = d.get("waypoints")
    if waypoints is not None:
        if not isinstance(waypoints, list) or not waypoints:
            raise SceneError(f"{source}: 'waypoints' must be a non-empty list of points, got {waypoints!r}")
        waypoints = tuple(
            _floats(w, (2, 3, 4), f"{source}: waypoints[{i}]") for i, w in enumerate(waypoints)
        )
    return Scene(
        name=name,
        barriers=tuple(_barrier(b, f"{source}: barriers[{i}]") for i, b in enumerate(barriers)),
        remove=tuple(remove),
        waypoints=waypoints,
        description=str(d.get("description", "")),
        source=source,
    )


def read_scene_file(path: str | Path) -> Scene:
    """Load a JSON (``.json``) or YAML (``.yaml``/``.yml``) scene file."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"scene file {path} does not exist")
    text = path.read_text()
    try:
        if path.suffix.lower() in (".yaml", ".yml"):
            import yaml

            data = yaml.safe_load(text)
        else:
            # parse_constant rejects NaN/Infinity literals, which json would otherwise accept.
            data = json.loads(text, parse_constant=lambda c: _reject_constant(c, path))
    except SceneError:
        raise
    except Exception as e:  # noqa: BLE001 - re-raised with the file name
        raise SceneError(f"{path}: cannot parse scene file: {e}") from e
    return scene_from_dict(data, source=str(path))


def _reject_constant(c: str, path: Path):
    raise SceneError(f"{path}: non-finite number {c} is not allowed in a scene file")


VALIDATION_SCENE = re.compile(r"^val[0-9]+$")  # names of shipped validation scenes: val1, val2, ...


def shipped_scene_path(env_name: str, index: int | str) -> Path:
    """Path of a scene file shipped with the package: ``("reach_around", 1)`` is test scene 1,
    ``("reach_around", "val1")`` validation scene 1."""
    stem = f"{env_name}_{index}" if isinstance(index, str) else f"{env_name}_scene{index}"
    p = resources.files("lerobot_pdp.envs") / "scenes" / f"{stem}.json"
    return Path(str(p))


def validation_scene_names(env_name: str) -> list[str]:
    """Names of the validation scenes ``env_name`` ships (``["val1", "val2", ...]``, numeric order)."""
    return sorted((n for n in _shipped_names(env_name) if VALIDATION_SCENE.match(n)), key=lambda n: int(n[3:]))


def scene_indices(env_name: str) -> list[int]:
    """The numbered scenes ``env_name`` ships (0 = training, then the test scenes), in order."""
    return sorted(int(n[5:]) for n in _shipped_names(env_name) if n.startswith("scene") and n[5:].isdigit())


def scenes_with_waypoints(env_name: str) -> list[str]:
    """The shipped scenes of ``env_name`` that carry way-points, as ``--scene`` names them (``"3"``, ``"val3"``)."""
    names = [n for n in _shipped_names(env_name) if "waypoints" in json.loads(shipped_scene_path(env_name, n).read_text())]
    named = sorted((n for n in names if VALIDATION_SCENE.match(n)), key=lambda n: int(n[3:]))
    return sorted((n[5:] for n in names if n.startswith("scene")), key=int) + named


def _shipped_names(env_name: str) -> list[str]:
    folder = resources.files("lerobot_pdp.envs") / "scenes"
    prefix = f"{env_name}_"
    return [f.name[len(prefix):-5] for f in folder.iterdir() if f.name.startswith(prefix) and f.name.endswith(".json")]


def load_scene(scene: int | str | Path | Scene | dict | None, env_name: str) -> Scene:
    """Resolve ``scene=`` as accepted by every env: an int 0-3, a validation scene name (``"val1"``), a path,
    a mapping or a :class:`Scene`. ``env_name``: the env's scene key (``reach_around``) or its CLI name
    (``reach-around``)."""
    env_name = env_name.replace("-", "_")  # the files are named by the scene key
    if scene is None:
        scene = 0
    if isinstance(scene, Scene):
        return scene
    if isinstance(scene, dict):
        return scene_from_dict(scene)
    if isinstance(scene, str) and scene.strip().lstrip("-").isdigit():
        scene = int(scene)
    if isinstance(scene, (int, np.integer)) and not isinstance(scene, bool):
        path = shipped_scene_path(env_name, int(scene))
        if not path.is_file():
            raise SceneError(f"env {env_name!r} ships no scene {int(scene)} (looked for {path}); it ships scenes "
                             f"{scene_indices(env_name)} and {validation_scene_names(env_name)}")
        return read_scene_file(path)
    if isinstance(scene, str) and VALIDATION_SCENE.match(scene.strip()):
        path = shipped_scene_path(env_name, scene.strip())
        if not path.is_file():
            raise SceneError(f"env {env_name!r} ships no validation scene {scene.strip()!r} (looked for {path}); "
                             f"it ships {validation_scene_names(env_name)}")
        return read_scene_file(path)
    if isinstance(scene, (str, Path)):
        return read_scene_file(scene)
    raise SceneError(f"scene must be an int, a path, a mapping or a Scene, got {type(scene).__name__}")
