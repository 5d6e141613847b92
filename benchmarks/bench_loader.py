"""LeRobotDataset loading with single-column delta queries (``lerobot_pdp.column_views``) next to LeRobot
0.6.1's own whole-row queries, side by side in one run.

For each dataset: the same ``LeRobotDataset`` with PDP's training windows (``delta_timestamps`` resolved by
LeRobot from a ``PDPConfig``, as ``lerobot-train`` does: 2 observation frames, 16 actions), once answering
its delta queries through the column views and once the way LeRobot 0.6.1 does. Two timings each:

- ``item``: ``dataset[i]`` in this process, over the same random indices;
- ``loader``: batches per second from a ``torch`` DataLoader with ``--workers`` spawned workers (as
  ``lerobot-train``: spawn context, persistent workers, shuffled), after one warm-up batch.

Datasets: ``--dataset PATH`` (any LeRobotDataset v3 folder), or by default the benchmark's scene-0 datasets
of ``--envs`` generated into ``--data`` (reused when present). One JSON line per (dataset, reader, timing),
then one ratio line per (dataset, timing).

    .venv/bin/python benchmarks/bench_loader.py [--envs reach-around pick-place] [--items 400]
        [--batches 30] [--batch 64] [--workers 2] [--dataset PATH ...]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import random
import sys
import tempfile
import time
import warnings
from pathlib import Path

import torch


def _dataset(root: Path, views: bool):
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata

    from lerobot_pdp import PDPConfig

    meta = LeRobotDatasetMetadata("local/bench", root=root)
    deltas = resolve_delta_timestamps(PDPConfig(), meta)
    ds = LeRobotDataset("local/bench", root=root, delta_timestamps=deltas)
    if not views:  # LeRobot's own method (the class attribute) answers again
        ds.reader.__dict__.pop("_query_hf_dataset", None)
    return ds


def _time_items(ds, indices: list[int]) -> float:
    ds[indices[0]]
    t = time.perf_counter()
    for i in indices:
        ds[i]
    return (time.perf_counter() - t) / len(indices)


def _time_loader(ds, batches: int, batch: int, workers: int) -> float:
    g = torch.Generator().manual_seed(0)
    loader = torch.utils.data.DataLoader(ds, batch_size=batch, shuffle=True, generator=g, num_workers=workers,
                                         multiprocessing_context="spawn" if workers else None,
                                         persistent_workers=workers > 0, prefetch_factor=4 if workers else None)
    it = iter(loader)
    next(it)  # workers started and warm
    t = time.perf_counter()
    for _ in range(batches):
        next(it)
    return batches / (time.perf_counter() - t)


def main(argv: list[str] | None = None) -> int:
    warnings.filterwarnings("ignore")
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--envs", nargs="*", default=["reach-around", "pick-place"])
    p.add_argument("--dataset", nargs="*", type=Path, default=[], help="LeRobotDataset folders (replace --envs)")
    p.add_argument("--data", type=Path, default=Path(tempfile.gettempdir()) / "pdp-bench-loader",
                   help="where the envs' datasets are generated (reused when present)")
    p.add_argument("--items", type=int, default=400)
    p.add_argument("--batches", type=int, default=30)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--workers", type=int, default=2)
    args = p.parse_args(argv)
    torch.set_num_threads(1)

    import lerobot

    from lerobot_pdp import column_views
    from lerobot_pdp.benchmark.data import ensure_dataset
    from lerobot_pdp.benchmark.machine import cpu_model
    from lerobot_pdp.benchmark.settings import SETTINGS
    from lerobot_pdp.envs import get_suite_env

    if not column_views.install():
        print(f"column views are off here (LeRobot {lerobot.__version__}, {column_views.ENV_VAR}="
              f"{os.environ.get(column_views.ENV_VAR)}): nothing to compare", file=sys.stderr)
        return 1
    roots = list(args.dataset)
    missing = [str(r) for r in roots if not (r / "meta" / "info.json").is_file()]
    if missing:
        p.error(f"not a LeRobotDataset folder (no meta/info.json): {', '.join(missing)}")
    for name in [] if args.dataset else args.envs:
        suite = get_suite_env(name)
        roots.append(ensure_dataset(suite, args.data / suite.scene_key, SETTINGS[suite.name][0]))

    common = {"torch_threads": 1, "workers": args.workers, "batch": args.batch, "lerobot": lerobot.__version__,
              "machine": platform.machine(), "cpu": cpu_model(), "cpus": os.cpu_count()}
    for root in roots:
        rows = {}
        for views in (True, False):
            ds = _dataset(root, views)
            indices = random.Random(0).sample(range(len(ds)), min(args.items, len(ds)))
            reader = "column_views" if views else "lerobot_whole_rows"
            rows[reader, "item"] = _time_items(ds, indices) * 1e3
            print(json.dumps({"dataset": root.name, "frames": len(ds), "reader": reader, "timing": "item",
                              "ms_per_item": round(rows[reader, "item"], 3), **common}), flush=True)
            rows[reader, "loader"] = _time_loader(ds, args.batches, args.batch, args.workers)
            print(json.dumps({"dataset": root.name, "reader": reader, "timing": "loader",
                              "batches_per_s": round(rows[reader, "loader"], 2), **common}), flush=True)
        print(json.dumps({"dataset": root.name, "ratio": "item time, whole rows / column views",
                          "value": round(rows["lerobot_whole_rows", "item"] / rows["column_views", "item"], 2)}))
        print(json.dumps({"dataset": root.name, "ratio": "loader batches/s, column views / whole rows",
                          "value": round(rows["column_views", "loader"] / rows["lerobot_whole_rows", "loader"], 2)}),
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
