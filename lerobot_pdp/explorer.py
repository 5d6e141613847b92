"""The explorer: a local web app for looking into a PDP checkpoint before steering it (``lerobot-pdp explore``).

The latent map says what behaviors the data holds; a number does not say what the policy does under a latent
in a scene it never saw. Here a person clicks a point of the map and sees the policy's rollouts from it in the
chosen scene (success and collisions), sweeps between two modes, fits a demonstration and sees where its latent
lies (and how well it fits), asks for the success landscape over the latent box, and keeps the latent they like
as an adapted checkpoint. Without an env (a real robot's checkpoint) the rollouts give way to the decoder's
view: the action chunks the denoiser samples at the latent from observations of a recorded episode.

Every panel is one method of :class:`Explorer`, plain Python that the tests call directly; :func:`build_app`
wires them into a Gradio app (an optional dependency, imported only there).
"""

from __future__ import annotations

import datetime
import hashlib
import io
import json
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch
from matplotlib.figure import Figure
from PIL import Image

from .adapted import load_base_policy, write_adapted_checkpoint
from .atomic import write_text_atomic
from .candidate_rollouts import CandidateRollouts, check_env_features, env_camera_kwargs
from .checkpoint import ADAPTATION_INFO, card_section
from .checkpoint_files import read_config_json, require_checkpoint_files, require_new_folder
from .demonstration import check_recording, recording_info
from .latent_map import LatentMap, groups_k, latent_map_figure
from .outcome_scores import Outcome
from .steer_requests import mode_key
from .steering_state import Steering

GRADIO_HINT = 'the explorer needs Gradio: pip install "lerobot_policy_pdp[explore]" (in a clone: pip install -e ".[explore]")'
MAP_DPI = 80  # the map's pixels: a click's coordinates are read in them
MAP_WIDEN_SPANS = 2.0  # a mark off the training latents widens the map's view by at most this many spans each side
LANDSCAPE_MAX_ROLLOUTS = 1024  # rollouts one landscape request may run (grid^2 x rollouts); Python: limit=None
LANDSCAPE_VERSION = 1  # bump when what a cached landscape holds changes
DECODER_MAX_DIMS = 8  # action dimensions the decoder's view draws, one row each
WINDOW_CACHE_SIZE = 8  # recorded episodes the decoder's view keeps encoded (clicks near other modes meet others)
Progress = Callable[[float, str], None]  # fraction done, what is running (gr.Progress is one)


@dataclass
class Selection:
    """The latent the panels act on, what chose it, and what an adapted checkpoint records of it."""

    z: list[float]
    source: str
    provenance: dict[str, Any] = field(default_factory=dict)


@dataclass
class MapImage:
    """The latent map as pixels, with the scatter's pixel box and data limits: a click's pixel -> map point."""

    image: np.ndarray  # [H, W, 3] uint8
    box: tuple[float, float, float, float]  # scatter axes in pixels from the top left: x0, y0, x1, y1
    xlim: tuple[float, float]
    ylim: tuple[float, float]

    def to_map(self, px: float, py: float) -> np.ndarray:
        """The map point under pixel (``px``, ``py``); outside the scatter's axes a ValueError."""
        x0, y0, x1, y1 = self.box
        if not (x0 <= px <= x1 and y0 <= py <= y1):
            raise ValueError(f"pixel ({px:.0f}, {py:.0f}) is outside the latent map's axes (x {x0:.0f}-{x1:.0f}, "
                             f"y {y0:.0f}-{y1:.0f} pixels): click on the scatter of training latents")
        fx, fy = (px - x0) / (x1 - x0), (y1 - py) / (y1 - y0)
        return np.array([self.xlim[0] + fx * (self.xlim[1] - self.xlim[0]),
                         self.ylim[0] + fy * (self.ylim[1] - self.ylim[0])])

    def to_pixel(self, xy: np.ndarray) -> tuple[float, float]:
        """The pixel of map point ``xy`` (the inverse of :meth:`to_map`)."""
        x0, y0, x1, y1 = self.box
        fx = (xy[0] - self.xlim[0]) / (self.xlim[1] - self.xlim[0])
        fy = (xy[1] - self.ylim[0]) / (self.ylim[1] - self.ylim[0])
        return x0 + fx * (x1 - x0), y1 - fy * (y1 - y0)


@dataclass
class RolloutView:
    """Rollouts from one latent in the explorer's scene, drawn over it."""

    image: np.ndarray
    outcomes: list[Outcome]
    modes: list[int | str]  # the route each rollout took (the env's classifier; "novel" for none)

    @property
    def successes(self) -> int:
        return sum(o.success for o in self.outcomes)

    @property
    def collisions(self) -> int:
        return sum(bool(o.info.get("collided", False)) for o in self.outcomes)

    def summary(self) -> str:
        n = len(self.outcomes)
        return f"success {self.successes}/{n} ({100 * self.successes / n:.0f} %), collisions {self.collisions}/{n}"


