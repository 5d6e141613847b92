"""What the taught modes' rehearsal costs a ``lerobot-train`` step: the same step with and without it, side by side.

A taught checkpoint is loaded to train on as ``lerobot-train --policy.path`` loads it (its training dataset's
metadata given, so its taught modes are kept and rehearsed: ``lerobot_pdp/taught_rehearsal.py``), and the training
step (forward, backward, Adam, as LeRobot's loop runs it, on batches from LeRobot's dataset and preprocessor) is timed
with the rehearsal on and off (``policy.model.rehearsal`` set aside), alternating in rounds so that a machine's drift
falls on both alike. One JSON object, printed and written to ``--out``: the median step of each and their ratio.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_taught_rehearsal.py TAUGHT_CHECKPOINT --data DATASET \
        [--batch-size 64] [--rounds 10] [--steps 10] [--out bench.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoint", type=Path, help="a taught PDP checkpoint (pretrained_model folder)")
    ap.add_argument("--data", type=Path, required=True, help="its training dataset")
    ap.add_argument("--batch-size", type=int, default=64)
    ap.add_argument("--rounds", type=int, default=10, help="alternations of the two")
    ap.add_argument("--steps", type=int, default=10, help="timed steps per round and side")
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON object here")
    args = ap.parse_args()

    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy, make_pre_post_processors
    from lerobot.utils.constants import ACTION

    from lerobot_pdp import PDPConfig

    meta = LeRobotDatasetMetadata("local/bench", root=args.data)
    cfg = PDPConfig.from_pretrained(args.checkpoint)
    cfg.pretrained_path = args.checkpoint
    policy = make_policy(cfg, ds_meta=meta)
    rehearsal = policy.model.rehearsal
    if rehearsal is None:
        raise SystemExit(f"{args.checkpoint} has no taught mode to rehearse over {args.data}")
    fps = meta.fps
    ds = LeRobotDataset("local/bench", root=args.data, video_backend="pyav", delta_timestamps={
        **{k: [i / fps for i in cfg.observation_delta_indices] for k in cfg.input_features},
        ACTION: [i / fps for i in cfg.action_delta_indices]})
    pre, _ = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    g = torch.Generator().manual_seed(0)
    batches = [pre(torch.utils.data.default_collate([ds[int(i)] for i in torch.randint(0, len(ds), (args.batch_size,),
                                                                                          generator=g)]))
               for _ in range(4)]
    policy.train()
    opt = torch.optim.Adam(policy.get_optim_params())

    def step(batch) -> float:
        t0 = time.perf_counter()
        loss, _ = policy.forward(batch)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), cfg.optimizer_grad_clip_norm)
        opt.step()
        return time.perf_counter() - t0

    times: dict[str, list[float]] = {"rehearsed": [], "not rehearsed": []}
    for i in range(3):  # warm-up, both ways
        policy.model.rehearsal = rehearsal if i % 2 else None
        step(batches[i % len(batches)])
    for r in range(args.rounds):
        for side in ("rehearsed", "not rehearsed") if r % 2 == 0 else ("not rehearsed", "rehearsed"):
            policy.model.rehearsal = rehearsal if side == "rehearsed" else None
            times[side] += [step(batches[k % len(batches)]) for k in range(args.steps)]
    med = {k: statistics.median(v) for k, v in times.items()}
    record = json.dumps({
        "checkpoint": str(args.checkpoint), "batch_size": args.batch_size,
        "taught_windows_per_batch": rehearsal.windows_for(args.batch_size), "share": rehearsal.share,
        "threads": torch.get_num_threads(), "steps_per_side": len(times["rehearsed"]),
        "median_step_s": {k: round(v, 4) for k, v in med.items()},
        "ratio": round(med["rehearsed"] / med["not rehearsed"], 3)})
    print(record)
    if args.out is not None:
        args.out.write_text(record + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
