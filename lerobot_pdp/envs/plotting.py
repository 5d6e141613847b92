"""Matplotlib figures of demonstrations and rollouts over a scene (Agg backend, no display needed).

Reusable pieces: :func:`draw_scene` draws an env's obstacles and a scene's barriers projected onto a plane,
:func:`draw_waypoints` a route's way-points in order, :func:`plot_trajectories` draws traces coloured by mode,
:func:`plot_dataset` combines them for a dataset written by :func:`lerobot_pdp.envs.recording.make_dataset`. Figure code for rollouts per method should
call the first two so every figure of the suite looks the same.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Circle, Rectangle  # noqa: E402

from ..atomic import write_figure_atomic  # noqa: E402
from ..console import counted  # noqa: E402
from .scene import Barrier, load_scene  # noqa: E402
from .suite import NOVEL, SuiteEnv, get_suite_env, parse_task_mode  # noqa: E402

AXES = {"x": 0, "y": 1, "z": 2}
OBSTACLE_COLOR = "#5a5a66"
BARRIER_COLOR = "#d9772b"
WAYPOINT_COLOR = "#7b2cbf"
VIEW_TITLES = {"xy": "top view (x-y)", "yz": "side view (y-z)", "xz": "front view (x-z)"}


def _plane_axes(plane: str) -> tuple[int, int]:
    if len(plane) != 2 or any(c not in AXES for c in plane) or plane[0] == plane[1]:
        raise ValueError(f"plane must be two distinct letters of 'xyz' such as 'xy' or 'xz', got {plane!r}")
    return AXES[plane[0]], AXES[plane[1]]


def mode_color(mode: int | str, n_modes: int):
    """A stable colour per mode id (tab10 / tab20 / hsv by count); black for novel."""
    if mode == NOVEL or not isinstance(mode, (int, np.integer)):
        return (0.0, 0.0, 0.0, 1.0)
    if n_modes <= 10:
        return plt.get_cmap("tab10")(int(mode) % 10)
    if n_modes <= 20:
        return plt.get_cmap("tab20")(int(mode) % 20)
    return plt.get_cmap("gist_rainbow")(int(mode) / max(n_modes - 1, 1))


def _patch(b: Barrier, i: int, j: int, default_z: float, color: str, alpha: float):
    c = b.center3(default_z)
    if b.shape == "box":
        hi, hj = b.half_size[i], b.half_size[j]
        return Rectangle((c[i] - hi, c[j] - hj), 2 * hi, 2 * hj, color=color, alpha=alpha, lw=0)
    if {i, j} == {0, 1}:
        return Circle((c[i], c[j]), b.radius, color=color, alpha=alpha, lw=0)
    half = (b.radius, b.radius, b.half_height)
    return Rectangle((c[i] - half[i], c[j] - half[j]), 2 * half[i], 2 * half[j], color=color, alpha=alpha, lw=0)


def draw_scene(ax: Axes, env_name: str, scene: Any = 0, plane: str = "xy") -> None:
    """Draw ``env_name``'s built-in obstacles (grey) and ``scene``'s barriers (orange) onto ``ax``.

    Env modules may expose ``static_primitives(scene)`` (obstacles left in the scene) and ``LANDMARKS``
    (name -> point, e.g. start and goal); without them only the scene's barriers are drawn. For 2-D envs
    only the ``"xy"`` plane is meaningful.
    """
    suite = get_suite_env(env_name)
    i, j = _plane_axes(plane)
    impl = suite.impl()
    sc = load_scene(scene, suite.scene_key)
    default_z = float(getattr(impl, "PLANE_Z", 0.0))  # height of 2-D cylinders; irrelevant to "xy"
    prims = impl.static_primitives(sc) if hasattr(impl, "static_primitives") else ()
    for b in prims:
        ax.add_patch(_patch(b, i, j, default_z, OBSTACLE_COLOR, 0.85))
    for b in sc.barriers:
        ax.add_patch(_patch(b, i, j, default_z, BARRIER_COLOR, 0.45))
    for name, p in getattr(impl, "LANDMARKS", {}).items():
        if len(p) > max(i, j):
            ax.plot(p[i], p[j], marker="*" if name == "goal" else "o", color="green" if name == "goal" else "k",
                    ms=10 if name == "goal" else 6, zorder=5, ls="none")
    finish = suite.extra.get("finish_y")
    if finish is not None and 1 in (i, j):
        (ax.axhline if j == 1 else ax.axvline)(finish, color="green", ls="--", lw=1)
    ax.set_xlabel(f"{plane[0]} [m]")
    ax.set_ylabel(f"{plane[1]} [m]")
    ax.set_aspect("equal", adjustable="datalim")


def draw_waypoints(ax: Axes, waypoints: Any, plane: str = "xy", radius: float | None = None) -> Line2D | None:
    """Draw way-points ([K, D]: one coordinate per trace dim, x y (z), as ``make-dataset --waypoints`` and
    ``lerobot-pdp search --waypoints`` take them) on ``plane``: numbered in order and joined by a dashed line, each
    with its pass ``radius`` when given. Returns the legend handle, or None when the points lack the plane's dims."""
    i, j = _plane_axes(plane)
    w = np.asarray(waypoints, dtype=float)
    if w.ndim != 2 or w.shape[1] <= max(i, j):
        return None
    ax.plot(w[:, i], w[:, j], ls="--", lw=1.0, color=WAYPOINT_COLOR, alpha=0.8, zorder=6)
    ax.plot(w[:, i], w[:, j], marker="D", ms=5, ls="none", color=WAYPOINT_COLOR, zorder=7)
    for k, p in enumerate(w):
        ax.annotate(str(k + 1), (p[i], p[j]), textcoords="offset points", xytext=(4, 4), fontsize=7,
                    color=WAYPOINT_COLOR, zorder=7)
        if radius is not None:
            ax.add_patch(Circle((p[i], p[j]), radius, fill=False, ls=":", lw=0.8, color=WAYPOINT_COLOR, zorder=6))
    label = "way-points" + (f" (pass within {radius:g} m)" if radius is not None else "")
    return Line2D([], [], color=WAYPOINT_COLOR, marker="D", ms=5, ls="--", lw=1.0, label=label)


