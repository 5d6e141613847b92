"""Benchmark figures (PNG): latent map, rollouts per scene and method, interpolation sweeps, fitted z.

Everything is drawn from what the protocol cached (``runs/<method>/seed<k>/eval.json``, ``traces.json`` and
the seed-0 PDP's ``sweep.json``); nothing here trains, loads a policy or rolls out.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..atomic import write_figure_atomic  # noqa: E402
from ..envs.plotting import draw_scene, mode_color, scene_views  # noqa: E402
from ..envs.suite import SuiteEnv  # noqa: E402
from .settings import ABLATIONS  # noqa: E402


def _plane_dims(plane: str) -> tuple[int, int]:
    return "xyz".index(plane[0]), "xyz".index(plane[1])


def behavior_phases(episode: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Phase index of each behavior within its episode (order of start frames; 0 if not segmented)."""
    episode, start = np.asarray(episode), np.asarray(start)
    return np.array([int(((episode == e) & (start < s)).sum()) for e, s in zip(episode, start, strict=True)],
                    dtype=int)


def latent_map(suite: SuiteEnv, eval_json: dict[str, Any], out_png: Path, title: str = "") -> Path:
    """Encoder means of every training behavior coloured by mode, per-mode means, fitted z of scenes 1-3.

    Gripper-segmented policies get one panel per phase (reach, carry, ...): each phase has its own
    latent per mode, and the fitted z of a phase is drawn in that phase's panel.
    """
    lat = eval_json["latents"]
    z = np.asarray(lat["z"])
    modes = np.asarray(lat["mode"])
    phases = (behavior_phases(lat["episode"], lat["start"]) if "episode" in lat and "start" in lat
              else np.zeros(len(z), dtype=int))
    n_phases = int(phases.max()) + 1
    if z.shape[1] > 2:  # one-hot / higher-d latents: first two principal axes
        centre = z.mean(0)
        _, _, vt = np.linalg.svd(z - centre, full_matrices=False)
        proj = vt[:2].T
    else:
        centre, proj = np.zeros(z.shape[1]), np.eye(z.shape[1], 2)
    p = (z - centre) @ proj
    fig, axes = plt.subplots(1, n_phases, figsize=(6.5 * n_phases, 5.5), squeeze=False)
    for ph, ax in enumerate(axes[0]):
        of_phase = phases == ph
        for m in sorted(set(modes[of_phase].tolist())):
            sel = of_phase & (modes == m)
            name = suite.mode_names[m] if 0 <= m < suite.n_modes else "unlabeled"
            c = mode_color(int(m), suite.n_modes)
            ax.scatter(p[sel, 0], p[sel, 1], s=14, color=c, alpha=0.6,
                       label=f"{m}: {name}" if suite.n_modes <= 24 and ph == 0 else None)
            mean = p[sel].mean(0)
            ax.scatter(*mean, s=120, color=c, edgecolor="k", marker="o", zorder=4)
            ax.annotate(str(m), mean, fontsize=8, ha="center", va="center", zorder=5)
        labelled: list[np.ndarray] = []  # stars already labelled: close ones stack their labels upwards
        near = 0.05 * float(np.ptp(p, axis=0).max() or 1.0)
        for scene, sc in eval_json["scenes"].items():
            if scene == "0" or "z" not in sc:
                continue
            zf, zi = np.atleast_2d(np.asarray(sc["z"])), np.atleast_2d(np.asarray(sc["z_init"]))
            if ph >= len(zf):
                continue
            pf, pi = (zf[ph] - centre) @ proj, (zi[ph] - centre) @ proj
            ax.annotate("", pf, pi, arrowprops={"arrowstyle": "->", "color": "k", "lw": 1})
            ax.scatter(pf[0], pf[1], marker="*", s=260, color="gold", edgecolor="k", zorder=6)
            right = pf[0] > float(np.median(p[:, 0]))  # label towards the map's middle, off the legend
            stack = sum(float(np.linalg.norm(pf - q)) < near for q in labelled)
            labelled.append(pf)
            ax.annotate(f"scene {scene} ({100 * sc['success']:.0f}%)", pf, xytext=(-6 if right else 6, 6 + 12 * stack),
                        textcoords="offset points", fontsize=9, weight="bold", ha="right" if right else "left")
        ax.set_xlabel("z[0]" if z.shape[1] <= 2 else "PC 1")
        ax.set_ylabel("z[1]" if z.shape[1] <= 2 else "PC 2")
        if n_phases > 1:
            ax.set_title(f"phase {ph} (behaviors between gripper events)", fontsize=10)
    fig.suptitle(title or f"{suite.name}: behavior latent (dots: demos, circles: mode means, stars: fitted z, "
                          "arrows: from the encoder warm start)")
    if suite.n_modes <= 24:
        axes[0][-1].legend(*axes[0][0].get_legend_handles_labels(), fontsize=7, loc="center left",
                           bbox_to_anchor=(1.0, 0.5))
    fig.tight_layout()
    write_figure_atomic(fig, out_png, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return out_png


def rollouts_grid(suite: SuiteEnv, traces: dict[str, dict[str, list]], scenes: list[int], out_png: Path,
                  plane: str = "xy") -> Path:
    """Rows = methods, columns = scenes: rollouts (green success, red failure) over the scene geometry."""
    methods = list(traces)
    fig, axes = plt.subplots(len(methods), len(scenes), figsize=(3.6 * len(scenes), 3.4 * len(methods)),
                             squeeze=False)
    i, j = _plane_dims(plane)
    for r, method in enumerate(methods):
        for c, scene in enumerate(scenes):
            ax = axes[r][c]
            draw_scene(ax, suite.name, scene, plane)
            rows = traces[method].get(str(scene), [])
            for row in rows:
                t = np.asarray(row["trace"])
                if t.ndim != 2 or t.shape[1] <= max(i, j):
                    continue
                ax.plot(t[:, i], t[:, j], color="tab:green" if row["success"] else "tab:red", alpha=0.5, lw=0.9)
            rate = np.mean([row["success"] for row in rows]) if rows else float("nan")
            ax.set_title(f"{method} · scene {scene}: {100 * rate:.0f}%", fontsize=9)
            ax.set_xlabel("")
            ax.set_ylabel("")
    fig.suptitle(f"{suite.name}: rollouts ({plane} view; green = success, red = failure)")
    fig.tight_layout()
    write_figure_atomic(fig, out_png, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return out_png


def interpolation_sweep(suite: SuiteEnv, sweep: dict[str, Any], out_png: Path) -> Path:
    """The latent sweep of ``evaluation.evaluate_sweep``: each path's rollouts in two views, and the path on
    the latent map."""
    a, b = sweep["modes"]
    n = len(sweep["paths"]["linear"]["z"])
    planes = scene_views(suite)[:2]
    # last column: where the sweep runs on the latent map (2-D latents; the first two coordinates otherwise)
    table = {k: np.asarray(v) for k, v in sweep["behaviors"].items()}
    fig, axes = plt.subplots(2, len(planes) + 1, figsize=(5.2 * (len(planes) + 1), 9), squeeze=False)
    cmap = plt.get_cmap("viridis")
    for r, path in enumerate(("linear", "elliptical")):
        results = sweep["paths"][path]["rollouts"]
        for c, plane in enumerate(planes):
            ax = axes[r][c]
            draw_scene(ax, suite.name, 0, plane)
            i, j = _plane_dims(plane)
            for k, res in enumerate(results):
                t = np.asarray(res["trace"])
                ax.plot(t[:, i], t[:, j], color=cmap(k / max(n - 1, 1)), lw=1.6, ls="-" if res["success"] else "--",
                        label=f"t={k / (n - 1):.2f}" + ("" if res["success"] else " ✗"))
            ax.set_title(f"{path} path ({plane} view)", fontsize=10)
        _sweep_on_latent_map(axes[r][-1], suite, table, np.asarray(sweep["paths"][path]["z"]), path)
        axes[r][-2].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    # the mode names are long (pick-place names both phases): once, in the figure title, not per panel
    fig.suptitle(f"{suite.name}: latent sweeps from mode {a} ({suite.mode_names[a]}) to mode {b} "
                 f"({suite.mode_names[b]})\nlinear: through the map's centre; elliptical: around it; "
                 "dashed = failed rollout", fontsize=11)
    fig.tight_layout()
    write_figure_atomic(fig, out_png, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return out_png


def _sweep_on_latent_map(ax, suite: SuiteEnv, table: dict[str, np.ndarray], zs: np.ndarray, path: str) -> None:
    """Training behaviors' latents (grey, mode ids at the means) and the sweep's latents coloured by t."""
    z, modes = table["z"][:, :2], table["mode"]
    ax.scatter(z[:, 0], z[:, 1], s=6, color="0.75", zorder=1)
    for m in sorted(set(modes[modes >= 0].tolist())) if suite.n_modes <= 24 else []:
        mean = z[modes == m].mean(0)
        ax.annotate(str(m), mean, fontsize=7, ha="center", va="center", color="0.35")
    zs = zs.reshape(len(zs), -1, zs.shape[-1])[..., :2]  # [n, phases, 2]
    t = np.linspace(0, 1, len(zs))
    for ph in range(zs.shape[1]):
        ax.plot(zs[:, ph, 0], zs[:, ph, 1], color="k", lw=0.8, zorder=2)
        ax.scatter(zs[:, ph, 0], zs[:, ph, 1], c=t, cmap="viridis", s=40, edgecolor="k", zorder=3,
                   marker="os^v"[ph % 4], label=f"phase {ph}" if zs.shape[1] > 1 else None)
    if zs.shape[1] > 1:
        ax.legend(fontsize=7)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("z[0]")
    ax.set_ylabel("z[1]")
    ax.set_title(f"{path} path on the latent map" + (" (first two dims)" if table["z"].shape[1] > 2 else ""),
                 fontsize=10)


def write_figures(suite: SuiteEnv, out: Path, cfg, ckpts: dict[tuple[str, int], Path],
                  sweep: dict[str, Any] | None = None) -> list[Path]:
    """All benchmark figures into ``out/figures`` from the cached evaluations (and the PDP latent ``sweep``
    of ``evaluation.evaluate_sweep``); runs nothing. Returns the figures' paths."""
    fig_dir = Path(out) / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    seed = cfg.seeds[0]
    traces: dict[str, dict[str, list]] = {}
    for (name, s), _ckpt in ckpts.items():
        if s != seed:
            continue
        run_dir = Path(out) / "runs" / name / f"seed{s}"
        if (run_dir / "traces.json").is_file():
            traces[name] = json.loads((run_dir / "traces.json").read_text())
        ev = run_dir / "eval.json"
        if ev.is_file():
            data = json.loads(ev.read_text())
            if "latents" in data:
                written.append(latent_map(suite, data, fig_dir / f"latent_map_{name}.png"))
    # Split by what a method is, not by how it was asked for: `--methods pdp_onehot ...` is still an ablation.
    # PDP heads the ablation grid too, as the row every variant is compared with.
    main_methods = {k: v for k, v in traces.items() if k not in ABLATIONS}
    for plane in scene_views(suite)[:2]:
        if main_methods:
            written.append(rollouts_grid(suite, main_methods, list(cfg.scenes), fig_dir / f"rollouts_{plane}.png", plane))
    ablated = [k for k in traces if k in ABLATIONS]
    if ablated:
        rows = (["pdp"] if "pdp" in traces else []) + ablated
        written.append(rollouts_grid(suite, {k: traces[k] for k in rows}, list(cfg.scenes), fig_dir / "rollouts_ablations.png",
                                     scene_views(suite)[0]))
    if sweep is not None:
        written.append(interpolation_sweep(suite, sweep, fig_dir / "interpolation.png"))
    return written
