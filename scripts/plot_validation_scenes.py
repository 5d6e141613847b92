"""Draw each env's shifted scenes, test (1-3, and the zero-mode test scenes of ``--teach``) next to validation
(val1, ...), with the one demonstration the benchmark gives in each: the open training mode's scripted expert,
or the scene's own way-points (black).

Shows at a glance that the validation scenes open other modes than scenes 1-2 and that their new routes leave
the training modes elsewhere than scene 3's. No policy, no training: scripted experts only (a few seconds).

Usage: ``.venv/bin/python scripts/plot_validation_scenes.py [--out docs/figures/validation_scenes] [--env ...]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import lerobot_pdp.envs  # noqa: E402,F401  (registers the suite)
from lerobot_pdp.benchmark.data import feasible_training_modes  # noqa: E402
from lerobot_pdp.benchmark.settings import TEACH_SCENES, VALIDATION_SCENES  # noqa: E402
from lerobot_pdp.envs.plotting import AXES, VIEW_TITLES, draw_scene, mode_color, scene_views  # noqa: E402
from lerobot_pdp.envs.recording import run_expert_episode  # noqa: E402
from lerobot_pdp.envs.scene import load_scene  # noqa: E402
from lerobot_pdp.envs.suite import SuiteEnv, get_suite_env  # noqa: E402


def demonstration(suite: SuiteEnv, scene: int | str) -> tuple[np.ndarray, int | str, bool]:
    """The benchmark's demonstration of ``scene`` (as ``data.ensure_demo`` picks it): positions, label, success."""
    sc = load_scene(scene, suite.scene_key)
    if sc.waypoints is not None:
        info, states, _ = run_expert_episode(suite, scene, waypoints=sc.waypoints, seed=0)
    else:
        modes = feasible_training_modes(suite, scene)
        info, states, _ = run_expert_episode(suite, scene, mode=modes[0], seed=0)
    return states, suite.classify_mode(states), bool(info.get("is_success"))


def plot_env(env: str, out_dir: Path) -> Path:
    suite = get_suite_env(env)
    # the test scenes, the zero-mode test scenes only `--teach` evaluates, then the validation scenes
    teach_test = list(TEACH_SCENES.get(suite.name, {}).get("test", ()))
    scenes: list[int | str] = [1, 2, 3, *teach_test, *VALIDATION_SCENES[suite.name]]
    views = scene_views(suite)
    fig, axes = plt.subplots(len(views), len(scenes), figsize=(3.2 * len(scenes), 3.2 * len(views)), squeeze=False)
    for c, scene in enumerate(scenes):
        states, label, ok = demonstration(suite, scene)
        pos = states[:, list(suite.trace_dims)]
        name = load_scene(scene, suite.scene_key).name.split(":", 1)
        what = "new route" if label == "novel" else f"mode {label} ({suite.mode_names[int(label)]})"
        for r, plane in enumerate(views):
            ax = axes[r][c]
            draw_scene(ax, suite.name, scene, plane)
            i, j = AXES[plane[0]], AXES[plane[1]]
            ax.plot(pos[:, i], pos[:, j], color=mode_color(label, suite.n_modes), lw=1.6,
                    ls="-" if ok else ":")
            ax.set_xlabel("")
            ax.set_ylabel(VIEW_TITLES.get(plane, plane) if c == 0 else "", fontsize=8)
            if r == 0:
                split = "validation" if isinstance(scene, str) else "test"
                ax.set_title(f"{split} · {name[0].strip()}\n{name[-1].strip()}\ndemo: {what}", fontsize=8)
    extra = f" (+ {', '.join(map(str, teach_test))}: zero-mode, --teach only)" if teach_test else ""
    fig.suptitle(f"{suite.name}: test scenes 1-3{extra} and validation scenes (barriers orange; the scene's one "
                 "demonstration drawn, black = a route no training mode takes)", fontsize=10)
    fig.tight_layout()
    out_dir.mkdir(parents=True, exist_ok=True)
    out = out_dir / f"{suite.scene_key}.png"
    fig.savefig(out, dpi=90, bbox_inches="tight")
    plt.close(fig)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("docs/figures/validation_scenes"), help="output folder")
    p.add_argument("--env", nargs="+", default=sorted(VALIDATION_SCENES), help="envs (default: all with a split)")
    args = p.parse_args()
    for env in args.env:
        print(f"wrote {plot_env(env, args.out)}")


if __name__ == "__main__":
    main()