def plot_trajectories(
    ax: Axes,
    trajectories: Sequence[np.ndarray],
    modes: Sequence[int | str] | None = None,
    mode_names: Sequence[str] | None = None,
    plane: str = "xy",
    trace_dims: Sequence[int] = (0, 1, 2),
    alpha: float = 0.7,
    lw: float = 1.0,
) -> list[Line2D]:
    """Draw each trajectory (rows of ``observation.state``) projected on ``plane``, coloured by mode.

    ``trace_dims`` maps x/y/z to state columns (the SuiteEnv's ``trace_dims``). Returns legend handles,
    one per distinct mode, labelled with ``mode_names`` when given.
    """
    i, j = _plane_axes(plane)
    if max(i, j) >= len(trace_dims):
        raise ValueError(f"plane {plane!r} needs {max(i, j) + 1} trace dims, got {tuple(trace_dims)}")
    ci, cj = trace_dims[i], trace_dims[j]
    n_modes = len(mode_names) if mode_names else 10
    modes = list(modes) if modes is not None else [NOVEL] * len(trajectories)
    if len(modes) != len(trajectories):
        raise ValueError(f"got {len(trajectories)} trajectories but {len(modes)} mode labels")
    seen: dict[Any, Line2D] = {}
    for traj, m in zip(trajectories, modes, strict=True):
        t = np.asarray(traj)
        (line,) = ax.plot(t[:, ci], t[:, cj], color=mode_color(m, n_modes), alpha=alpha, lw=lw)
        if m not in seen:
            if m == NOVEL or mode_names is None or not isinstance(m, (int, np.integer)):
                label = str(m)
            else:
                label = f"{int(m)}: {mode_names[int(m)]}"
            seen[m] = Line2D([], [], color=line.get_color(), lw=2, label=label)
    ids = sorted(k for k in seen if isinstance(k, (int, np.integer)))
    others = sorted(str(k) for k in seen if not isinstance(k, (int, np.integer)))
    return [seen[k] for k in ids] + [seen[k] for k in others]


