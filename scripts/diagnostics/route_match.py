"""Do the latents that succeed follow the demonstration? Closed-loop route match against the fitting objective.

For a benchmark run with an unsegmented latent and a shifted scene, evaluates a set of candidate latents: the
latent the benchmark fitted (``eval.json``), the encoder's latent of the demonstration (the warm start), every
training mode's mean latent, and any ``--z``. For each candidate it reports

- ``L_fit``: the fitting objective on the demonstration (every window, ``--noise-draws`` (k, eps) draws each,
  the same draws for every candidate), i.e. what a fit compares, with the demonstration's own states as the
  observations (teacher forcing);
- with ``--rollouts N``: success and collision rates in the scene (the protocol's rollout seeds) and
  ``route_dtw``, the hard DTW between each rollout's behavior trace and the demonstration's (both resampled to
  the checkpoint's trace length, per trace step; raw positions), i.e. how closely the policy under z follows
  the demonstration in closed loop, and ``steps``, the rollouts' mean length. A rollout that ends early (a
  collision) is a partial route stretched over the whole demonstration, so its DTW is large however well it
  started: read ``route_dtw`` with ``steps``, ``off_route`` (the mean distance from a rollout's positions to
  the nearest point of the demonstration's path: how far it strays while it lasts) and the picture.

Prints one JSON line per candidate and a summary line (the candidate each criterion would pick), and writes a
PNG: the traces of each candidate's rollouts next to the demonstration's, and success against both criteria.

    python scripts/diagnostics/route_match.py runs/kitchen_val/runs/pdp/seed100 --env kitchen-microwave \\
        --scene val3 --rollouts 10 --z 0.35,0.45 --out route_match_val3.png
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np
import torch

os.environ.setdefault("HF_HUB_OFFLINE", "1")


def _latent(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--z takes comma-separated numbers (e.g. 0.35,0.45), got {text!r}") from None


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
    from lerobot_pdp.soft_dtw import dtw

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_run_args(ap)
    ap.add_argument("--z", type=_latent, action="append", default=[], help="an extra candidate latent, e.g. 0.35,0.45")
    ap.add_argument("--rollouts", type=int, default=10, help="rollouts per candidate (0: L_fit only)")
    ap.add_argument("--noise-draws", type=int, default=32, help="(k, eps) draws per demonstration window for L_fit")
    ap.add_argument("--out", type=Path, default=Path("route_match.png"))
    args = ap.parse_args()
    if args.rollouts < 0 or args.noise_draws < 1:
        ap.error(f"--rollouts must be >= 0 and --noise-draws >= 1, got {args.rollouts} and {args.noise_draws}")

    policy, pre, post = load_run(args.run)
    cfg = policy.config
    if cfg.segment_gripper_dim is not None:
        ap.error(f"needs an unsegmented latent; {args.run} segments its behaviors on the gripper "
                 f"(segment_gripper_dim={cfg.segment_gripper_dim})")
    for z in args.z:
        if len(z) != cfg.latent_dim:
            ap.error(f"--z {z}: {args.run} has latent_dim={cfg.latent_dim}")
    meta = eval_record(ap, args.run, "its fitted latent is read from there")
    suite = get_suite_env(args.env)
    demo = scene_demo(ap, suite, args.run, args.scene)
    policy.eval()

    candidates = {"fitted": np.asarray(meta["scenes"][str(args.scene)]["z"], dtype=np.float32),
                  "warm start": policy.encode(demo).numpy()}
    candidates |= {f"mode {m}": z.numpy() for m, z in policy.mode_latents().items()}
    candidates |= {f"z={','.join(f'{v:g}' for v in z)}": np.asarray(z, dtype=np.float32) for z in args.z}

    # Raw positions (not the checkpoint's trace normalisation): the route in the scene is what is compared.
    def trace(states: np.ndarray) -> np.ndarray:
        return make_trace(states, None, cfg.trace_length, "none")

    demo_trace = trace(np.asarray(demo["observation.state"])[:, list(suite.trace_dims)])
    windows = policy.demo_windows(demo)
    den, sched = policy.model.denoiser, policy.model.noise_schedule
    den = FrozenDenoiser(den, sched.num_train_timesteps)  # weights frozen: built once
    idx = torch.arange(len(windows.segment))
    with torch.no_grad():
        obs = den.observations(windows.obs_cond)

    rows, traces = [], {}
    for name, z in candidates.items():
        zt = torch.as_tensor(z, dtype=torch.float32)
        with torch.no_grad():
            loss = float(fit_loss(den, sched, windows, zt[None], idx, args.noise_draws, cfg.fit_lambda,
                                  torch.Generator().manual_seed(0), obs))
        row = {"candidate": name, "z": [round(float(v), 3) for v in z], "L_fit": round(loss, 5)}
        if args.rollouts:
            policy.set_latent(zt)
            batch = run_rollouts(suite, args.scene, policy, pre, post, args.rollouts,
                                 meta["seed"] * 10_000 + scene_seed_offset(args.scene))
            traces[name] = [trace(r.trace) for r in batch.results]
            steps = float(np.mean([len(r.trace) - 1 for r in batch.results]))
            demo_path = np.asarray(demo["observation.state"])[:, list(suite.trace_dims)]
            off = [np.linalg.norm(r.trace[:, None] - demo_path[None], axis=-1).min(1).mean() for r in batch.results]
            d = [dtw(t, demo_trace) / cfg.trace_length for t in traces[name]]
            row |= {"success": batch.success_rate, "collision": batch.collision_rate,
                    "route_dtw": round(float(np.mean(d)), 5), "route_dtw_median": round(float(np.median(d)), 5), "steps": round(steps, 1),
                    "off_route": round(float(np.mean(off)), 4)}
        rows.append(row)
        print(json.dumps(row), flush=True)
    policy.set_latent(None)

    summary = {"scene": str(args.scene), "by_L_fit": min(rows, key=lambda r: r["L_fit"])["candidate"]}
    if args.rollouts:
        best = min(rows, key=lambda r: r["route_dtw"])
        summary |= {"by_route_dtw": best["candidate"], "its_success": best["success"],
                    "best_success": max(r["success"] for r in rows)}
    print(json.dumps(summary))
    if not args.rollouts:
        return

    # Traces of the named candidates, each criterion's pick and the most successful mode (ten colours at most).
    by_success = max((r for r in rows if r["candidate"].startswith("mode")), key=lambda r: r["success"], default=None)
    shown = list(dict.fromkeys([*(n for n in traces if not n.startswith("mode")), summary["by_L_fit"],
                                summary["by_route_dtw"], *([by_success["candidate"]] if by_success else [])]))[:10]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
    for c, name in zip(plt.cm.tab10(np.arange(10)), shown, strict=False):
        for i, t in enumerate(traces[name]):
            axes[0].plot(t[:, 0], t[:, 1], color=c, alpha=0.5, lw=1, label=name if i == 0 else None)
    axes[0].plot(demo_trace[:, 0], demo_trace[:, 1], "k", lw=3, label="demonstration")
    axes[0].set(title="rollout traces (first two trace dims)", xlabel="trace dim 0", ylabel="trace dim 1")
    axes[0].legend(fontsize=6, loc="best")
    for ax, key, label in ((axes[1], "route_dtw", "closed-loop DTW to the demonstration (per trace step)"),
                           (axes[2], "L_fit", "L_fit on the demonstration (teacher forcing)")):
        for r in rows:
            ax.scatter(r[key], r["success"], s=40)
            ax.annotate(r["candidate"], (r[key], r["success"]), fontsize=7)
        ax.set(xlabel=label, ylabel=f"success ({args.rollouts} rollouts)", ylim=(-0.05, 1.05))
    fig.suptitle(f"{args.env} scene {args.scene}: {args.run}", fontsize=8)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"figure: {args.out}")


if __name__ == "__main__":
    main()
