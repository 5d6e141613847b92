"""Is a shifted scene lost by the fit or by the denoiser? L_fit and rollout success over a grid of latents.

For a benchmark run with a 2-D, unsegmented latent, evaluates on an n x n grid of z:

- ``L_fit`` of the scene's demonstration (the objective ``fit_latent`` minimises, with the checkpoint's
  ``fit_lambda``): every demonstration window, ``--noise-draws`` (k, eps) draws each, the same draws at every
  grid point (common random numbers), so the map is smooth and its minimum is where a converged fit lands;
- with ``--objective sample``: instead of L_fit, the error of the chunks the policy samples under z (the
  ``fit_objective="sample"`` loss, ``--noise-draws`` noises per window); with ``--objective decoder``, the
  trajectory VAE decoder's error on the demonstration's (standardised) behavior trace;
- with ``--rollouts N``: the scene's success and collision rates with z held at that grid point (the
  protocol's rollout seeds for that scene). ``--scene`` takes test (1-3, and a zero-mode test scene such as
  avoiding's 4, which a validation run never evaluates: then no fitted latent is marked) and validation
  (val1, ...) scenes.

Prints one JSON line per grid point and writes a PNG with both maps, the training modes' mean latents, the
encoder's warm start and the latent the benchmark fitted (``eval.json``). If some grid latents succeed
where the fitted one fails, the denoiser can produce the behaviour and the fit does not find it.

    python scripts/diagnostics/latent_landscape.py runs/kitchen_seeds/runs/pdp/seed0 \\
        --env kitchen-microwave --scene 3 -n 6 --rollouts 10 --z0 -0.5 2.0 --z1 -3.5 -1.0 --out k3.png
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

os.environ.setdefault("HF_HUB_OFFLINE", "1")


def main() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from run_args import add_run_args, eval_record, scene_demo

    from lerobot_pdp.behavior import make_trace
    from lerobot_pdp.benchmark.rollouts import run_rollouts
    from lerobot_pdp.benchmark.settings import scene_seed_offset
    from lerobot_pdp.benchmark.training import load_run
    from lerobot_pdp.envs.suite import get_suite_env
    from lerobot_pdp.fast_inference import FrozenDenoiser
    from lerobot_pdp.latent_fitting import fit_loss

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_run_args(ap)
    ap.add_argument("-n", type=int, default=11, help="grid points per latent axis")
    ap.add_argument("--z0", type=float, nargs=2, metavar=("LO", "HI"), help="range of z[0] (default: around the "
                    "mode means, the warm start and the fitted z, +30 %%)")
    ap.add_argument("--z1", type=float, nargs=2, metavar=("LO", "HI"), help="range of z[1] (default: as --z0)")
    ap.add_argument("--noise-draws", type=int, default=32, help="(k, eps) draws per demonstration window")
    ap.add_argument("--objective", choices=("denoise", "sample", "decoder"), default="denoise",
                    help="what is mapped: L_fit (noise prediction), the sampled chunks' error, or the trajectory "
                    "VAE decoder's error on the demonstration's behavior trace")
    ap.add_argument("--rollouts", type=int, default=0, help="rollouts per grid point (0: L_fit only)")
    ap.add_argument("--first-windows", type=int, metavar="W",
                    help="L_fit on the demonstration's first W windows only (where does the early part point?)")
    ap.add_argument("--out", type=Path, default=Path("latent_landscape.png"))
    args = ap.parse_args()
    for name, value, least in (("-n", args.n, 2), ("--noise-draws", args.noise_draws, 1),
                               ("--rollouts", args.rollouts, 0), ("--first-windows", args.first_windows or 1, 1)):
        if value < least:
            ap.error(f"{name} must be >= {least}, got {value}")

    policy, pre, post = load_run(args.run)
    cfg = policy.config
    if cfg.latent_dim != 2 or cfg.segment_gripper_dim is not None:
        ap.error(f"needs a 2-D unsegmented latent; {args.run} has latent_dim={cfg.latent_dim}, "
                 f"segment_gripper_dim={cfg.segment_gripper_dim}")
    meta = eval_record(ap, args.run, "its fitted latent is read from there")
    suite = get_suite_env(args.env)
    demo = scene_demo(ap, suite, args.run, args.scene)

    policy.eval()
    means = np.stack([m.numpy() for m in policy.mode_latents().values()])
    warm = policy.encode(demo).numpy()
    # a scene the run did not evaluate (a zero-mode test scene checked on a validation run) has no fitted latent
    fit_record = meta["scenes"].get(str(args.scene))
    fitted = None if fit_record is None else np.asarray(fit_record["z"], dtype=np.float32)
    pts = np.vstack([means, warm] + ([] if fitted is None else [fitted]))
    lo, hi = pts.min(0), pts.max(0)
    lo, hi = lo - 0.3 * (hi - lo), hi + 0.3 * (hi - lo)
    r0 = args.z0 or (lo[0], hi[0])
    r1 = args.z1 or (lo[1], hi[1])
    a_axis, b_axis = np.linspace(*r0, args.n), np.linspace(*r1, args.n)

    # L_fit on every window with the same noise at every grid point (a fresh generator per point).
    windows = policy.demo_windows(demo)
    den, sched = policy.model.denoiser, policy.model.noise_schedule
    den = FrozenDenoiser(den, sched.num_train_timesteps)  # weights frozen: built once
    idx = torch.arange(len(windows.segment))
    if args.first_windows:
        if args.first_windows > len(idx):
            ap.error(f"--first-windows {args.first_windows}: the scene-{args.scene} demonstration has {len(idx)} windows")
        idx = idx[: args.first_windows]
    with torch.no_grad():
        obs = den.observations(windows.obs_cond)

        vae = policy.model.vae
        trace = make_trace(np.asarray(demo[cfg.trace_key]), cfg.trace_dims, cfg.trace_length, cfg.trace_normalize)
        target = vae.standardize(torch.as_tensor(trace, dtype=torch.float32)[None])

        def objective(z: np.ndarray) -> float:
            g = torch.Generator().manual_seed(0)
            zt = torch.tensor(z, dtype=torch.float32)[None]
            if args.objective == "decoder":
                return float((vae.decode(zt) - target).pow(2).mean())
            steps = cfg.num_inference_steps if args.objective == "sample" else None
            return float(fit_loss(den, sched, windows, zt, idx, args.noise_draws, cfg.fit_lambda, g, obs,
                                  sample_steps=steps))

        loss = np.zeros((args.n, args.n))
        success = np.full((args.n, args.n), np.nan)
        for i, a in enumerate(tqdm(a_axis, desc="grid rows")):
            for j, b in enumerate(b_axis):
                z = np.array([a, b], dtype=np.float32)
                loss[i, j] = objective(z)
                row = {"z": [round(float(a), 3), round(float(b), 3)], "L_fit": round(loss[i, j], 5)}
                if args.rollouts:
                    policy.set_latent(torch.tensor(z))
                    batch = run_rollouts(suite, args.scene, policy, pre, post, args.rollouts,
                                         meta["seed"] * 10_000 + scene_seed_offset(args.scene))
                    success[i, j] = batch.success_rate
                    row |= {"success": batch.success_rate, "collision": batch.collision_rate}
                print(json.dumps(row), flush=True)
        marks = {"warm start": warm} | ({} if fitted is None else {"fitted (benchmark)": fitted})
        i_min, j_min = np.unravel_index(loss.argmin(), loss.shape)
        fit_row = {} if fitted is None else {"fitted": fitted.round(3).tolist(), "L_fit(fitted)": round(objective(fitted), 5)}
        print(json.dumps({**fit_row, "warm": warm.round(3).tolist(), "L_fit(warm)": round(objective(warm), 5),
                          "grid argmin": [round(float(a_axis[i_min]), 3), round(float(b_axis[j_min]), 3)],
                          "L_fit(grid min)": round(float(loss.min()), 5)}))
    policy.set_latent(None)

    part = f", first {len(idx)} windows" if args.first_windows else ""
    name = {"sample": "sampled-chunk error", "decoder": "decoder trace error"}.get(args.objective, "L_fit")
    panels = [(f"{name} (lambda = {cfg.fit_lambda:g}{part})", loss, "viridis")]
    if args.rollouts:
        panels.append((f"scene-{args.scene} success ({args.rollouts} rollouts per z)", success, "RdYlGn"))
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4.6), squeeze=False)
    # Each cell centred on its grid point (imshow spreads n cells over the extent).
    da, db = (a_axis[1] - a_axis[0]) / 2, (b_axis[1] - b_axis[0]) / 2
    xlim, ylim = (r1[0] - db, r1[1] + db), (r0[0] - da, r0[1] + da)
    extent = (*xlim, *ylim)
    for ax, (title, grid, cmap) in zip(axes[0], panels, strict=True):
        im = ax.imshow(grid, origin="lower", extent=extent, aspect="auto", cmap=cmap,
                       **({"vmin": 0, "vmax": 1} if grid is success else {}))
        fig.colorbar(im, ax=ax)
        ax.scatter(means[:, 1], means[:, 0], c="k", marker="o", s=30, label="training mode means")
        for (name, z), m in zip(marks.items(), ("s", "*"), strict=False):
            ax.scatter([z[1]], [z[0]], c="w", edgecolors="k", marker=m, s=120, label=name)
        ax.set(title=title, xlabel="z[1]", ylabel="z[0]", xlim=xlim, ylim=ylim)
    axes[0][0].legend(loc="best", fontsize=7)
    fig.suptitle(f"{args.env} scene {args.scene}: {args.run}", fontsize=8)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"figure: {args.out}")


if __name__ == "__main__":
    main()
