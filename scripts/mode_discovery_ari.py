"""How well ``policy.discover_modes()`` recovers the demonstrated modes of a benchmark dataset, labels hidden.

For each env: the scene-0 benchmark dataset (generated, or given with ``--dataset``), PDP trained on it by the
benchmark's own ``lerobot-train`` command (``benchmark.training.train_method``; PDP never reads mode labels
while training a continuous latent), then ``discover_modes()`` in both spaces: the behavior traces (the
default; HDBSCAN finds k) and the latents (k by silhouette score), each also with k = the number of modes,
compared with the dataset's mode labels by the adjusted Rand index (sklearn). One JSON line per env on
stdout; the checkpoint stays in ``--out/<env>/run``.

    .venv/bin/python scripts/mode_discovery_ari.py --env reach-around avoiding pick-place kitchen-microwave \
        --out outputs/ari [--steps 1500] [--episodes-per-mode 10] [--device cuda] [--dataset ENV=DIR ...]
        [--seed 0] [--data-seed 0] [--max-k 12 0]   # latents: 0 = discover_modes' default bound
        [--run ENV=RUN_DIR --dataset ENV=DIR]       # a finished benchmark run instead of training
        [--no-train]                                # traces only: clustering them reads no weight
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def measure(env: str, out: Path, steps: int | None, episodes_per_mode: int | None, device: str,
            dataset: Path | None, seed: int = 0, data_seed: int = 0, max_k: list[int | None] | None = None,
            run: Path | None = None, train: bool = True) -> dict:
    from dataclasses import replace

    from sklearn.metrics import adjusted_rand_score

    from lerobot_pdp import PDPPolicy
    from lerobot_pdp.benchmark.data import ensure_dataset
    from lerobot_pdp.benchmark.settings import SETTINGS, methods_for
    from lerobot_pdp.benchmark.training import train_method
    from lerobot_pdp.envs import get_suite_env
    from lerobot_pdp.episodes import parse_task_mode, read_episodes

    suite = get_suite_env(env)
    full, quick = SETTINGS[suite.name]
    settings = replace(quick, episodes_per_mode=episodes_per_mode or full.episodes_per_mode)
    steps = steps or quick.steps
    root = dataset or ensure_dataset(suite, out / env, settings, seed=data_seed)
    t0 = time.time()
    if not train:  # the policy built from the dataset as lerobot-train builds it, never trained
        import draccus
        from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
        from lerobot.policies.factory import make_policy

        from lerobot_pdp import PDPConfig

        args = ["--" + a.removeprefix("--policy.") for a in methods_for(suite)["pdp"].overrides]
        cfg = draccus.parse(PDPConfig, args=[*args, f"--device={device}"])
        ckpt = None
        steps = seed = None
    elif run is None:
        ckpt = train_method(methods_for(suite)["pdp"], root, out / env / "run", seed, settings, steps, device)
    else:  # a finished benchmark run, trained on `root`: its own steps and seed
        ckpt = run / "pretrained_model"
        steps = seed = None
    train_s = time.time() - t0 if run is None and train else None
    policy = (PDPPolicy.from_pretrained(ckpt) if ckpt is not None
              else make_policy(cfg, ds_meta=LeRobotDatasetMetadata(f"local/{root.name}", root=root)))
    episodes = read_episodes(root, [], None)
    truth = {ep: item["mode"] if "mode" in item else parse_task_mode(item["task"]) for ep, item in episodes.items()}
    row = {"env": env, "episodes": len(truth), "modes": len(set(truth.values())), "steps": steps,
           "episodes_per_mode": settings.episodes_per_mode, "seed": seed, "data_seed": data_seed if dataset is None else None,
           "device": device, "train_s": None if train_s is None else round(train_s, 1),
           **({"run": run.name} if run else {})}
    k_true = len(set(truth.values()))
    cases = [("traces_auto", "traces", None, None), ("traces_k_true", "traces", k_true, None)]
    if train:  # an untrained encoder's latents mean nothing
        cases += [(f"latents_auto_max{m}" if m else "latents_auto", "latents", None, m) for m in (max_k or [None])]
        cases.append(("latents_k_true", "latents", k_true, None))
    for name, space, k, cap in cases:
        found = policy.discover_modes(k=k, max_k=cap, space=space)
        eps = sorted(found.labels)
        row[f"ari_{name}"] = round(float(adjusted_rand_score([truth[e] for e in eps],
                                                             [found.labels[e] for e in eps])), 4)
        row[f"k_{name}"] = found.k
        if space == "traces" and k is None:
            row["outliers_traces_auto"] = len(found.outliers)
    if not train:
        return row
    # where each demonstrated mode lies on the latent map: per mode, the range of its episodes' latents
    # (phases concatenated) along each coordinate, to see which modes neighbour
    import numpy as np
    import torch

    from lerobot_pdp.modes import episode_features

    with torch.no_grad():
        z = policy.behavior_latents().cpu().numpy()
    eps, feats = episode_features(z, policy.model.bank.episode.cpu().numpy(), policy.behavior_phase().cpu().numpy())
    modes = np.array([truth[int(e)] for e in eps])
    row["latent_range"] = {str(m): [[round(float(lo), 2), round(float(hi), 2)] for lo, hi in
                                    zip(feats[modes == m].min(0), feats[modes == m].max(0), strict=True)]
                           for m in sorted(set(modes.tolist()))}
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", nargs="+", required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=None, help="training steps (default: the env's quick budget)")
    ap.add_argument("--episodes-per-mode", type=int, default=None,
                    help="dataset size (default: the env's full benchmark dataset)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--dataset", nargs="*", default=[], help="ENV=DIR: use this dataset instead of generating one")
    ap.add_argument("--run", nargs="*", default=[],
                    help="ENV=RUN_DIR: a finished benchmark run (its pretrained_model) trained on --dataset "
                         "ENV=DIR, measured without training")
    ap.add_argument("--seed", type=int, default=0, help="training seed")
    ap.add_argument("--data-seed", type=int, default=0, help="seed of the generated dataset's demonstrations")
    ap.add_argument("--max-k", type=int, nargs="*", default=None,
                    help="discover_modes upper bounds to compare (default: its default only)")
    ap.add_argument("--no-train", action="store_true",
                    help="measure the traces' clustering only, on a policy built from the dataset without training "
                    "(it reads no weight); no --run")
    args = ap.parse_args(argv)
    given = dict(item.split("=", 1) for item in args.dataset)
    runs = dict(item.split("=", 1) for item in args.run)
    if args.no_train and runs:
        ap.error("--no-train measures an untrained policy: drop --run")
    if set(runs) - set(given):
        ap.error(f"--run needs the dataset it was trained on: --dataset {sorted(set(runs) - set(given))[0]}=DIR")
    for env in args.env:
        row = measure(env, args.out, args.steps, args.episodes_per_mode, args.device,
                      Path(given[env]) if env in given else None, args.seed, args.data_seed,
                      [m or None for m in args.max_k] if args.max_k else None,
                      Path(runs[env]) if env in runs else None, not args.no_train)
        print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