def load_episodes(dataset_dir: str | Path) -> tuple[list[np.ndarray], list[int | str]]:
    """``observation.state`` rows per episode and each episode's mode (parsed from its task string)."""
    import pandas as pd

    from ..episodes import check_data_files, recording_info

    root = Path(dataset_dir)
    files = sorted((root / "data").glob("*/*.parquet"))
    if not files:
        raise FileNotFoundError(f"{root} has no data/*/*.parquet: not a LeRobotDataset v3 directory")
    recording_info(root)  # a missing or damaged meta/info.json, named
    check_data_files(root, files)
    df = pd.concat([pd.read_parquet(f, columns=["observation.state", "episode_index", "frame_index", "task_index"])
                    for f in files])
    tasks = pd.read_parquet(root / "meta" / "tasks.parquet")
    task_of = {int(r.task_index): str(idx) for idx, r in tasks.iterrows()}
    trajs, modes = [], []
    for _, ep in df.sort_values(["episode_index", "frame_index"]).groupby("episode_index", sort=True):
        trajs.append(np.stack(ep["observation.state"].to_numpy()))
        label = parse_task_mode(task_of.get(int(ep["task_index"].iloc[0]), ""))
        modes.append(label if label is not None else NOVEL)
    return trajs, modes


def scene_views(suite: SuiteEnv) -> tuple[str, ...]:
    """Planes drawn for an env: top view for 2-D, plus side and front views for 3-D traces."""
    return ("xy",) if len(suite.trace_dims) < 3 else ("xy", "yz", "xz")


def plot_dataset(
    dataset_dir: str | Path, out_png: str | Path, scene: Any = None, env: str | None = None, waypoints: Any = None
) -> Path:
    """Plot a dataset's demonstrations coloured by mode over its scene; writes ``out_png``.

    ``env`` and ``scene`` default to the generation record (``meta/pdp_suite.json``) written by
    ``make_dataset``; pass them for datasets made otherwise. ``waypoints`` (a JSON/YAML file, ``"scene"`` for the
    drawn scene's own, or a list of points) are drawn in order; by default the ones the dataset was recorded
    along, if any.
    """
    from .recording import check_waypoints, read_dataset_meta, resolve_waypoints

    if not (Path(dataset_dir) / "meta" / "info.json").is_file():
        raise FileNotFoundError(f"{dataset_dir} is not a LeRobotDataset folder (no meta/info.json)")
    meta = read_dataset_meta(dataset_dir) or {}
    if env is not None and meta.get("env") not in (None, env):
        raise ValueError(f"{dataset_dir} was recorded in {meta['env']!r} (meta/pdp_suite.json), not {env!r}: its "
                         "demonstrations would be drawn over another env's scene and modes")
    env = env or meta.get("env")
    if env is None:
        raise ValueError(f"{dataset_dir}: no meta/pdp_suite.json says which env it was recorded in; give it "
                         "(--env, or env= from Python; e.g. 'reach-around')")
    suite = get_suite_env(env)
    if scene is None:
        scene = meta.get("scene", 0)
    if waypoints is not None:
        source = waypoints if isinstance(waypoints, (str, Path)) else "waypoints"
        waypoints = resolve_waypoints(waypoints, scene, suite)
        check_waypoints(suite, waypoints, source)
    else:
        waypoints = meta.get("waypoints")  # recorded along them (make-dataset --waypoints)
    trajs, modes = load_episodes(dataset_dir)
    views = scene_views(suite)
    fig, axes = plt.subplots(1, len(views), figsize=(5.0 * len(views), 5.0), squeeze=False)
    handles: list[Line2D] = []
    for ax, plane in zip(axes[0], views, strict=True):
        draw_scene(ax, suite.name, scene, plane)
        handles = plot_trajectories(ax, trajs, modes, suite.mode_names, plane, suite.trace_dims)
        route = draw_waypoints(ax, waypoints, plane) if waypoints is not None else None
        handles += [route] if route is not None else []
        ax.set_title(VIEW_TITLES.get(plane, plane))
    sc_name = load_scene(scene, suite.scene_key).name
    fig.suptitle(f"{suite.name}: {counted(len(trajs), 'demonstration')}, {sc_name}")
    ncol = 1 if len(handles) <= 12 else 2
    fig.legend(handles=handles, loc="center left", bbox_to_anchor=(1.0, 0.5), ncol=ncol, fontsize=8,
               title="mode")
    fig.tight_layout()
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    write_figure_atomic(fig, out_png, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return out_png