@dataclass
class Landscape:
    """Success (and collision) rate on a grid over the latent map's box, and where it is cached."""

    xs: np.ndarray  # [grid] map x
    ys: np.ndarray  # [grid] map y
    success: np.ndarray  # [grid (y), grid (x)] rate
    collision: np.ndarray
    cache: Path
    from_cache: bool


@dataclass
class FitMark:
    """A demonstration's fitted latent and its error ratio (fit error / the training demonstrations')."""

    z: list[float]
    error_ratio: float | None
    label: str


class Explorer:
    """One checkpoint, and optionally a suite env and scene to roll it out in; each method is one panel."""

    def __init__(self, checkpoint: str | Path, env: str | None = None, scene: str | int = "0",
                 rollouts: int = 8, max_steps: int | None = None, cache_dir: str | Path | None = None,
                 dataset: str | Path | None = None, device: str = "cpu", seed: int = 0, k: int | None = None):
        self.checkpoint = Path(checkpoint)
        check_checkpoint_folder(self.checkpoint)
        if dataset is not None:  # a bad argument is refused now, not at the first click
            _check_episode(dataset, 0)
        self.policy = load_base_policy(self.checkpoint, device)
        if dataset is not None:  # ... also a recording the checkpoint cannot read (another camera, no state)
            cfg = self.policy.config
            check_recording(dataset, 0, {k: tuple(ft.shape) for k, ft in cfg.condition_features.items()},
                            fps=cfg.dataset_fps, names=cfg.dataset_feature_names)
        self.rollouts, self.seed, self.device = _positive("rollouts", rollouts), seed, device
        self.cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
        self._training_data = _training_dataset(self.checkpoint)
        self.dataset = Path(dataset) if dataset is not None else self._training_data
        self._lock = threading.RLock()  # Gradio serves requests from threads; the policy acts for one at a time
        self._window_cache: dict[tuple, Any] = {}  # (recording, episode, its info.json mtime) -> its windows
        self.suite = self.scene = None
        self.max_steps = max_steps
        if env is not None:
            self._set_env(env, scene, max_steps)
        k = groups_k(self.policy, None if self.policy.model.bank.labelled() else k)  # None: found (or labels)
        self.map: LatentMap = latent_map_figure(self.policy, k, title=f"{self.checkpoint.name}: latent map")
        self.map.axes.set_title(self.map.axes.get_title() + "\nclick a point: the policy's behavior there", fontsize=9)
        self.modes = self.policy.mode_latents(k)
        self.map.figure.set_dpi(MAP_DPI)
        self.map.figure.canvas.draw()
        self._limits = (self.map.axes.get_xlim(), self.map.axes.get_ylim())  # the map stays put between clicks

    # ------------------------------------------------------------------ setup

    def _set_env(self, env: str, scene: str | int, max_steps: int | None) -> None:
        import gymnasium as gym

        import lerobot_pdp.envs as envs
        from lerobot_pdp.envs.scene import load_scene

        self.suite = envs.get_suite_env(env)
        self.scene = load_scene(str(scene), self.suite.scene_key)
        self.max_steps = _positive("max_steps", max_steps if max_steps is not None else self.suite.max_episode_steps)
        kwargs = env_camera_kwargs(self.policy.config)
        self.env_factory = lambda: gym.make(self.suite.gym_id, scene=self.scene, max_episode_steps=self.max_steps,
                                            disable_env_checker=True, **kwargs)
        probe = None
        try:
            probe = self.env_factory()  # a camera the env lacks: the checkpoint is another env's, said so
            check_env_features(self.policy.config, probe)
        except ValueError as e:
            raise ValueError(f"--env {self.suite.name} does not match checkpoint {self.checkpoint}: {e}") from e
        finally:
            if probe is not None:
                probe.close()
        self.processors = self._processors()

    def _processors(self) -> tuple:
        """The checkpoint's saved processors, as ``lerobot-eval`` loads them (else built from its statistics)."""
        if (self.checkpoint / "policy_preprocessor.json").is_file():
            from lerobot.policies.factory import make_pre_post_processors

            return make_pre_post_processors(self.policy.config, pretrained_path=str(self.checkpoint),
                                            preprocessor_overrides={"device_processor": {"device": self.device}})
        from .processor_pdp import make_pdp_pre_post_processors

        return make_pdp_pre_post_processors(self.policy.config, self.policy.stats.as_dict())

    @property
    def has_env(self) -> bool:
        return self.suite is not None

    @property
    def latent_dim(self) -> int:
        return int(self.policy.config.latent_dim)

    def describe(self) -> str:
        """One paragraph: the checkpoint, its modes, and where rollouts run."""
        names = self.modes.names
        modes = ", ".join(f"{m}" + (f" ({names[m]})" if names.get(m) else "") for m in sorted(self.modes))
        where = (f"rollouts in **{self.suite.name}**, {self.scene.name} ({self.rollouts} per latent, "
                 f"{self.max_steps} steps)" if self.has_env else
                 "no env: the decoder's view of a latent (action chunks it samples from a recorded episode)")
        kind = "discovered modes" if self.modes.discovered else "modes"
        return (f"**{self.checkpoint.name}**: latent dim {self.latent_dim}, {len(self.policy.behavior_table()['z'])} "
                f"training behaviors, {kind} {modes}; {where}.")

    def mode_choices(self) -> list[str]:
        names = self.modes.names
        return [f"{m}: {names[m]}" if names.get(m) else str(m) for m in sorted(self.modes)]

    # ------------------------------------------------------------------ the map

    def latent(self, z: Any) -> np.ndarray:
        """``z`` as a checked latent [d_z] (a list, array, or text of numbers separated by commas or spaces)."""
        if isinstance(z, str):
            try:
                z = [float(v) for v in z.replace(",", " ").replace("[", " ").replace("]", " ").split()]
            except ValueError as e:
                raise ValueError(f"latent {z!r}: expected {self.latent_dim} numbers separated by commas") from e
        z = np.asarray(z, dtype=float).reshape(-1)
        if z.shape != (self.latent_dim,) or not np.isfinite(z).all():
            raise ValueError(f"latent {z.tolist()}: expected {self.latent_dim} finite numbers (the checkpoint's "
                             "latent_dim)")
        return z

    def far_note(self, z: Any) -> str:
        """A warning when ``z`` lies far outside the training latents (``set_latent``'s rule), else ''."""
        far = self.policy.latent_outlier(torch.as_tensor(self.latent(z), dtype=torch.float32)[None])
        return "" if far is None else (f" (far outside the training latents: {far[0]:.3g} spreads from the nearest; "
                                       "the policy was never trained there)")

    def render_map(self, selected: Selection | None = None, fit: FitMark | None = None,
                   path: list[list[float]] | None = None) -> MapImage:
        """The latent map with the selected latent (star), a fitted latent with its error ratio (diamond) and an
        interpolation path (dashed) marked; the marks are removed again, the base map is drawn once."""
        ax, proj = self.map.axes, self.map.projection
        with self._lock:
            artists = []
            if path is not None:
                xy = proj.to_map(np.asarray(path))
                artists += ax.plot(xy[:, 0], xy[:, 1], "k--", lw=1.2, zorder=6)
            if fit is not None:
                xy = proj.to_map(self.latent(fit.z))[0]
                ratio = "n/a" if fit.error_ratio is None else f"{fit.error_ratio:.2f}"
                artists.append(ax.scatter(*xy, marker="D", s=90, color="white", edgecolor="k", lw=1.5, zorder=7))
                artists.append(ax.annotate(f"{fit.label}\nerror ratio {ratio}", xy, xytext=(8, -18),
                                           textcoords="offset points", fontsize=8, zorder=8))
            star = None
            if selected is not None:
                star = proj.to_map(self.latent(selected.z))[0]
                # an outline: the training points under the selection stay visible
                artists.append(ax.scatter(*star, marker="*", s=260, facecolor="none", edgecolor="darkgoldenrod",
                                          lw=1.8, zorder=9))
            marked = [a.get_offsets() if hasattr(a, "get_offsets") else np.c_[a.get_xdata(), a.get_ydata()]
                      for a in artists if hasattr(a, "get_offsets") or hasattr(a, "get_xdata")]
            (x0, x1), (y0, y1) = self._limits
            if marked:  # a mark beyond the training latents widens the view, for this picture only, up to
                # MAP_WIDEN_SPANS of the map each side: a latent far out would shrink the training latents to a dot
                span = max(x1 - x0, y1 - y0)
                lo = np.array([x0, y0]) - MAP_WIDEN_SPANS * span
                hi = np.array([x1, y1]) + MAP_WIDEN_SPANS * span
                pts = np.clip(np.concatenate([np.asarray(m, dtype=float).reshape(-1, 2) for m in marked]), lo, hi)
                pad = 0.05 * span
                x0, x1 = min(x0, pts[:, 0].min() - pad), max(x1, pts[:, 0].max() + pad)
                y0, y1 = min(y0, pts[:, 1].min() - pad), max(y1, pts[:, 1].max() + pad)
            if star is not None and not (x0 <= star[0] <= x1 and y0 <= star[1] <= y1):  # said at the edge
                edge = (float(np.clip(star[0], x0, x1)), float(np.clip(star[1], y0, y1)))
                artists.append(ax.annotate("selection off the map", edge, xytext=(0.5, 0.04),
                                           textcoords="axes fraction", ha="center", fontsize=8, color="darkgoldenrod",
                                           arrowprops={"arrowstyle": "->", "color": "darkgoldenrod"}, zorder=9))
            ax.set_xlim(x0, x1)
            ax.set_ylim(y0, y1)
            fig = self.map.figure
            fig.set_dpi(MAP_DPI)
            fig.canvas.draw()
            image = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
            bb = ax.get_window_extent()
            h = image.shape[0]
            view = MapImage(image, (bb.x0, h - bb.y1, bb.x1, h - bb.y0), ax.get_xlim(), ax.get_ylim())
            for a in artists:
                a.remove()
        return view

    def pick(self, view: MapImage, px: float, py: float) -> Selection:
        """The latent under a click at pixel (``px``, ``py``) of ``view``."""
        xy = view.to_map(px, py)
        z = self.map.projection.to_latent(xy)[0]
        return Selection(z.tolist(), f"map point ({xy[0]:.3g}, {xy[1]:.3g})", {"source": "explorer: map point"})

    # ------------------------------------------------------------------ rollouts

    def rollout(self, z: Any, n: int | None = None) -> RolloutView:
        """``n`` rollouts (default the explorer's) under latent ``z`` in the scene, drawn over it: one trace per
        rollout coloured by the route it took, its end marked green (success) or red (collision)."""
        from lerobot_pdp.envs.plotting import VIEW_TITLES, scene_views

        self._need_env("rollouts")
        z = self.latent(z)
        outcomes = self.run_latents([z], n or self.rollouts)[0]
        suite, scene = self.suite, self.scene
        modes = [suite.classify_mode(o.states, scene=scene) if len(o.states) else "novel" for o in outcomes]
        views = scene_views(suite)
        fig = Figure(figsize=(4.6 * len(views), 4.6))
        axes = fig.subplots(1, len(views), squeeze=False)
        view = RolloutView(np.zeros((1, 1, 3), np.uint8), outcomes, modes)
        for ax, plane in zip(axes[0], views, strict=True):
            handles = self.draw_rollouts(ax, outcomes, modes, plane)
            ax.set_title(VIEW_TITLES.get(plane, plane), fontsize=9)
        axes[0][-1].legend(handles=handles, fontsize=7, title="route", loc="best")
        fig.suptitle(f"z = {np.round(z, 3).tolist()}: {view.summary()}", fontsize=10)
        fig.tight_layout()
        view.image = _pixels(fig)
        return view

    def draw_rollouts(self, ax: Any, outcomes: list[Outcome], modes: list[int | str], plane: str) -> list:
        """``outcomes`` over the scene on ``plane``: one trace per rollout coloured by the route it took (``modes``),
        its end marked green (success) or grey, a red x for a collision; the scene's way-points (a route it
        admits), when it has some. Returns the legend handles."""
        from lerobot_pdp.envs.plotting import draw_scene, draw_waypoints, plot_trajectories

        suite = self.suite
        draw_scene(ax, suite.name, self.scene, plane)
        handles = plot_trajectories(ax, [o.states for o in outcomes], modes, suite.mode_names, plane,
                                    suite.trace_dims, alpha=0.85, lw=1.4)
        route = draw_waypoints(ax, self.scene.waypoints, plane) if self.scene.waypoints else None
        if route is not None:
            route.set_label("the scene's way-points")
            handles = [*handles, route]
        i, j = ("xyz".index(plane[0]), "xyz".index(plane[1]))
        for o in outcomes:
            end = o.states[-1, [suite.trace_dims[i], suite.trace_dims[j]]]
            if o.info.get("collided"):
                ax.plot(*end, "x", color="red", ms=9, mew=2, zorder=6)
            ax.plot(*end, "o", color="green" if o.success else "grey", ms=5, zorder=6)
        return handles

    def run_latents(self, latents: list[np.ndarray], n: int, progress: Progress | None = None
                    ) -> list[list[Outcome]]:
        """``n`` rollouts under each latent (one per phase for segmented policies) in the scene, on the
        explorer's seeds: one list of outcomes per latent."""
        out: list[list[Outcome]] = []
        with self._lock, CandidateRollouts(self.policy, self.env_factory, n, self.seed, self.processors) as run:
            per = run.candidates_per_batch()
            for i in range(0, len(latents), per):
                if progress is not None:
                    progress(i / len(latents), f"rollouts of latents {i + 1}-{min(i + per, len(latents))} "
                                               f"of {len(latents)}")
                out.extend(run([torch.as_tensor(z, dtype=torch.float32) for z in latents[i:i + per]]))
        return out

    def _need_env(self, what: str) -> None:
        if not self.has_env:
            raise ValueError(f"{what} need an env: start the explorer with --env (and --scene) for a simulated "
                             "checkpoint; without one it shows the decoder's view")

    # ------------------------------------------------------------------ interpolation, fit, decoder

    def mode_key(self, mode: int | str) -> int | str:
        """A mode's id, given as an id or as a choice of :meth:`mode_choices` (``"2: right-wide"``)."""
        head = str(mode).split(":")[0].strip()
        return head if isinstance(head := mode_key(head), int) else mode

    def mode_name(self, mode: int | str) -> str:
        key = self.mode_key(mode)
        return f"mode {key}" + (f" ({self.modes.names[key]})" if self.modes.names.get(key) else "")

    def mode_latent(self, mode: int | str) -> np.ndarray:
        """A mode's mean latent (its first phase's for per-phase latents), by id or choice."""
        z = self.modes[self.mode_key(mode)]
        return z[0].cpu().numpy() if z.dim() == 2 else z.cpu().numpy()

    def interpolate(self, mode_a: int | str, mode_b: int | str, t: float, path: str = "linear",
                    steps: int = 41) -> tuple[Selection, list[list[float]]]:
        """The latent a fraction ``t`` of the way from mode ``mode_a`` to ``mode_b`` (``path``: linear or
        elliptical, :meth:`PDPPolicy.interpolate`), and the whole path for the map."""
        if not 0.0 <= float(t) <= 1.0:
            raise ValueError(f"t must be within [0, 1] ({self.mode_name(mode_a)} at 0, {self.mode_name(mode_b)} at 1), "
                             f"got {t}")
        line = self.policy.interpolate(torch.as_tensor(self.mode_latent(mode_a)),
                                       torch.as_tensor(self.mode_latent(mode_b)), steps, path)
        z = self.policy.interpolate(line[0], line[-1], 1001, path)[round(float(t) * 1000)]
        what = f"{path} interpolation from {self.mode_name(mode_a)} to {self.mode_name(mode_b)} at t = {float(t):.2f}"
        return Selection(z.tolist(), what, {"source": f"explorer: {what}"}), line.tolist()

    def fit(self, dataset: str | Path, episode: int, steps: int | None = None) -> tuple[Selection, FitMark]:
        """Fit z to episode ``episode`` of the LeRobotDataset at ``dataset`` (``policy.fit_latent``, weights
        frozen), as ``lerobot-pdp adapt`` does."""
        from .adaptation import fit_provenance

        root, episode = _check_episode(dataset, episode)
        with self._lock:
            result = self.policy.fit_latent((root, episode), steps=steps, activate=False)
        z = result.z[0] if result.z.dim() == 2 else result.z
        label = f"episode {episode} of {root.name}"
        prov = fit_provenance((root, episode), result, self.policy.config, steps=steps)
        ratio = "n/a" if result.error_ratio is None else f"{result.error_ratio:.2f}"
        return (Selection(z.tolist(), f"fit to {label} (error ratio {ratio})", prov),
                FitMark(z.tolist(), result.error_ratio, label))

    def decoder_source(self, dataset: str | Path | None = None) -> Path | None:
        """The recording the decoder's view samples on: ``dataset``, else the explorer's (``--dataset`` or the
        training dataset); None when there is none."""
        return Path(str(dataset).strip()) if dataset not in (None, "") and str(dataset).strip() else self.dataset

    def no_recording_note(self) -> str:
        """Why there is no decoder's view, and how to get one."""
        return ("the decoder's view needs a recorded episode: start with --dataset DATA (a LeRobotDataset folder), "
                f"or fit an episode below ({_training_dataset_note(self.checkpoint)})")

    def decoder_episode(self, z: Any, dataset: str | Path | None = None) -> tuple[int, str]:
        """The episode the decoder's view compares latent ``z`` with when none is given, and why: in the training
        dataset, the one whose behaviour's latent lies nearest ``z`` (a mode's latent meets a demonstration of that
        mode); in another recording, its first."""
        source = self.decoder_source(dataset)
        training = self._training_data
        if source is None or training is None or source.resolve() != training.resolve():
            return 0, "its first"
        table = self.policy.behavior_table()
        trained = ~self.policy.model.bank.is_taught().cpu().numpy()  # taught rows hold no episode of this dataset
        if not trained.any():
            return 0, "its first"
        dist = np.linalg.norm(table["z"][trained] - np.asarray(self.latent(z))[None], axis=1)
        return int(table["episode"][trained][int(dist.argmin())]), "the training episode nearest z"

    def decoder_view(self, z: Any, dataset: str | Path | None = None, episode: int | None = None, frames: int = 4,
                     samples: int = 4) -> np.ndarray:
        """What the denoiser makes of latent ``z``: ``samples`` action chunks sampled at ``frames`` observations
        of a recorded episode (default: :meth:`decoder_episode`), against the recorded actions."""
        from lerobot.utils.constants import ACTION

        z = self.latent(z)
        source = self.decoder_source(dataset)
        if source is None:
            raise ValueError(self.no_recording_note())
        why = "the one fitted" if episode is not None else None
        if episode is None:
            episode, why = self.decoder_episode(z, dataset)
        root, episode = _check_episode(source, episode)
        with self._lock:
            windows = self._windows(root, episode)
            at = np.linspace(0, len(windows.obs_cond) - 1, max(1, frames)).round().astype(int)
            cond = windows.obs_cond[at].repeat_interleave(samples, 0)
            g = torch.Generator(device=cond.device).manual_seed(self.seed)
            zs = torch.as_tensor(z, dtype=torch.float32, device=cond.device).expand(len(cond), -1)
            chunks = self.policy.generate(cond, zs, generator=g)
            chunks = self.policy.stats.unnormalize(ACTION, chunks).cpu().numpy().reshape(len(at), samples, *chunks.shape[1:])
            recorded = self.policy.stats.unnormalize(ACTION, windows.actions[at]).cpu().numpy()
        dims = min(chunks.shape[-1], DECODER_MAX_DIMS)  # an arm's joints and gripper: 7
        names = (self.policy.config.dataset_feature_names or {}).get(ACTION) or []
        fig = Figure(figsize=(2.6 * len(at), 1.5 * dims + 0.6))
        axes = fig.subplots(dims, len(at), squeeze=False, sharex=True)
        for c, t in enumerate(at):
            for d in range(dims):
                ax = axes[d][c]
                ax.plot(recorded[c, :, d], "k--", lw=1.2, label="recorded")
                for s in range(samples):
                    ax.plot(chunks[c, s, :, d], color="tab:blue", alpha=0.6, lw=1,
                            label="sampled at z" if s == 0 else None)
                ax.tick_params(labelsize=6)
                if c == 0:
                    ax.set_ylabel(names[d] if d < len(names) else f"action[{d}]", fontsize=8)
                if d == 0:
                    ax.set_title(f"frame {t}", fontsize=8)
        axes[0][0].legend(fontsize=6)
        more = f"; the first {dims} of {chunks.shape[-1]} action dimensions" if dims < chunks.shape[-1] else ""
        fig.suptitle(f"decoder's view of z = {np.round(z, 3).tolist()}: action chunks at frames of episode {episode} "
                     f"of {root.name} ({why}{more})", fontsize=9)
        fig.tight_layout()
        return _pixels(fig)

    def _windows(self, root: Path, episode: int) -> Any:
        """A recorded episode's windows, read and encoded once (the weights are frozen): each click of the decoder's
        view would otherwise decode and encode the whole episode again (seconds for a camera episode)."""
        info = root / "meta" / "info.json"  # a folder recorded again is read again
        key = (str(root.resolve()), episode, info.stat().st_mtime_ns if info.is_file() else None)
        if key not in self._window_cache:
            if len(self._window_cache) >= WINDOW_CACHE_SIZE:
                self._window_cache.pop(next(iter(self._window_cache)))
            self._window_cache[key] = self.policy.demo_windows((root, episode))
        return self._window_cache[key]

    # ------------------------------------------------------------------ landscape and saving

    def landscape_key(self, grid: int, rollouts: int) -> dict[str, Any]:
        """What a cached landscape depends on: the checkpoint's weights, the env, scene, grid and rollouts."""
        self._need_env("success landscapes")
        return {"version": LANDSCAPE_VERSION, "checkpoint": file_digest(self.checkpoint / "model.safetensors"),
                "env": self.suite.name, "scene": self.scene.to_dict(), "max_steps": self.max_steps,
                "grid": grid, "rollouts": rollouts, "seed": self.seed, "box": self.box().tolist()}

    def box(self, margin: float = 0.15) -> np.ndarray:
        """The latent map's box around the training latents, ``margin`` of its span added each side: [[x0, x1],
        [y0, y1]] in map coordinates."""
        xy = self.map.projection.to_map(self.policy.behavior_table()["z"])
        lo, hi = xy.min(0), xy.max(0)
        pad = np.maximum((hi - lo) * margin, 1e-3)
        return np.round(np.stack([lo - pad, hi + pad], 1), 6)

    def landscape(self, grid: int = 5, rollouts: int = 2, progress: Progress | None = None,
                  limit: int | None = LANDSCAPE_MAX_ROLLOUTS) -> Landscape:
        """Success rate of ``rollouts`` rollouts at each point of a ``grid`` x ``grid`` grid over the latent box,
        read from the cache when this checkpoint, scene and grid were run before (else run and cached). More than
        ``limit`` rollouts to run is refused (a page's request would hold the app for hours; None: no limit)."""
        grid, rollouts = _positive("grid", grid), _positive("rollouts", rollouts)
        key = self.landscape_key(grid, rollouts)
        digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:20]
        cache = self.cache_dir / f"landscape-{digest}.json"
        box = np.asarray(key["box"])
        xs, ys = np.linspace(*box[0], grid), np.linspace(*box[1], grid)
        if cache.is_file():
            try:
                saved = json.loads(cache.read_text())
                if saved.get("key") == key:
                    return Landscape(xs, ys, np.asarray(saved["success"]), np.asarray(saved["collision"]), cache, True)
            except (ValueError, KeyError):
                pass  # a damaged cache file is run again and replaced
        if limit is not None and grid * grid * rollouts > limit:
            raise ValueError(f"a {grid} x {grid} grid at {rollouts} rollout(s) each is {grid * grid * rollouts} "
                             f"rollouts, over the limit of {limit} per request: use a coarser grid or fewer rollouts "
                             "(from Python: landscape(..., limit=None))")
        points = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)  # row-major: y outer, x inner
        latents = list(self.map.projection.to_latent(points))
        outcomes = self.run_latents(latents, rollouts, progress)
        success = np.array([np.mean([o.success for o in os_]) for os_ in outcomes]).reshape(grid, grid)
        collision = np.array([np.mean([bool(o.info.get("collided")) for o in os_]) for os_ in outcomes]).reshape(grid, grid)
        if progress is not None:
            progress(1.0, "done")
        self.cache_dir.mkdir(parents=True, exist_ok=True)
        write_text_atomic(cache, json.dumps({"key": key, "success": success.tolist(), "collision": collision.tolist()}))
        return Landscape(xs, ys, success, collision, cache, False)

    def landscape_image(self, land: Landscape) -> np.ndarray:
        """The success landscape as a heat map under the training latents (collisions hatched)."""
        proj = self.map.projection
        xy = proj.to_map(self.policy.behavior_table()["z"])
        fig = Figure(figsize=(5.6, 4.6))
        ax = fig.subplots()
        dx = (land.xs[1] - land.xs[0]) / 2 if len(land.xs) > 1 else 0.5
        dy = (land.ys[1] - land.ys[0]) / 2 if len(land.ys) > 1 else 0.5
        im = ax.imshow(land.success, origin="lower", cmap="RdYlGn", vmin=0, vmax=1, aspect="auto",
                       extent=(land.xs[0] - dx, land.xs[-1] + dx, land.ys[0] - dy, land.ys[-1] + dy))
        for (r, c), v in np.ndenumerate(land.collision):
            if v > 0:
                ax.plot(land.xs[c], land.ys[r], "x", color="k", ms=4 + 6 * v)
        # white dots: mode colours would read as success levels on the red-yellow-green map
        ax.scatter(xy[:, 0], xy[:, 1], s=12, color="white", edgecolor="k", lw=0.5)
        fig.colorbar(im, ax=ax, label="success rate")
        ax.set_xlabel(proj.axis_labels[0])
        ax.set_ylabel(proj.axis_labels[1])
        where = "cache" if land.from_cache else "rollouts just run"
        ax.set_title(f"success over z, {self.scene.name} ({len(land.xs)}x{len(land.ys)} grid; from {where})\n"
                     "x: collisions; white dots: training latents", fontsize=9)
        fig.tight_layout()
        return _pixels(fig)

    def save_adapted(self, selection: Selection, out: str | Path) -> Path:
        """Write ``selection``'s latent as an adapted checkpoint ``out`` (which must not exist): the checkpoint's
        files plus the adaptation, as ``lerobot-pdp adapt`` writes them, acting under it from the first action."""
        out = Path(str(out).strip()) if str(out).strip() else None
        if out is None:
            raise ValueError("give a folder to write the adapted checkpoint to")
        require_new_folder(out, "adapted", self.checkpoint)  # not there yet, nor inside the checkpoint it copies
        z = self.latent(selection.z)
        date = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
        where = {"env": self.suite.name, "scene": self.scene.name} if self.has_env else {}
        provenance = {"source": "explorer", **selection.provenance, "chosen": selection.source, "via": "lerobot-pdp explore", **where,
                      "base_checkpoint": _origin(self.checkpoint), "date": selection.provenance.get("date", date)}
        steering = Steering(self.latent_dim)
        steering.activate(torch.as_tensor(z, dtype=torch.float32), provenance=provenance)
        card = card_section(f"This checkpoint acts under a latent chosen in the explorer (`lerobot-pdp explore`): "
                            f"`{np.round(z, 6).tolist()}`, {selection.source} ({provenance['date']}).")
        in_the_way = next((p for p in out.parents if p.exists() and not p.is_dir()), None)
        if in_the_way is not None:
            raise FileExistsError(f"{in_the_way} is a file, not a folder: give a new folder for the adapted checkpoint")
        out.parent.mkdir(parents=True, exist_ok=True)
        write_adapted_checkpoint(self.checkpoint, SimpleNamespace(steering=steering), out, card)
        return out


