"""Camera observations of the suite's scenes: a numpy pinhole ray caster, no OpenGL.

Why not MuJoCo's renderer: it needs a GL context (EGL here, ~40 ms per frame in software) and its pixels
differ between GPU and software drivers, so a dataset's images would depend on the machine that made it.
Every scene of the point-mass and pick-place envs is built from axis-aligned boxes, upright cylinders,
spheres and a floor, which a ray caster renders exactly (true perspective, occlusion, per-face shading):
the static scene is cast once per camera, and each frame only re-casts the moving bodies (well under a
millisecond at 96x96), with bit-identical pixels on every machine.

An env's observation then carries ``obs["pixels"] = {camera name: uint8 (H, W, 3)}``, the layout LeRobot's
``preprocess_observation`` maps to ``observation.images.<name>``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

DEFAULT_IMAGE_SIZE = 96
BACKGROUND = (0.80, 0.86, 0.92)  # sky
LIGHT = np.array([0.4, -0.6, 1.0]) / np.linalg.norm([0.4, -0.6, 1.0])  # fixed world light: faces shade apart
AMBIENT = 0.45
_EPS = 1e-9


@dataclass(frozen=True)
class CameraSpec:
    """A fixed pinhole camera: position, point looked at, image-up direction and vertical field of view."""

    name: str
    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    fovy: float = 45.0  # degrees


@dataclass(frozen=True)
class Solid:
    """One renderable primitive.

    ``size``: box half-sizes (3); cylinder (radius, half height), axis along z; sphere (radius,);
    floor: unused (an infinite horizontal plane at ``center[2]``). ``rgb`` in [0, 1].
    """

    shape: str
    center: tuple[float, float, float]
    size: tuple[float, ...]
    rgb: tuple[float, float, float]


def parse_image_size(value: int | str | Sequence[int]) -> tuple[int, int]:
    """``96``, ``"96"``, ``"64x96"`` or ``(64, 96)`` -> (height, width); both at least 8 pixels."""
    if isinstance(value, str):
        parts = value.lower().replace(",", "x").split("x")
        try:
            hw = [int(p) for p in parts if p.strip()]
        except ValueError as e:
            raise ValueError(f"image size must be N or HxW (e.g. 96 or 64x96), got {value!r}") from e
    elif isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        hw = [int(value)]
    else:
        hw = [int(v) for v in value]
    if len(hw) == 1:
        hw = hw * 2
    if len(hw) != 2 or min(hw) < 8:
        raise ValueError(f"image size must be N or HxW with sides >= 8 pixels, got {value!r}")
    return hw[0], hw[1]


def resolve_cameras(camera: str | Sequence[str] | None, specs: Sequence[CameraSpec], env: str) -> tuple[str, ...]:
    """Camera names from ``"top"``, ``"top,front"`` or a list; None or empty = no camera.

    Raises ValueError naming the env's valid cameras for an unknown one.
    """
    if camera is None:
        return ()
    names = [c.strip() for c in camera.split(",")] if isinstance(camera, str) else [str(c).strip() for c in camera]
    names = [n for n in names if n]
    valid = [s.name for s in specs]
    unknown = [n for n in names if n not in valid]
    if unknown:
        have = ", ".join(valid) if valid else "none"
        raise ValueError(f"{env}: unknown camera {unknown[0]!r}; valid cameras: {have}")
    if len(set(names)) != len(names):
        raise ValueError(f"{env}: camera names repeat in {camera!r}")
    return tuple(names)


def pixels_space(cameras: Sequence[str], size: tuple[int, int]) -> gym.spaces.Dict:
    """Observation space of ``obs["pixels"]``: one uint8 (H, W, 3) box per camera."""
    h, w = size
    return gym.spaces.Dict({n: gym.spaces.Box(0, 255, shape=(h, w, 3), dtype=np.uint8) for n in cameras})


# ---- ray-primitive intersections (vectorised over rays; t = inf where missed) --------------------------


def _hit_box(o: np.ndarray, d: np.ndarray, c: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    safe = np.where(np.abs(d) < 1e-12, 1e-12, d)
    t1 = (c - h - o) / safe
    t2 = (c + h - o) / safe
    tn, tf = np.minimum(t1, t2), np.maximum(t1, t2)
    tnear, tfar = tn.max(axis=1), tf.min(axis=1)
    hit = (tnear <= tfar) & (tnear > _EPS)
    axis = tn.argmax(axis=1)
    rows = np.arange(len(d))
    n = np.zeros_like(d)
    n[rows, axis] = -np.sign(safe[rows, axis])
    return np.where(hit, tnear, np.inf), n


def _hit_cylinder(o: np.ndarray, d: np.ndarray, c: np.ndarray, r: float, hh: float) -> tuple[np.ndarray, np.ndarray]:
    ox, oy = o[0] - c[0], o[1] - c[1]
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = 2.0 * (ox * d[:, 0] + oy * d[:, 1])
    cc = ox * ox + oy * oy - r * r
    disc = b * b - 4.0 * a * cc
    with np.errstate(invalid="ignore", divide="ignore"):
        ts = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * np.maximum(a, 1e-12))
    zs = o[2] + ts * d[:, 2]
    side = (disc >= 0) & (a > 1e-12) & (ts > _EPS) & (np.abs(zs - c[2]) <= hh)
    t = np.where(side, ts, np.inf)
    n = np.stack([(ox + ts * d[:, 0]) / r, (oy + ts * d[:, 1]) / r, np.zeros_like(ts)], axis=1)
    safe_dz = np.where(np.abs(d[:, 2]) < 1e-12, 1e-12, d[:, 2])
    for sign in (1.0, -1.0):
        tc = (c[2] + sign * hh - o[2]) / safe_dz
        inside = (ox + tc * d[:, 0]) ** 2 + (oy + tc * d[:, 1]) ** 2 <= r * r
        cap = inside & (tc > _EPS) & (tc < t)
        t = np.where(cap, tc, t)
        n[cap] = (0.0, 0.0, sign)
    return t, n


def _hit_sphere(o: np.ndarray, d: np.ndarray, c: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
    oc = o - c
    b = d @ oc  # rays are unit length
    disc = b * b - (oc @ oc - r * r)
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    hit = (disc >= 0) & (t > _EPS)
    t = np.where(hit, t, np.inf)
    n = (o + np.where(hit, t, 0.0)[:, None] * d - c) / r
    return t, n


def _hit_floor(o: np.ndarray, d: np.ndarray, z: float) -> tuple[np.ndarray, np.ndarray]:
    safe_dz = np.where(np.abs(d[:, 2]) < 1e-12, 1e-12, d[:, 2])
    t = (z - o[2]) / safe_dz
    t = np.where(t > _EPS, t, np.inf)
    n = np.zeros_like(d)
    n[:, 2] = 1.0 if o[2] >= z else -1.0
    return t, n


def _intersect(o: np.ndarray, d: np.ndarray, s: Solid) -> tuple[np.ndarray, np.ndarray]:
    c = np.asarray(s.center, dtype=float)
    if s.shape == "box":
        return _hit_box(o, d, c, np.asarray(s.size, dtype=float))
    if s.shape == "cylinder":
        return _hit_cylinder(o, d, c, float(s.size[0]), float(s.size[1]))
    if s.shape == "sphere":
        return _hit_sphere(o, d, c, float(s.size[0]))
    if s.shape == "floor":
        return _hit_floor(o, d, float(c[2]))
    raise ValueError(f"unknown solid shape {s.shape!r}")


class RayCaster:
    """Renders one :class:`CameraSpec` of a static scene plus moving solids to uint8 (H, W, 3) images.

    The static scene is cast and averaged once; a frame re-casts only the rays that can meet a moving solid
    (those hitting its bounding sphere) and re-averages only their pixels, so the cost follows the moving
    bodies' footprint, not the image size.
    """

    def __init__(self, spec: CameraSpec, size: tuple[int, int], static: Sequence[Solid], supersample: int = 2):
        """``supersample``: rays per pixel side, averaged, so a body smaller than a pixel (the end effector at
        32x32) still tints its pixel instead of vanishing between rays."""
        h, w = size
        k = int(supersample)
        eye = np.asarray(spec.eye, dtype=float)
        fwd = np.asarray(spec.target, dtype=float) - eye
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, np.asarray(spec.up, dtype=float))
        if np.linalg.norm(right) < 1e-9:
            raise ValueError(f"camera {spec.name!r}: 'up' is parallel to the viewing direction")
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        tan = math.tan(math.radians(spec.fovy) / 2.0)
        ys = (1.0 - 2.0 * (np.arange(h * k) + 0.5) / (h * k)) * tan
        xs = (2.0 * (np.arange(w * k) + 0.5) / (w * k) - 1.0) * tan * (w / h)
        d = fwd + xs[None, :, None] * right + ys[:, None, None] * up
        self.name = spec.name
        self.size = (h, w)
        self._eye = eye
        self._dirs = (d / np.linalg.norm(d, axis=-1, keepdims=True)).reshape(-1, 3)
        rows, cols = np.divmod(np.arange(h * k * w * k), w * k)
        self._pixel_of_ray = (rows // k) * w + cols // k
        self._rays_of_pixel = np.argsort(self._pixel_of_ray, kind="stable").reshape(h * w, k * k)
        self._depth = np.full(len(self._dirs), np.inf)
        self._rgb = np.tile(np.asarray(BACKGROUND, dtype=float), (len(self._dirs), 1))
        self._cast(static, self._dirs, self._depth, self._rgb)
        self._scratch = self._rgb.copy()
        self._image = _to_uint8(self._rgb[self._rays_of_pixel].mean(axis=1))  # (h * w, 3)

    def _cast(self, solids: Sequence[Solid], dirs: np.ndarray, depth: np.ndarray, rgb: np.ndarray) -> None:
        for s in solids:
            t, n = _intersect(self._eye, dirs, s)
            front = t < depth
            if not front.any():
                continue
            shade = AMBIENT + (1.0 - AMBIENT) * np.clip(n[front] @ LIGHT, 0.0, 1.0)
            depth[front] = t[front]
            rgb[front] = np.asarray(s.rgb, dtype=float)[None, :] * shade[:, None]

    def _rays_near(self, s: Solid) -> np.ndarray:
        """Indices of rays that meet the bounding sphere of ``s`` (a superset of the rays that hit it)."""
        c = np.asarray(s.center, dtype=float)
        if s.shape == "box":
            r = float(np.linalg.norm(s.size))
        elif s.shape == "cylinder":
            r = math.hypot(s.size[0], s.size[1])
        elif s.shape == "sphere":
            r = float(s.size[0])
        else:
            return np.arange(len(self._dirs))
        oc = self._eye - c
        b = self._dirs @ oc
        return np.flatnonzero(b * b - (oc @ oc - r * r) >= 0.0)

    def render(self, moving: Sequence[Solid] = ()) -> np.ndarray:
        """The static scene with ``moving`` solids cast over it (occlusion both ways)."""
        h, w = self.size
        image = self._image.copy()
        if moving:
            idx = np.unique(np.concatenate([self._rays_near(s) for s in moving]))
            if len(idx):
                depth, rgb = self._depth[idx].copy(), self._rgb[idx].copy()
                self._cast(moving, self._dirs[idx], depth, rgb)
                pix = np.unique(self._pixel_of_ray[idx])
                self._scratch[idx] = rgb
                image[pix] = _to_uint8(self._scratch[self._rays_of_pixel[pix]].mean(axis=1))
                self._scratch[idx] = self._rgb[idx]
        return image.reshape(h, w, 3)


def _to_uint8(rgb: np.ndarray) -> np.ndarray:
    return np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)


def barrier_solid(b, default_z: float, rgb: Sequence[float]) -> Solid:
    """A scene :class:`~lerobot_pdp.envs.scene.Barrier` as a :class:`Solid` (its own rgba wins over ``rgb``).

    Alpha is dropped: barriers are solid to the camera as they are to the end effector.
    """
    col = tuple(float(v) for v in (b.rgba[:3] if b.rgba else rgb))
    c = tuple(float(v) for v in b.center3(default_z))
    if b.shape == "box":
        return Solid("box", c, tuple(float(v) for v in b.half_size), col)
    return Solid("cylinder", c, (float(b.radius), float(b.half_height)), col)
