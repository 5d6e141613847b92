"""Can a latent *sequence* reach a route that no single latent holds? One z per executed chunk, in time.

The benchmark fits one z (one per gripper phase) to a scene's demonstration. This fits one z per executed
chunk instead (the demonstration cut every ``n_action_steps`` frames, each piece's windows fitting its own z,
all starting from the benchmark's fitted latent of that piece's phase), then rolls out playing them in
order, chunk j of the rollout under z_j (the last one repeats), in the unchanged scene with the protocol's
rollout seeds: what DP's per-chunk noise adaptation does with its noise. One JSON line per scene, beside the
benchmark's single-latent success from ``eval.json``:

    python scripts/diagnostics/chunk_latents.py runs/kitchen_val/runs/pdp/seed100 --env kitchen-microwave \\
        --scene val3 --rollouts 20
"""

from __future__ import annotations

import argparse
import json
import os

import torch

os.environ.setdefault("HF_HUB_OFFLINE", "1")


class ChunkClock:
    """Stands in for the policy's gripper :class:`~lerobot_pdp.phases.PhaseTracker`: the "phase" of the
    next chunk is the number of chunks generated since reset (the policy asks once per chunk)."""

    def __init__(self) -> None:
        self.count = 0

    def reset(self) -> None:
        self.count = 0

    def phases(self, batch_size: int, device) -> torch.Tensor:
        out = torch.full((batch_size,), self.count, dtype=torch.long, device=device)
        self.count += 1
        return out

    def update(self, *args, **kwargs) -> bool:  # gripper events no longer switch latents
        return False


def main() -> None:
    from run_args import add_run_args, eval_record, scene_demo

    from lerobot_pdp.benchmark.rollouts import run_rollouts
    from lerobot_pdp.benchmark.settings import scene_seed_offset
    from lerobot_pdp.benchmark.training import load_run
    from lerobot_pdp.envs.suite import get_suite_env

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_run_args(ap)
    ap.add_argument("--rollouts", type=int, default=20)
    ap.add_argument("--steps", type=int, default=None, help="fitting steps (default: the checkpoint's)")
    ap.add_argument("--lam", type=float, default=None, help="weight of lambda |z|^2 (default: the checkpoint's)")
    args = ap.parse_args()
    if args.rollouts < 1:
        ap.error(f"--rollouts must be >= 1, got {args.rollouts}")
    meta = eval_record(ap, args.run, "its seed and fitted latents are read from there")
    entry = meta["scenes"].get(str(args.scene))
    if entry is None or entry.get("z") is None:
        ap.error(f"{args.run}/eval.json has no fitted latent for scene {args.scene}")
    suite = get_suite_env(args.env)
    seed = meta["seed"]
    policy, pre, post = load_run(args.run)
    policy.eval()
    demo = scene_demo(ap, suite, args.run, args.scene)

    n_a, T = policy.config.n_action_steps, len(demo["action"])
    chunks = [(a, min(a + n_a, T)) for a in range(0, T, n_a)]
    phases = policy.demo_windows(demo).segment  # the benchmark's phase of every frame
    z_single = torch.tensor(entry["z"], dtype=torch.float32).reshape(-1, policy.config.latent_dim)
    init = z_single[phases[[a for a, _ in chunks]]]
    res = policy.fit_latent(demo, steps=args.steps, lam=args.lam, init=init, segments=chunks, seed=seed)
    tracker, policy.phases = policy.phases, ChunkClock()
    try:
        batch = run_rollouts(suite, args.scene, policy, pre, post, args.rollouts,
                             seed * 10_000 + scene_seed_offset(args.scene))
    finally:
        policy.phases = tracker
        policy.set_latent(None)
    print(json.dumps({"scene": str(args.scene), "chunks": len(chunks), "single latent success": entry["success"],
                      "chunk latents success": batch.success_rate, "collision": batch.collision_rate,
                      "fit_error_ratio": None if res.error_ratio is None else round(res.error_ratio, 2),
                      "z move from the single fit": round(float((res.z - init).norm(dim=1).mean()), 3),
                      "rollouts": args.rollouts}), flush=True)


if __name__ == "__main__":
    main()