# ---------------------------------------------------------------------------------------- helpers


def default_cache_dir() -> Path:
    """Where landscapes are cached: ``$LEROBOT_PDP_CACHE/explorer`` (the package's cache, ``~/.cache/lerobot_pdp``)."""
    return Path(os.environ.get("LEROBOT_PDP_CACHE", Path.home() / ".cache" / "lerobot_pdp")) / "explorer"


def file_digest(path: Path) -> str:
    """SHA-256 of a file, read in blocks (weights files are large)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _pixels(fig: Figure) -> np.ndarray:
    """A figure's RGB pixels. Figures are made without pyplot: its global state is not for Gradio's threads."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    buf.seek(0)
    return np.asarray(Image.open(buf).convert("RGB"))


def _positive(name: str, value: Any) -> int:
    try:
        ok = not isinstance(value, bool) and float(value).is_integer() and int(value) >= 1
    except (TypeError, ValueError):  # None (an emptied number box), text
        ok = False
    if not ok:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    return int(value)


def check_checkpoint_folder(checkpoint: Path) -> None:
    """A PDP checkpoint folder (config.json of type pdp + model.safetensors), else an error naming what is wrong."""
    require_checkpoint_files(checkpoint)
    kind = read_config_json(checkpoint / "config.json").get("type")  # a damaged file: named
    if kind != "pdp":
        raise ValueError(f"{checkpoint / 'config.json'} has type {kind!r}: the explorer needs a PDP checkpoint "
                         "(type 'pdp')")


