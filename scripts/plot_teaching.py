"""Draw what teaching a new mode changed, as rollouts over the scenes (no numbers a table does not already give).

Three panels per view of the env: (1) the zero-mode scene with its demonstration and the *untaught*
checkpoint's rollouts under the latent fitted to it (z alone: the denoiser has no such route); the
demonstration is dashed purple; (2) the *taught*
checkpoint steered to its new mode in that scene; (3) the taught checkpoint in scene 0, steered to each old mode
by its latent (the routes it kept). Each trace is coloured by the route the env's classifier says it took; a red x
marks a collision, a green dot a success (the explorer's drawing, `Explorer.draw_rollouts`).

Usage (the taught checkpoint from ``lerobot-pdp teach BASE --demo DEMO --out TAUGHT``)::

    .venv/bin/python scripts/plot_teaching.py BASE TAUGHT --env avoiding --scene 4 --demo DEMO \\
        --out docs/figures/teaching/avoiding_scene4.png
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

os.environ.setdefault("HF_HUB_OFFLINE", "1")


def rollouts(explorer, latents: list, n: int) -> list:
    """``n`` rollouts per latent in the explorer's scene (the explorer's seeds), flattened."""
    return [o for per_latent in explorer.run_latents(latents, n) for o in per_latent]


def draw(ax, explorer, outcomes: list, plane: str, title: str, demo: np.ndarray | None = None) -> None:
    """The explorer's drawing of ``outcomes`` (routes coloured by the env's classifier), the demonstration dashed."""
    modes = [explorer.suite.classify_mode(o.states, scene=explorer.scene) if len(o.states) else "novel"
             for o in outcomes]
    explorer.draw_rollouts(ax, outcomes, modes, plane)
    if demo is not None:
        i, j = ("xyz".index(plane[0]), "xyz".index(plane[1]))
        cols = [explorer.suite.trace_dims[i], explorer.suite.trace_dims[j]]
        ax.plot(demo[:, cols[0]], demo[:, cols[1]], "--", color="tab:purple", lw=2.5, zorder=7, label="demonstration")
        ax.legend(fontsize=8, loc="lower left")
    wins = sum(o.success for o in outcomes)
    ax.set_title(f"{title}\nsuccess {wins}/{len(outcomes)}", fontsize=9)


def main() -> None:
    from lerobot_pdp.demonstration import read_demonstration
    from lerobot_pdp.envs.plotting import VIEW_TITLES, scene_views
    from lerobot_pdp.explorer import Explorer

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("base", help="the untaught checkpoint (pretrained_model folder)")
    ap.add_argument("taught", help="the checkpoint lerobot-pdp teach wrote")
    ap.add_argument("--env", required=True)
    ap.add_argument("--scene", required=True, help="the zero-mode scene the demonstration was recorded in")
    ap.add_argument("--demo", required=True, help="the demonstration's dataset folder (episode 0)")
    ap.add_argument("--rollouts", type=int, default=10, help="rollouts on the new route, per panel")
    ap.add_argument("--per-mode", type=int, default=2, help="scene-0 rollouts per old mode")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()

    base = Explorer(args.base, env=args.env, scene=args.scene)
    selection, _ = base.fit(args.demo, 0)
    before = rollouts(base, [base.latent(selection.z)], args.rollouts)
    taught = Explorer(args.taught, env=args.env, scene=args.scene)
    modes = taught.policy.mode_latents()
    new_mode = max(modes)
    after = rollouts(taught, [modes[new_mode].numpy()], args.rollouts)
    kept = Explorer(args.taught, env=args.env, scene="0")
    old = rollouts(kept, [z.numpy() for m, z in sorted(modes.items()) if m != new_mode], args.per_mode)
    demo = read_demonstration((Path(args.demo), 0), taught.policy.config, taught.policy.action_dim,
                              "auto").arrays["observation.state"]

    views = scene_views(base.suite)
    fig, axes = plt.subplots(len(views), 3, figsize=(13.5, 4.6 * len(views)), squeeze=False)
    for row, plane in zip(axes, views, strict=True):
        draw(row[0], base, before, plane, f"untaught, z fitted to the demonstration, scene {args.scene}", demo)
        draw(row[1], taught, after, plane, f"taught, steered to the new mode {new_mode}, scene {args.scene}")
        draw(row[2], kept, old, plane, f"taught, scene 0, steered to each of the {len(modes) - 1} old modes")
        row[0].set_ylabel(VIEW_TITLES.get(plane, plane), fontsize=9)
    fig.suptitle(f"{args.env}: teaching one demonstration as a new mode", fontsize=11)
    fig.tight_layout()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