def _training_dataset(checkpoint: Path) -> Path | None:
    """The local training dataset the checkpoint's ``train_config.json`` names, if it is there."""
    from .taught import training_data_of

    try:
        root = training_data_of(checkpoint)
    except (OSError, ValueError):
        return None
    return root if (root / "meta" / "info.json").is_file() else None


def _training_dataset_note(checkpoint: Path) -> str:
    """What the checkpoint's train_config.json says of its training dataset, for a message."""
    from .taught import training_data_of

    try:
        root = training_data_of(checkpoint)
    except (OSError, ValueError):
        return f"{checkpoint} has no train_config.json naming a local training dataset"
    return f"{checkpoint}'s train_config.json names {root}, which is not a LeRobotDataset folder on this machine" + (
        f" (looked for relative to {Path.cwd()})" if not root.is_absolute() else "")


def _check_episode(dataset: str | Path, episode: Any) -> tuple[Path, int]:
    """``dataset`` is a LeRobotDataset folder and ``episode`` one of its episodes; else an error naming both."""
    if dataset is None or not str(dataset).strip():
        raise ValueError("give a LeRobotDataset folder (the folder box is empty)")
    root = Path(str(dataset).strip())
    total = int(recording_info(root).get("total_episodes") or 0)
    try:
        whole = not isinstance(episode, bool) and float(episode).is_integer()
    except (TypeError, ValueError):
        whole = False
    if not whole:
        raise ValueError(f"episode must be a whole number (an index of {root}'s episodes 0-{total - 1}), "
                         f"got {episode!r}")
    if not 0 <= int(episode) < total:
        raise ValueError(f"episode {episode!r} is out of range: {root} has episodes 0-{total - 1} "
                         f"(meta/info.json total_episodes = {total})")
    return root, int(episode)


def _origin(checkpoint: Path) -> str:
    """The base checkpoint: the one an adapted checkpoint names, else this one."""
    try:
        return json.loads((checkpoint / ADAPTATION_INFO).read_text())["base_checkpoint"]
    except (OSError, ValueError, KeyError, TypeError):
        return str(checkpoint.resolve())


def import_gradio() -> Any:
    """Gradio, or an ImportError saying how to install it (it is an optional dependency)."""
    try:
        import gradio as gr
    except ImportError as e:
        raise ImportError(GRADIO_HINT) from e
    return gr
